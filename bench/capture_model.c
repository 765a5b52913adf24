/* The NUCLEO firmware's capture.c and integrity.c on the PC against a timing model of TIM2, TIM8, ADC1 and DMA1 (bench/capture_integrity.py builds it). */
#include <stdio.h>
#include <stdlib.h>

#include "armv7m.h"    /* bench's stand-in: no-op barriers, counted invalidations */
#include "h743_regs.h" /* the firmware's, with peripherals turned into the variables below */
#include "nucleo.h"

struct rcc fake_rcc;
struct pwr fake_pwr;
struct syscfg fake_syscfg;
struct gpio fake_gpioa, fake_gpiob, fake_gpiod, fake_gpioe;
struct usart fake_usart3;
struct crc fake_crc_unit;
struct dma fake_dma1;
struct adc fake_adc1;
struct adc_common fake_adc12_common;
struct tim fake_tim2, fake_tim8;
volatile uint32_t fake_dmamux[16];
volatile uint32_t fake_FLASH_ACR, fake_DBGMCU_IDCODE, fake_AXI_TARG7_FN_MOD;
int fake_inval_calls;
uint32_t fake_inval_bytes;
struct clocks clocks = {.rev_v = true, .sysclk_hz = 480000000u, .hclk_hz = 240000000u,
                        .pclk_hz = 120000000u, .timclk_hz = 240000000u, .adc_hz = 36000000u};

bool adc_init(void) { return true; }
void adc_start(void) {}
bool adc_stop(void) { return true; }
void wait_use_tim2(uint32_t hz) { (void)hz; }
bool wait_bits(const volatile uint32_t *r, uint32_t m, uint32_t w, uint32_t us)
{
    (void)r, (void)m, (void)w, (void)us;
    return true;
}

#include "capture.c"
#include "integrity.c"

/* the hardware: sample k (timer index) reaches ring[] lat(k) ticks after its trigger at
 * t0 + (k + 1) T; `missed` triggers shift the data, a stall stops it at timer index stall_at;
 * model time is 64-bit (t0s: the last pacing start), TIM2 shows its low 32 bits */
static uint64_t t0s;
static uint32_t L, JIT, t0_seen, missed, filled, stall_at = UINT32_MAX;

static uint32_t lat(uint32_t k)
{
    return L + (JIT ? (k * 2654435761u >> 7) % (JIT + 1u) : 0u);
}

static void hardware(uint64_t now)
{
    if (cap.k0 == 0 && cap.t0 != t0_seen) { /* pacing (re)started at TIM2 = cap.t0 */
        t0_seen = cap.t0;
        t0s = now - (uint32_t)((uint32_t)now - cap.t0);
        missed = filled = 0;
        stall_at = UINT32_MAX;
    }
    for (uint32_t k = filled + missed; k < stall_at; k = filled + missed) {
        if (now - t0s < (uint64_t)(k + 1u) * cap.T + lat(k))
            break;
        ring[filled++ % RING] = (uint16_t)k;
    }
    fake_dma1.S[0].NDTR = RING - filled % RING;
    fake_tim2.CNT = (uint32_t)now;
    fake_adc1.ISR = 0;
}

int main(int argc, char **argv)
{
    if (argc != 6) {
        fprintf(stderr, "usage: capture_model LATENCY JITTER POLL FAULT SEED\n");
        return 2;
    }
    L = (uint32_t)atoi(argv[1]);   /* ticks at 240 MHz */
    JIT = (uint32_t)atoi(argv[2]); /* peak-to-peak ticks */
    int poll = atoi(argv[3]);      /* largest gap between polls, ticks */
    int fault = atoi(argv[4]);     /* 0 none, 1 / 2 missed triggers, 3 stall */
    srand((unsigned)atoi(argv[5]));
    uint64_t now = fake_tim2.CNT = 123456789u;
    capture_init();
    struct dmdsm_set_config cfg = {1024, 1, 1, 64, 0, 0, 0, 1000};
    int good = 0, faults = 0, injected = 0, wrong = 0, overruns = 0, skipped = 0;
    for (int shot = 0; shot < 2000; shot++) {
        if (shot == 700)
            cfg.sample_rate_div = 3;
        if (shot == 1400)
            cfg = (struct dmdsm_set_config){8192, 1, 1, 8000, 0, 0, 0, 1000};
        capture_arm(&cfg);
        int inject = fault && shot % 10 == 3, at = rand() % 3000;
        uint32_t edge_at = 240000u + (uint32_t)(rand() % 100000), edge = 0;
        for (int i = 0; i < 50000000; i++) {
            now += 1u + (uint32_t)(rand() % poll);
            hardware(now);
            if (inject && i == at) {
                inject = 0;
                injected++;
                if (fault < 3)
                    missed += (uint32_t)fault;
                else
                    stall_at = (uint32_t)((now - t0s) / cap.T);
            }
            if (!edge && (uint32_t)i * 25u >= edge_at) {
                edge = (uint32_t)now;
                fake_tim2.CCR1 = edge;
                TIM2_IRQHandler();
                if (!cap.edge) {
                    skipped++; /* too soon after a restart for the pre-trigger */
                    break;
                }
            }
            const uint16_t *s;
            uint32_t e;
            uint16_t ph;
            enum dmdsm_capture r;
            if (!capture_poll(&s, &e, &ph, &r))
                continue;
            if (r == DMDSM_CAPTURE_INTEGRITY) {
                faults++;
            } else if (r == DMDSM_CAPTURE_OVERRUN) {
                overruns++;
            } else {
                uint32_t k = (edge + ph - t0_seen) / cap.T - 1u; /* first sample after the edge */
                int ok = s[0] == (uint16_t)(k - cfg.pretrigger);
                for (uint32_t j = 1; j < cfg.n_samples; j++)
                    ok &= (uint16_t)(s[j] - s[0]) == j;
                ok ? good++ : wrong++;
            }
            break;
        }
    }
    printf("%d %d %d %d %d %d %d %u\n", good, faults, injected, wrong, overruns, skipped,
           fake_inval_calls, fake_inval_bytes);
    return 0;
}

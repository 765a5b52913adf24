/* Shot capture: TIM8 paces ADC1 into a circular DMA ring; TIM2 latches the laser edge; no CPU in the sampling path. */
#include "armv7m.h"
#include "core.h"
#include "h743_regs.h"
#include "nucleo.h"

/*
 * TIM2 (32 bit, timer clock) runs free from capture_init on and is the device
 * clock. TIM8 is started by TIM2's enable (TRGO = enable, TIM8 in trigger mode
 * on ITR1) at TIM2 tick t0, so sample k is taken at TIM2 tick t0 + (k + 1) * T,
 * T = sample period in timer ticks. ADC1 converts on each TIM8 update and DMA1
 * stream 0 writes ring[k mod RING]. A (re)start of sampling holds TIM2 for the
 * one CNT read between clearing and setting CEN (a few ticks, interrupts off)
 * and never resets it: device time only moves forward.
 *
 * The photodiode edge on PA0 is captured by TIM2 CH1 in hardware (CCR1). Its
 * interrupt only does arithmetic: the first sample after the edge is
 * k = ceil((E - t0) / T) - 1 and the trigger phase is the time from E to that
 * sample, so pre-trigger samples come from the ring and the host can remove
 * the sub-sample start jitter. The main loop copies the burst out once the
 * timer says the ring holds it, if the DMA's position agrees (integrity.c).
 */
#define RING 16384u /* samples: twice the longest burst; a power of two */
/* Shortest sample period: one 16-bit conversion at 1.5-cycle sampling is 10 ADC cycles,
 * 277.8 ns at 36 MHz; 300 ns leaves 8 % for the trigger resynchronisation. T = 72 ticks at
 * 240 MHz (rev V), 60 at 200 MHz (rev Y): 3.333 MS/s on both. */
#define PERIOD_MIN_NS 300u
/* the motion-sync inputs' capture interrupts (X on CH2, A on CH3): always on */
#define SYNC_IE (TIM_DIER_CC2IE | TIM_DIER_CC3IE)

_Static_assert((RING & (RING - 1u)) == 0, "RING must be a power of two");
_Static_assert((RING * sizeof(uint16_t)) % DCACHE_LINE == 0, "ring is whole cache lines");

static uint16_t ring[RING] __attribute__((section(".dma_buffers"), aligned(32)));
static uint16_t burst[8192] __attribute__((aligned(32)));

static struct {
    bool adc_ok;       /* ADC1 calibrated and enabled at boot */
    uint32_t T;        /* sample period, timer ticks */
    uint32_t t0;       /* TIM2 tick of "sample -1": sample k at t0 + (k + 1) T */
    uint32_t k0;       /* sample index at t0 (advances when t0 is re-based) */
    struct integrity check; /* the DMA's position against the timer since t0 */
    bool suspect;           /* the check failed: the next burst is not good */
    struct dmdsm_set_config cfg;
    volatile int armed;
    volatile int edge;  /* an edge was latched and its burst is being collected */
    volatile uint32_t edge_ticks;
    volatile uint32_t start; /* absolute sample index of the burst's first sample */
    volatile uint16_t phase;
} cap;

uint32_t capture_now(void)
{
    return TIM2->CNT;
}

/* a tick difference with its top bit set is a time before t0 (differences stay < 2^31) */
static bool before_t0(uint32_t since)
{
    return since >= 0x80000000u;
}

/* sample period at sample_rate_div = 1 in timer ticks: ceil(timclk x 300 ns) */
static uint32_t base_period(void)
{
    return (uint32_t)(((uint64_t)clocks.timclk_hz * PERIOD_MIN_NS + 999999999u) / 1000000000u);
}

uint32_t capture_adc_rate_hz(void)
{
    return clocks.timclk_hz / base_period();
}

/* (re)start sampling with period T ticks, ring[0] first */
static void pacing_start(uint32_t T)
{
    TIM8->CR1 = 0; /* no more ADC triggers */
    (void)adc_stop(); /* should it not stop, the integrity check catches what follows */
    struct dma_stream *s = &DMA1->S[0];
    s->CR = 0;
    (void)wait_bits(&s->CR, DMA_CR_EN, 0, 1000u); /* ends the current transfer: < 1 us */
    (void)ADC1->DR; /* no conversion left pending for the new ring (clears EOC) */
    DMA1->LIFCR = DMA_LIFCR_S0;
    s->PAR = (uint32_t)(uintptr_t)&ADC1->DR;
    s->M0AR = (uint32_t)(uintptr_t)ring;
    s->NDTR = RING;
    s->CR = DMA_CR_CIRC | DMA_CR_MINC | DMA_CR_PSIZE_16 | DMA_CR_MSIZE_16 | DMA_CR_PL_HIGH |
            DMA_CR_EN;
    adc_start(); /* waits for TIM8 triggers */
    TIM8->ARR = T - 1u;
    TIM8->CNT = 0;
    irq_disable();
    TIM2->CR1 = 0;          /* CNT holds its value... */
    uint32_t t0 = TIM2->CNT;
    TIM2->CR1 = TIM_CR1_CEN; /* ...and counts on: TRGO (enable) starts TIM8 on this tick */
    cap.T = T;
    cap.t0 = t0;
    cap.k0 = 0;
    cap.suspect = false;
    integrity_reset(&cap.check, clocks.timclk_hz);
    irq_enable();
}

/* TIM2 runs from here on whatever else fails: it is the device clock */
void capture_init(void)
{
    RCC->AHB4ENR |= RCC_AHB4ENR_GPIOAEN | RCC_AHB4ENR_GPIOBEN;
    RCC->AHB1ENR |= RCC_AHB1ENR_DMA1EN;
    RCC->APB1LENR |= RCC_APB1LENR_TIM2EN;
    RCC->APB2ENR |= RCC_APB2ENR_TIM8EN;
    (void)RCC->APB2ENR; /* read back: the clocks are on before the first access */
    /* PA0 = TIM2_CH1 (AF1), PA6 analog */
    GPIOA->MODER = (GPIOA->MODER & ~3u) | 2u;
    GPIOA->AFR[0] = (GPIOA->AFR[0] & ~0xFu) | 1u;
    GPIOA->MODER |= 3u << (2 * 6);
    /* PB3 = TIM2_CH2 (AF1): the stage's X STEP line; PB10 = TIM2_CH3 (AF1): its A STEP line */
    GPIOB->MODER = (GPIOB->MODER & ~((3u << (2 * 3)) | (3u << (2 * 10)))) |
                   (2u << (2 * 3)) | (2u << (2 * 10));
    GPIOB->AFR[0] = (GPIOB->AFR[0] & ~(0xFu << (4 * 3))) | (1u << (4 * 3));
    GPIOB->AFR[1] = (GPIOB->AFR[1] & ~(0xFu << (4 * 2))) | (1u << (4 * 2));

    /* TIM8: update every T ticks -> TRGO -> ADC; started by TIM2's TRGO (ITR1) */
    TIM8->PSC = 0;
    TIM8->CR2 = TIM_CR2_MMS_UPDATE;
    TIM8->SMCR = TIM_SMCR_TS_ITR1 | TIM_SMCR_SMS_TRIGGER;
    TIM8->EGR = TIM_EGR_UG; /* loads PSC before the ADC listens */
    /* TIM2: free-running 32-bit clock, CH1 input capture; TRGO on enable once pacing runs */
    TIM2->PSC = 0;
    TIM2->ARR = 0xFFFFFFFFu;
    TIM2->CCMR1 = TIM_CCMR1_CC1S_TI1 | (2u << TIM_CCMR1_IC1F_SHIFT) | /* 4-sample filters */
                  TIM_CCMR1_CC2S_TI2 | (2u << TIM_CCMR1_IC2F_SHIFT);
    TIM2->CCMR2 = TIM_CCMR2_CC3S_TI3 | (2u << TIM_CCMR2_IC3F_SHIFT);
    /* CH2, CH3: rising edges (a step) */
    TIM2->CCER = TIM_CCER_CC1E | TIM_CCER_CC2E | TIM_CCER_CC3E;
    TIM2->SR = ~(TIM_SR_CC2IF | TIM_SR_CC2OF | TIM_SR_CC3IF | TIM_SR_CC3OF);
    TIM2->DIER = SYNC_IE;
    TIM2->CR1 = TIM_CR1_CEN;
    TIM2->CR2 = TIM_CR2_MMS_ENABLE;
    wait_use_tim2(clocks.timclk_hz);
    nvic_enable(IRQ_TIM2);

    cap.adc_ok = clocks.adc_hz != 0 && adc_init();
    if (cap.adc_ok)
        pacing_start(base_period());
}

bool capture_available(void)
{
    return cap.adc_ok;
}

void capture_arm(const struct dmdsm_set_config *cfg)
{
    if (!cap.adc_ok)
        return; /* the core NAKs arm first (dmdsm_board_info.capture_error) */
    uint32_t T = base_period() * cfg->sample_rate_div;
    if (T != cap.T || cap.suspect)
        pacing_start(T); /* suspect: the check failed while nothing was captured */
    cap.cfg = *cfg;
    TIM2->CCER = TIM_CCER_CC1E | TIM_CCER_CC2E | TIM_CCER_CC3E |
                 (cfg->trigger_edge ? TIM_CCER_CC1P : 0u);
    TIM2->SR = ~(TIM_SR_CC1IF | TIM_SR_CC1OF);
    cap.edge = 0;
    cap.armed = 1;
    TIM2->DIER = TIM_DIER_CC1IE | SYNC_IE;
}

void capture_disarm(void)
{
    TIM2->DIER = SYNC_IE;
    cap.armed = 0;
    cap.edge = 0;
}

/* the laser edge: hardware latched CCR1; compute where the burst lies in the ring */
static struct dmdsm_core *sync_core;

void capture_sync_to(struct dmdsm_core *core)
{
    sync_core = core;
}

/* TIM2: a step on CH2 or CH3 (motion sync: X, A) and/or the laser edge on CH1, each latched
 * in hardware */
void TIM2_IRQHandler(void)
{
    uint32_t sr = TIM2->SR;
    if (sr & TIM_SR_CC2IF) {
        uint32_t s = TIM2->CCR2; /* reading CCR2 clears CC2IF */
        if (sync_core != NULL)
            dmdsm_core_sync_edge(sync_core, DMDSM_SYNC_INPUT_X, s);
    }
    if (sr & TIM_SR_CC3IF) {
        uint32_t s = TIM2->CCR3; /* reading CCR3 clears CC3IF */
        if (sync_core != NULL)
            dmdsm_core_sync_edge(sync_core, DMDSM_SYNC_INPUT_A, s);
    }
    if (!(sr & TIM_SR_CC1IF))
        return;
    uint32_t e = TIM2->CCR1; /* reading CCR1 clears CC1IF */
    if (!cap.armed) {
        TIM2->DIER = SYNC_IE;
        return;
    }
    uint32_t since = e - cap.t0;
    uint32_t k = since / cap.T; /* samples 0..k-1 were taken at or before the edge */
    if (before_t0(since) || cap.k0 + k < cap.cfg.pretrigger)
        return; /* sampling (re)started too recently for the pre-trigger: next edge */
    TIM2->DIER = SYNC_IE; /* one edge per burst; re-armed by the core */
    uint32_t next_at = (k + 1u) * cap.T;
    cap.phase = (uint16_t)(next_at - since);
    cap.start = cap.k0 + k - cap.cfg.pretrigger;
    cap.edge_ticks = e;
    cap.armed = 0;
    cap.edge = 1;
}

/* drop the cache lines of ring[first % RING ...] for n samples: at most two segments */
static void invalidate_burst(uint32_t first, uint32_t n)
{
    uint32_t a = first % RING;
    uint32_t n1 = n < RING - a ? n : RING - a;
    dcache_invalidate(&ring[a], n1 * (uint32_t)sizeof ring[0]);
    if (n1 < n)
        dcache_invalidate(&ring[0], (n - n1) * (uint32_t)sizeof ring[0]);
}

/*
 * Called from the main loop. CNT, NDTR and CNT again are read back to back;
 * every call feeds the integrity check (integrity.c). A burst
 * is complete once the DMA has written its last sample; if the check failed
 * since pacing started it is reported as DMDSM_CAPTURE_INTEGRITY as soon as
 * its edge was seen, never copied, and pacing restarts so that later bursts
 * are right.
 */
int capture_poll(const uint16_t **samples, uint32_t *edge, uint16_t *phase,
                 enum dmdsm_capture *result)
{
    if (!cap.adc_ok)
        return 0;
    uint32_t c1 = TIM2->CNT;
    uint32_t ndtr = DMA1->S[0].NDTR;
    uint32_t c2 = TIM2->CNT; /* an interrupt in between only widens this poll's bounds */
    irq_disable(); /* t0, k0 and the edge's start index change together */
    uint32_t since = c1 - cap.t0;
    if (!cap.edge && since >= RING * cap.T && !before_t0(since)) {
        /* keep t0 recent so tick differences stay below 2^31; the ring index of
         * t0 + RING * T is the same as t0's (RING * T <= 2^14 * 72 * 1024 < 2^31) */
        cap.t0 += RING * cap.T;
        cap.k0 += RING;
        since -= RING * cap.T;
    }
    irq_enable();
    if (before_t0(since))
        return 0;
    uint32_t done = cap.k0 + since / cap.T; /* samples triggered so far */
    /* timer minus DMA sample count, -RING/2..RING/2 (the DMA may pass c1 before NDTR) */
    uint32_t lag_mod = (done - (RING - ndtr) % RING + RING / 2u) % RING;
    int32_t lag = (int32_t)lag_mod - (int32_t)(RING / 2u);
    uint32_t written = done - (uint32_t)lag; /* since pacing started */
    if (!integrity_observe(&cap.check, since % cap.T, lag, c2 - c1, written != 0, cap.T))
        cap.suspect = true;
    if (!cap.edge)
        return 0;
    uint32_t end = cap.start + cap.cfg.n_samples;
    if (!cap.suspect && (int32_t)(written - end) < 0)
        return 0; /* the DMA has not written the burst's last sample yet */
    *edge = cap.edge_ticks;
    *phase = cap.phase;
    *samples = burst;
    cap.edge = 0;
    if (cap.suspect) {
        *result = DMDSM_CAPTURE_INTEGRITY;
        pacing_start(cap.T);
        return 1;
    }
    bool lapped = (done - cap.start) > RING - 64u;
    invalidate_burst(cap.start, cap.cfg.n_samples);
    for (uint32_t i = 0; i < cap.cfg.n_samples; i++)
        burst[i] = ring[(cap.start + i) % RING];
    *result = lapped || (ADC1->ISR & ADC_ISR_OVR) ? DMDSM_CAPTURE_OVERRUN : DMDSM_CAPTURE_OK;
    ADC1->ISR = ADC_ISR_OVR;
    return 1;
}

/* QEMU mps2-an500 (Cortex-M7) board: the firmware core on the CMSDK UART with a test-pattern ADC. */
#include <string.h>

#include "armv7m.h"
#include "core.h"
#include "startup.h"

extern uint32_t _estack;

/*
 * What is emulated: the core, the protocol, the transmit queue and the clock
 * run exactly as on the NUCLEO. The "laser" fires every SHOT_PERIOD_US while
 * armed and the "ADC" returns a test pattern the host can check:
 *   sample[i] = (i + k) mod 4096, trigger phase = k mod 7,
 * where k counts edges since boot.
 */
#define SYSCLK_HZ 25000000u     /* AN500 SYSCLK */
#define SHOT_PERIOD_US 1000u    /* 1 kHz laser */
#define MAX_SAMPLES 8192u

/* CMSDK APB UART0 (QEMU hw/char/cmsdk-apb-uart.c) */
#define UART0 0x40004000u
#define UART_DATA REG32(UART0 + 0x00u)
#define UART_STATE REG32(UART0 + 0x04u)
#define UART_CTRL REG32(UART0 + 0x08u)
#define UART_BAUDDIV REG32(UART0 + 0x10u)
#define UART_STATE_TXFULL (1u << 0)
#define UART_STATE_RXFULL (1u << 1)

static struct dmdsm_core core;
static uint16_t adc_buf[MAX_SAMPLES];
static volatile uint32_t systick_wraps;
static const uint8_t *tx_ptr;
static size_t tx_left;
static struct {
    int armed;
    struct dmdsm_set_config cfg;
    uint32_t next_shot;
    uint32_t edges;
} trig;

void board_early_init(void) {}

void SysTick_Handler(void)
{
    systick_wraps++;
}

/* 32-bit tick counter at SYSCLK from SysTick (24-bit down-counter) and its wraps.
 * A wrap whose interrupt is still pending is counted here, or time would step back. */
static uint32_t now_ticks(void *ctx)
{
    (void)ctx;
    uint32_t w, v, pending;
    do {
        w = systick_wraps;
        v = SYST_CVR;
        pending = SCB_ICSR & SCB_ICSR_PENDSTSET;
    } while (w != systick_wraps);
    if (pending && v > 0x800000u)
        w++; /* the counter reloaded before we read it, the ISR has not run yet */
    return w * 0x1000000u + (0xFFFFFFu - v);
}

static void arm_capture(void *ctx, const struct dmdsm_set_config *cfg)
{
    (void)ctx;
    if (!trig.armed)
        trig.next_shot = now_ticks(NULL) + SHOT_PERIOD_US * (SYSCLK_HZ / 1000000u);
    trig.cfg = *cfg;
    trig.armed = 1;
}

static void disarm_capture(void *ctx)
{
    (void)ctx;
    trig.armed = 0;
}

static void tx_start(void *ctx, const uint8_t *p, size_t n)
{
    (void)ctx;
    tx_ptr = p;
    tx_left = n;
}

static bool tx_busy(void *ctx)
{
    (void)ctx;
    return tx_left != 0;
}

static const struct dmdsm_board_ops ops = {NULL, arm_capture, disarm_capture, now_ticks,
                                           tx_start, tx_busy, NULL};
static const struct dmdsm_board_info info = {"QEMU mps2-an500 test pattern", SYSCLK_HZ,
                                             3333333u, MAX_SAMPLES, 0, 0};

/* the emulated laser and ADC: one burst per period while armed */
static void trigger_poll(void)
{
    if (!trig.armed)
        return;
    uint32_t now = now_ticks(NULL);
    if ((int32_t)(now - trig.next_shot) < 0)
        return;
    uint32_t edge = trig.next_shot;
    trig.next_shot += SHOT_PERIOD_US * (SYSCLK_HZ / 1000000u);
    if ((int32_t)(now - trig.next_shot) > 0)
        trig.next_shot = now; /* fell behind: the laser does not queue shots */
    uint32_t k = trig.edges++;
    for (uint32_t i = 0; i < trig.cfg.n_samples; i++)
        adc_buf[i] = (uint16_t)((i + k) & 0xFFFu);
    trig.armed = 0; /* the core re-arms for the next shot */
    dmdsm_core_capture_done(&core, adc_buf, edge, (uint16_t)(k % 7u), DMDSM_CAPTURE_OK);
}

static void uart_poll(void)
{
    while (UART_STATE & UART_STATE_RXFULL) {
        uint8_t b = (uint8_t)UART_DATA;
        dmdsm_core_rx(&core, &b, 1);
    }
    while (tx_left && !(UART_STATE & UART_STATE_TXFULL)) {
        UART_DATA = *tx_ptr++;
        tx_left--;
    }
}

int main(void)
{
    UART_BAUDDIV = 16;
    UART_CTRL = 3; /* TX and RX enable */
    SYST_RVR = 0xFFFFFFu;
    SYST_CVR = 0;
    SYST_CSR = SYST_CSR_ENABLE | SYST_CSR_TICKINT | SYST_CSR_CLKSOURCE;
    dmdsm_core_init(&core, &ops, &info);
    struct fault_record f;
    if (fault_take(&f)) {
        char text[FAULT_TEXT_SIZE];
        fault_format(&f, text);
        dmdsm_core_log(&core, DMDSM_LOG_LEVEL_ERROR, DMDSM_ERROR_INTERNAL, text);
    }
    for (;;) {
        uart_poll();
        trigger_poll();
        dmdsm_core_poll(&core);
    }
}

/* vector table: 16 system exceptions; the test pattern needs no device IRQs */
__attribute__((section(".isr_vector"), used)) static void (*const vectors[16])(void) = {
    (void (*)(void))&_estack, /* initial SP: top of the 4 MiB data SRAM */
    Reset_Handler, Default_Handler, HardFault_Handler, Default_Handler, Default_Handler,
    Default_Handler, 0, 0, 0, 0, Default_Handler, Default_Handler, 0, Default_Handler,
    SysTick_Handler,
};

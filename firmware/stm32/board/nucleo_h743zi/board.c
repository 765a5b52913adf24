/* NUCLEO-H743ZI(2) board: main loop, board ops for the core, LEDs, CRC unit, vector table. */
#include <string.h>

#include "armv7m.h"
#include "core.h"
#include "h743_regs.h"
#include "nucleo.h"
#include "startup.h"

extern uint32_t _estack;

/* in AXI SRAM (NOLOAD; dmdsm_core_init clears it): its frames are sent by DMA */
static struct dmdsm_core core __attribute__((section(".axi_bss"), aligned(32)));
static struct dmdsm_board_info info;
static char board_name[80];

void board_early_init(void)
{
    if (!rev_is_v())
        AXI_TARG7_FN_MOD = 1u; /* ES0392 2.2.9 (rev Y and older) before any AXI SRAM access */
}

/*
 * LD1 green PB0 and LD3 red PB14 on both boards; LD2 blue is PB7 on the
 * NUCLEO-H743ZI and PE1 on the -ZI2 (make NUCLEO=ZI2 -> DMDSM_NUCLEO_ZI2).
 */
#ifdef DMDSM_NUCLEO_ZI2
#define BOARD "NUCLEO-H743ZI2"
#define LD2_PORT GPIOE
#define LD2_PIN 1u
#else
#define BOARD "NUCLEO-H743ZI"
#define LD2_PORT GPIOB
#define LD2_PIN 7u
#endif
static struct gpio *const led_port[3] = {GPIOB, LD2_PORT, GPIOB};
static const unsigned led_pin[3] = {0, LD2_PIN, 14};

void led_set(unsigned led, bool on)
{
    led_port[led]->BSRR = on ? 1u << led_pin[led] : 1u << (led_pin[led] + 16u);
}

static void leds_init(void)
{
    RCC->AHB4ENR |= RCC_AHB4ENR_GPIOBEN | RCC_AHB4ENR_GPIOEEN;
    (void)RCC->AHB4ENR; /* read back: the ports are clocked before the first access */
    for (unsigned i = 0; i < 3; i++) {
        struct gpio *port = led_port[i];
        unsigned pin = led_pin[i];
        port->MODER = (port->MODER & ~(3u << (2 * pin))) | (1u << (2 * pin));
    }
}

/* zlib's CRC-32 on the CRC unit: reflected in (by byte) and out, continued via INIT */
uint32_t board_crc32(uint32_t crc, const uint8_t *p, size_t n)
{
    uint32_t state = ~crc;
    __asm__("rbit %0, %1" : "=r"(state) : "r"(state));
    CRC_UNIT->INIT = state;
    CRC_UNIT->CR = CRC_CR_REV_IN_BYTE | CRC_CR_REV_OUT | CRC_CR_RESET;
    while (n--)
        *(volatile uint8_t *)&CRC_UNIT->DR = *p++;
    return ~CRC_UNIT->DR;
}

static void op_arm(void *ctx, const struct dmdsm_set_config *cfg)
{
    (void)ctx;
    capture_arm(cfg);
}

static void op_disarm(void *ctx)
{
    (void)ctx;
    capture_disarm();
}

static uint32_t op_now(void *ctx)
{
    (void)ctx;
    return capture_now();
}

static void op_tx_start(void *ctx, const uint8_t *p, size_t n)
{
    (void)ctx;
    serial_tx_start(p, n);
}

static bool op_tx_busy(void *ctx)
{
    (void)ctx;
    return serial_tx_busy();
}

/* the motion-sync edges come from TIM2's interrupt: hold it off while the core reads them */
static void op_sync_lock(void *ctx, bool locked)
{
    (void)ctx;
    if (locked)
        irq_disable();
    else
        irq_enable();
}

static const struct dmdsm_board_ops ops = {NULL,        op_arm,     op_disarm,   op_now,
                                           op_tx_start, op_tx_busy, op_sync_lock};

/* why arm is refused: the failure that left the board without acquisition, or 0 */
static uint8_t capture_error(void)
{
    if (capture_available())
        return DMDSM_ERROR_NONE;
    return clocks.failure ? clocks.failure : DMDSM_ERROR_ADC_FAILURE;
}

int main(void)
{
    wait_init(64000000u); /* HSI after reset: bounded waits from the first one on */
    clock_init();
    mpu_config(); /* before the D-cache: no speculative reads of external memory */
    caches_enable();
    leds_init();
    RCC->AHB4ENR |= RCC_AHB4ENR_CRCEN;
    (void)RCC->AHB4ENR;
    CRC_UNIT->POL = 0x04C11DB7u;
    serial_init(DMDSM_BAUD);
    capture_init();
    boot_board_name(board_name, sizeof board_name,
                    clocks.rev_v ? BOARD " rev V" : BOARD " rev Y");
    info = (struct dmdsm_board_info){board_name, clocks.timclk_hz, capture_adc_rate_hz(),
                                     8192u, capture_error(), DMDSM_BAUD / 10u};
    dmdsm_core_init(&core, &ops, &info);
    capture_sync_to(&core);
    boot_report(&core);
    struct fault_record f;
    bool fault = fault_take(&f);
    if (fault) {
        char text[FAULT_TEXT_SIZE];
        fault_format(&f, text);
        dmdsm_core_log(&core, DMDSM_LOG_LEVEL_ERROR, DMDSM_ERROR_INTERNAL, text);
    }
    uint8_t rx[64];
    for (;;) {
        size_t n = serial_read(rx, sizeof rx);
        if (n)
            dmdsm_core_rx(&core, rx, n);
        const uint16_t *samples;
        uint32_t edge;
        uint16_t phase;
        enum dmdsm_capture result;
        if (capture_poll(&samples, &edge, &phase, &result))
            dmdsm_core_capture_done(&core, samples, edge, phase, result);
        dmdsm_core_poll(&core);
        /* LEDs: green heartbeat 1 Hz, blue while armed, red: the boot failure's blink
         * code, else steady after a fault or an error */
        uint64_t ms = dmdsm_core_now(&core) / (info.tick_hz / 1000u);
        led_set(0, (ms / 500u) & 1u);
        led_set(1, core.state == DMDSM_STATE_ARMED);
        led_set(2, boot_failed_step() ? boot_led(ms)
                                      : fault || core.last_error == DMDSM_ERROR_ADC_OVERRUN ||
                                            core.last_error == DMDSM_ERROR_SAMPLE_INTEGRITY ||
                                            core.last_error == DMDSM_ERROR_INTERNAL);
    }
}

void TIM2_IRQHandler(void);
void USART3_IRQHandler(void);

/* 16 system exceptions + 150 device interrupts (RM0433 Table 143) */
__attribute__((section(".isr_vector"), used)) static void (*const vectors[16 + N_IRQ])(void) = {
    [0] = (void (*)(void))&_estack,
    [1] = Reset_Handler,
    [2] = Default_Handler,
    [3] = HardFault_Handler,
    [4 ... 16 + IRQ_TIM2 - 1] = Default_Handler,
    [16 + IRQ_TIM2] = TIM2_IRQHandler,
    [16 + IRQ_TIM2 + 1 ... 16 + IRQ_USART3 - 1] = Default_Handler,
    [16 + IRQ_USART3] = USART3_IRQHandler,
    [16 + IRQ_USART3 + 1 ... 16 + N_IRQ - 1] = Default_Handler,
};

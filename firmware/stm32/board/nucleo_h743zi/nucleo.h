/* What the NUCLEO-H743ZI board files share: clock facts, pins and the drivers' entry points. */
#ifndef DMDSM_NUCLEO_H
#define DMDSM_NUCLEO_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#include "core.h" /* struct dmdsm_core, enum dmdsm_capture, dmdsm_spec.h */

/*
 * Pins (NUCLEO-144 connectors):
 *   PA0  TIM2_CH1 (AF1)  photodiode comparator output: the laser edge
 *   PA6  ADC12_INP3      pre-amplified transducer signal (fast channel, 0-3.3 V)
 *   PB3  TIM2_CH2 (AF1)  the stage's X STEP line (motion sync, input x)
 *   PB10 TIM2_CH3 (AF1)  the stage's turntable (A, former E0) STEP line (motion sync, input a)
 *   PD8  USART3_TX (AF7) ST-LINK virtual COM port
 *   PD9  USART3_RX (AF7)
 *   PB0  LD1 green (heartbeat), PB14 LD3 red (error, boot blink code)
 *   PB7  LD2 blue (armed) on the NUCLEO-H743ZI, PE1 on the -ZI2 (DMDSM_NUCLEO_ZI2)
 */
#ifndef DMDSM_BAUD
#define DMDSM_BAUD 2000000u /* ST-LINK/V2-1 VCP; the -ZI2's STLINK-V3 takes more */
#endif

/* read back from RCC after clock_init: right on the fallback clock too */
struct clocks {
    bool rev_v;      /* silicon revision V (REV_ID > 0x1003, as ST's HAL decides) */
    uint8_t failure; /* enum dmdsm_error that left the board without acquisition, or 0 */
    uint32_t sysclk_hz, hclk_hz, pclk_hz, timclk_hz; /* CPU, AXI/AHB, APB1, TIM2/TIM8 */
    uint32_t adc_hz; /* ADC conversion clock, 0 when PLL2 is not running */
};
extern struct clocks clocks;

void clock_init(void);

/* serial.c: USART3 with DMA transmit and an interrupt-fed receive ring */
void serial_init(uint32_t baud);
void serial_tx_start(const uint8_t *p, size_t n);
bool serial_tx_busy(void);
size_t serial_read(uint8_t *out, size_t cap);

/* capture.c: TIM8-paced ADC1 into a circular DMA ring, TIM2 capturing the edge */
void capture_init(void); /* TIM2 always; ADC1 and pacing when clocks.adc_hz is set */
bool capture_available(void);
void capture_arm(const struct dmdsm_set_config *cfg);
void capture_disarm(void);
struct dmdsm_core;
/* motion sync: TIM2 CH2 (PB3, X) and CH3 (PB10, A) rising edges go to this core's
 * dmdsm_core_sync_edge */
void capture_sync_to(struct dmdsm_core *core);
uint32_t capture_now(void);
/* 1 when a burst is complete: samples, edge ticks, phase ticks, and how it ended */
int capture_poll(const uint16_t **samples, uint32_t *edge, uint16_t *phase,
                 enum dmdsm_capture *result);
uint32_t capture_adc_rate_hz(void);

/* integrity.c: bounds on the trigger-to-ring latency implied by each (NDTR, CNT) poll */
struct integrity {
    int64_t lo, hi;       /* latency bounds (ticks) from all polls since pacing started */
    uint32_t jitter, max; /* allowed spread and largest latency (ticks) */
};
void integrity_reset(struct integrity *g, uint32_t timclk_hz);
/* false once the polls disagree: phase = (CNT - t0) mod T and lag = timer minus DMA count
 * (-RING/2..RING/2) at the CNT read before NDTR, skew = ticks to the CNT read after it,
 * written = the DMA stored a sample since pacing started */
bool integrity_observe(struct integrity *g, uint32_t phase, int32_t lag, uint32_t skew,
                       bool written, uint32_t T);

/* adc.c: ADC1 power-up and calibration (false, with a boot failure, if it timed out) */
bool adc_init(void);
void adc_start(void);
bool adc_stop(void);

/* wait.c: bounded waits, timed by SysTick at cpu_hz (again after a clock change), then by
 * TIM2 once it runs */
void wait_init(uint32_t cpu_hz);
void wait_use_tim2(uint32_t timclk_hz);
/* true once (*reg & mask) == want, false after us microseconds */
bool wait_bits(const volatile uint32_t *reg, uint32_t mask, uint32_t want, uint32_t us);
void delay_us(uint32_t us);

/* boot.c: start-up failures; the step number is LD3's blink count (docs/firmware.md) */
enum boot_step {
    BOOT_SUPPLY = 1, /* LDO supply: PWR_CSR1.ACTVOSRDY */
    BOOT_VOS1 = 2,   /* voltage scale 1: PWR_D3CR.VOSRDY, PWR_CSR1.ACTVOS */
    BOOT_VOS0 = 3,   /* VOS0 (rev V): SYSCFG clock, SYSCFG_PWRCR.ODEN, VOSRDY, ACTVOS */
    BOOT_FLASH = 4,  /* flash wait states: FLASH_ACR.LATENCY read back */
    BOOT_HSE = 5,    /* HSE bypass: RCC_CR.HSERDY */
    BOOT_PLL = 6,    /* PLL1 / PLL2 lock: RCC_CR.PLLxRDY */
    BOOT_SWITCH = 7, /* system clock switch: RCC_CFGR.SWS */
    BOOT_ADC = 8,    /* ADC1 calibration or ready */
};
void boot_fail(enum boot_step step, uint8_t code, const char *text);
unsigned boot_failed_step(void); /* first failed step, 0 if none */
void boot_board_name(char *out, size_t cap, const char *base);
void boot_report(struct dmdsm_core *core); /* one error log per failure */
bool boot_led(uint64_t ms);                /* LD3 state of the blink code at ms since boot */

/* board.c */
void led_set(unsigned led, bool on);

/* memory.c: ST's MPU background region, then the I- and D-cache */
void mpu_config(void);
void caches_enable(void);

#endif

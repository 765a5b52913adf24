/* What the NUCLEO-H743ZI board files share: clock facts, pins and the drivers' entry points. */
#ifndef DMDSM_NUCLEO_H
#define DMDSM_NUCLEO_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#include "dmdsm_spec.h" /* struct dmdsm_set_config */

/*
 * Pins (NUCLEO-144 connectors):
 *   PA0  TIM2_CH1 (AF1)  photodiode comparator output: the laser edge
 *   PA6  ADC12_INP3      pre-amplified transducer signal (fast channel, 0-3.3 V)
 *   PD8  USART3_TX (AF7) ST-LINK virtual COM port
 *   PD9  USART3_RX (AF7)
 *   PB0  LD1 green (heartbeat), PB7 LD2 blue (armed), PB14 LD3 red (error)
 */
#ifndef DMDSM_BAUD
#define DMDSM_BAUD 2000000u /* ST-LINK/V2-1 VCP; the -ZI2's STLINK-V3 takes more */
#endif

struct clocks {
    bool rev_v;
    uint32_t sysclk_hz, hclk_hz, pclk_hz, timclk_hz, adc_hz;
};
extern struct clocks clocks;

void clock_init(void);

/* serial.c: USART3 with DMA transmit and an interrupt-fed receive ring */
void serial_init(uint32_t baud);
void serial_tx_start(const uint8_t *p, size_t n);
bool serial_tx_busy(void);
size_t serial_read(uint8_t *out, size_t cap);

/* capture.c: TIM8-paced ADC1 into a circular DMA ring, TIM2 capturing the edge */
void capture_init(void);
void capture_arm(const struct dmdsm_set_config *cfg);
void capture_disarm(void);
uint32_t capture_now(void);
/* 1 when a burst is complete: samples, edge ticks, phase ticks, overrun flag */
int capture_poll(const uint16_t **samples, uint32_t *edge, uint16_t *phase, bool *overrun);
uint32_t capture_adc_rate_hz(void);

/* board.c */
void led_set(unsigned led, bool on);

#endif

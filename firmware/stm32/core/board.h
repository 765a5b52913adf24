/* The hardware abstraction each board implements for the portable core (NUCLEO, QEMU, PC/SIL). */
#ifndef DMDSM_BOARD_H
#define DMDSM_BOARD_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#include "dmdsm_spec.h" /* struct dmdsm_set_config */

/*
 * The core never touches a register. A board gives it these operations and
 * calls the core's event functions (core.h) from its interrupts or main loop:
 *
 *   arm_capture    Prepare one hardware-triggered burst as cfg says: on the
 *                  next photodiode edge the ADC fills the board's DMA buffer
 *                  with cfg->n_samples samples (cfg->pretrigger of them from
 *                  before the edge) with no CPU in the path. When the burst
 *                  completes the board calls dmdsm_core_capture_done() with
 *                  the samples. Called again for every shot.
 *   disarm_capture Stop any pending or running burst; no capture_done follows.
 *   now_ticks      Free-running 32-bit counter at info.tick_hz (the core extends
 *                  it to 64 bits; it must be read at least once per wrap).
 *   tx_start       Start sending n bytes without blocking (DMA or a FIFO the
 *                  board drains). The bytes stay valid until tx_busy() is false.
 *   tx_busy        True while a tx_start transfer is still going out.
 *   sync_lock      Hold off (true) or release (false) the interrupt that calls
 *                  dmdsm_core_sync_edge(); an edge meanwhile must stay latched.
 *                  NULL where that interrupt cannot preempt the main loop.
 */
struct dmdsm_board_ops {
    void *ctx;
    void (*arm_capture)(void *ctx, const struct dmdsm_set_config *cfg);
    void (*disarm_capture)(void *ctx);
    uint32_t (*now_ticks)(void *ctx);
    void (*tx_start)(void *ctx, const uint8_t *p, size_t n);
    bool (*tx_busy)(void *ctx);
    void (*sync_lock)(void *ctx, bool locked);
};

/* Static facts a board reports in identify_reply. */
struct dmdsm_board_info {
    const char *name;     /* e.g. "NUCLEO-H743ZI rev V" */
    uint32_t tick_hz;     /* rate of now_ticks and capture timestamps */
    uint32_t adc_rate_hz; /* sample rate at sample_rate_div = 1 */
    uint16_t max_samples; /* largest burst the board's buffers hold */
    uint8_t capture_error; /* enum dmdsm_error: why acquisition is unavailable (arm is NAKed
                            * with it), e.g. an ADC that failed at boot; 0 = available */
    uint32_t link_bytes_per_s; /* the link's rate (8N1: baud / 10). The core times the shots
                                * it takes on a busy link so a waveform is ready just as the
                                * wire frees (fresh data, the wire kept full); 0 = unknown:
                                * it fills every slot and skips shots only when none is free */
};

#endif /* DMDSM_BOARD_H */

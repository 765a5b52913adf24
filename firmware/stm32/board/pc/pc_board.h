/* C API of the PC build of the firmware core (libdmdsm_core.so), for the SIL emulator. */
#ifndef DMDSM_PC_BOARD_H
#define DMDSM_PC_BOARD_H

#include <stddef.h>
#include <stdint.h>

#include "dmdsm_spec.h" /* struct dmdsm_set_config */

struct dmdsm_pc;

/* a new device at tick counter `ticks`; NULL if out of memory */
struct dmdsm_pc *dmdsm_pc_new(const char *name, uint32_t tick_hz, uint32_t adc_rate_hz,
                              uint16_t max_samples, uint32_t ticks);
void dmdsm_pc_free(struct dmdsm_pc *d);
/* advance the device clock (32-bit, wraps) and run the main loop once */
void dmdsm_pc_set_ticks(struct dmdsm_pc *d, uint32_t ticks);
/* bytes from the host */
void dmdsm_pc_rx(struct dmdsm_pc *d, const uint8_t *p, size_t n);
/* up to cap bytes the device sends; 0 when its queues are empty */
size_t dmdsm_pc_tx(struct dmdsm_pc *d, uint8_t *out, size_t cap);
/* 1 if waiting for a laser edge (and the configuration of that burst) */
int dmdsm_pc_armed(const struct dmdsm_pc *d, struct dmdsm_set_config *cfg);
/* 1 if armed and a good burst at edge_ticks would be averaged, not skipped (no free slot) */
int dmdsm_pc_takes_shot(struct dmdsm_pc *d, uint32_t edge_ticks);
/* one burst after an edge at edge_ticks: cfg.n_samples samples; result 0 = good,
 * 1 = ADC overrun, 2 = sample-integrity fault (enum dmdsm_capture); only good ones are averaged */
void dmdsm_pc_capture(struct dmdsm_pc *d, const uint16_t *samples, uint32_t edge_ticks,
                      uint16_t phase, int result);
void dmdsm_pc_sync_edges(struct dmdsm_pc *d, unsigned input, const uint32_t *ticks,
                         size_t n);
/* the rate (bytes/s) the emulator drains the link at, as a board knows its baud rate
 * (board_info.link_bytes_per_s); 0 = unknown (the default) */
void dmdsm_pc_set_link_rate(struct dmdsm_pc *d, uint32_t bytes_per_s);
void dmdsm_pc_poll(struct dmdsm_pc *d);
/* enum dmdsm_state */
uint8_t dmdsm_pc_state(const struct dmdsm_pc *d);

#endif

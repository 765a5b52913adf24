/* The portable firmware core: commands, acquisition state machine, averaging, transmit queue. */
#ifndef DMDSM_CORE_H
#define DMDSM_CORE_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#include "board.h"       /* struct dmdsm_board_ops, dmdsm_board_info */
#include "dmdsm_frame.h" /* struct dmdsm_decoder, DMDSM_WIRE_SIZE */

#define DMDSM_FW_MAJOR 0
#define DMDSM_FW_MINOR 2
#define DMDSM_FW_PATCH 1

#ifndef DMDSM_CORE_MAX_SAMPLES
#define DMDSM_CORE_MAX_SAMPLES 8192u /* accumulator length; boards may accept fewer */
#endif
#define DMDSM_CORE_WAVE_SLOTS 2u /* waveform frames: one on the wire, one ready */
#define DMDSM_CORE_CTL_SLOTS 4u  /* responses and log lines waiting for the link */
/* sync edge times kept to count the edges before a shot: a burst's capture-done comes one
 * ADC burst (~0.3 ms) after its laser edge, when X (<= 16 kHz of steps) made at most ~6 more */
#define DMDSM_SYNC_RING 16u
/* motion-sync inputs: X and A STEP lines (enum dmdsm_sync_input) */
#define DMDSM_SYNC_INPUTS 2u
#define DMDSM_CORE_CTL_FRAME DMDSM_WIRE_SIZE(240u)
#define DMDSM_CORE_RX_CAP \
    DMDSM_ENCODED_SIZE(DMDSM_HEADER_SIZE + DMDSM_MAX_COMMAND_PAYLOAD + DMDSM_CRC_SIZE)

/* one motion-sync input (sync.c): written by the board's edge interrupt, read by poll */
struct dmdsm_sync_line {
    volatile uint32_t first; /* 32-bit ticks of the open burst's first edge */
    volatile uint32_t last;  /* ... and of its latest edge */
    volatile uint32_t edges; /* edges in the open burst; 0 = no burst open */
    /* ticks of the open burst's latest edges: edge n at [n % DMDSM_SYNC_RING] */
    volatile uint32_t ring[DMDSM_SYNC_RING];
};

/* cumulative counters since boot, reported in status */
struct dmdsm_counters {
    uint32_t triggers;
    uint32_t shots_sent;
    uint32_t triggers_skipped; /* shots not captured: no free waveform slot (by design) */
    uint32_t adc_overruns;
    uint32_t integrity_faults; /* bursts whose DMA position disagreed with the timer */
    uint32_t no_trigger_timeouts;
    uint32_t rx_frames;
    uint32_t ctl_dropped; /* responses lost to a full control queue (never expected) */
};

struct dmdsm_core {
    const struct dmdsm_board_ops *ops;
    const struct dmdsm_board_info *info;
    struct dmdsm_set_config cfg;
    uint8_t state;      /* enum dmdsm_state */
    uint8_t last_error; /* enum dmdsm_error */
    bool continuous;
    uint32_t shots_remaining;
    uint32_t shot_id;        /* next waveform's id, from 0 after each arm */
    uint16_t wave_seq;       /* seq of the next waveform frame */
    uint16_t log_seq;        /* seq of the next log frame */
    uint64_t armed_at;       /* ticks of arm or of the last edge, for the timeout */
    /* 64-bit clock from the board's 32-bit counter */
    uint32_t clock_last;
    uint64_t clock_high;
    /* running average */
    uint32_t acc[DMDSM_CORE_MAX_SAMPLES];
    uint32_t n_in_avg;
    uint64_t avg_first_edge;
    uint32_t avg_phase_sum;
    /* sum of each averaged shot's sync edge count, per input */
    uint32_t avg_sync_steps[DMDSM_SYNC_INPUTS];
    struct dmdsm_counters count;
    struct dmdsm_sync_line sync[DMDSM_SYNC_INPUTS]; /* the X and A STEP lines */
    uint32_t sync_burst_id;       /* next motion_sync's burst_id (both inputs) */
    /* receive */
    struct dmdsm_decoder rx;
    uint8_t rx_buf[DMDSM_CORE_RX_CAP];
    bool have_last;    /* last command's seq and response, for retransmissions */
    uint16_t last_seq;
    uint8_t last_cmd; /* type of the last command answered (for retransmissions) */
    uint8_t last_resp[DMDSM_CORE_CTL_FRAME];
    size_t last_resp_len;
    /* transmit: control frames first, then waveforms */
    uint8_t ctl[DMDSM_CORE_CTL_SLOTS][DMDSM_CORE_CTL_FRAME];
    size_t ctl_len[DMDSM_CORE_CTL_SLOTS];
    unsigned ctl_head, ctl_count;
    uint8_t wave[DMDSM_CORE_WAVE_SLOTS][DMDSM_WIRE_SIZE(DMDSM_MAX_PAYLOAD)];
    size_t wave_len[DMDSM_CORE_WAVE_SLOTS];
    unsigned wave_head, wave_count;
    bool tx_wave; /* the transfer on the wire is wave[wave_head] */
    bool tx_ctl;  /* the transfer on the wire is ctl[ctl_head] */
    uint64_t tx_end;     /* ticks: when the transfer on the wire will be out (estimate) */
    uint64_t last_edge;  /* ticks of the last laser edge since the arm (0: none yet) */
    uint32_t laser_period; /* ticks between the last two laser edges (0: not known yet) */
};

/* set up with default configuration, state idle */
void dmdsm_core_init(struct dmdsm_core *c, const struct dmdsm_board_ops *ops,
                     const struct dmdsm_board_info *info);
/* bytes received from the host (any chunking) */
void dmdsm_core_rx(struct dmdsm_core *c, const uint8_t *p, size_t n);
/* how a burst ended; only DMDSM_CAPTURE_OK bursts are averaged */
enum dmdsm_capture {
    DMDSM_CAPTURE_OK = 0,
    DMDSM_CAPTURE_OVERRUN = 1,   /* the ADC or DMA overran, or the ring lapped the burst */
    DMDSM_CAPTURE_INTEGRITY = 2, /* the DMA's write position disagreed with the timer */
};
/* whether a good burst at this edge (32-bit ticks, now or just past) would be averaged
 * rather than skipped for want of a free slot: an emulator asks it before it computes the
 * samples of a shot the core would throw away */
bool dmdsm_core_takes_shot(struct dmdsm_core *c, uint32_t edge_ticks);
/* a burst finished: samples, 32-bit ticks of the edge, edge-to-first-sample
 * phase in ticks, and how it ended (enum dmdsm_capture) */
void dmdsm_core_capture_done(struct dmdsm_core *c, const uint16_t *samples,
                             uint32_t edge_ticks, uint16_t phase, enum dmdsm_capture result);
/* a rising edge on motion-sync input `input` (enum dmdsm_sync_input) at 32-bit ticks (the
 * board's capture interrupt); an input number the core does not have is ignored */
void dmdsm_core_sync_edge(struct dmdsm_core *c, unsigned input, uint32_t ticks);
/* from poll: report each input's burst that has been quiet for DMDSM_SYNC_QUIET_MS */
void dmdsm_core_sync_poll(struct dmdsm_core *c);
/* edges of an input's open burst at or before 32-bit ticks (a laser edge of the last ~1 ms) */
uint32_t dmdsm_core_sync_count_at(struct dmdsm_core *c, unsigned input, uint32_t ticks);
/* run from the main loop: starts queued transfers, checks the trigger timeout */
void dmdsm_core_poll(struct dmdsm_core *c);
/* current time in ticks, 64-bit */
uint64_t dmdsm_core_now(struct dmdsm_core *c);
/* the 64-bit time of a 32-bit tick value at most one wrap before `now` (a dmdsm_core_now) */
uint64_t dmdsm_core_extend(uint64_t now, uint32_t ticks);
/* queue a log line (also used by boards, e.g. after a HardFault reset or a boot failure);
 * an error-level line with a code also becomes status.last_error */
void dmdsm_core_log(struct dmdsm_core *c, uint8_t level, uint8_t code, const char *text);

/* internal, shared between the core's files */
void dmdsm_core_queue_ctl(struct dmdsm_core *c, const uint8_t *frame, size_t n);
void dmdsm_core_stop(struct dmdsm_core *c);
bool dmdsm_core_arm(struct dmdsm_core *c, uint32_t n_shots);

#endif /* DMDSM_CORE_H */

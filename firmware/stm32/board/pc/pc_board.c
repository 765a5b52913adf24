/* PC board: the firmware core as a shared library the SIL emulator drives (clock, edges, link). */
#include <stdlib.h>
#include <string.h>

#include "core.h"
#include "pc_board.h"

/*
 * The emulator owns time and the physics: it sets the 32-bit tick counter,
 * asks whether the core is armed (and with which configuration), delivers a
 * burst of samples for each laser edge, and drains the device's transmit
 * side at whatever speed its link model allows.
 */
struct dmdsm_pc {
    struct dmdsm_core core;
    struct dmdsm_board_ops ops;
    struct dmdsm_board_info info;
    char name[64];
    uint32_t ticks;
    int armed;
    struct dmdsm_set_config cfg;
    const uint8_t *tx_ptr;
    size_t tx_left;
};

static void arm_capture(void *ctx, const struct dmdsm_set_config *cfg)
{
    struct dmdsm_pc *d = ctx;
    d->armed = 1;
    d->cfg = *cfg;
}

static void disarm_capture(void *ctx)
{
    struct dmdsm_pc *d = ctx;
    d->armed = 0;
}

static uint32_t now_ticks(void *ctx)
{
    return ((struct dmdsm_pc *)ctx)->ticks;
}

static void tx_start(void *ctx, const uint8_t *p, size_t n)
{
    struct dmdsm_pc *d = ctx;
    d->tx_ptr = p;
    d->tx_left = n;
}

static bool tx_busy(void *ctx)
{
    return ((struct dmdsm_pc *)ctx)->tx_left != 0;
}

static const struct dmdsm_board_ops ops_template = {NULL,     arm_capture, disarm_capture,
                                                    now_ticks, tx_start, tx_busy, NULL};

struct dmdsm_pc *dmdsm_pc_new(const char *name, uint32_t tick_hz, uint32_t adc_rate_hz,
                              uint16_t max_samples, uint32_t ticks)
{
    struct dmdsm_pc *d = calloc(1, sizeof *d);
    if (d == NULL)
        return NULL;
    d->ops = ops_template;
    d->ops.ctx = d;
    strncpy(d->name, name, sizeof d->name - 1);
    d->info = (struct dmdsm_board_info){d->name, tick_hz, adc_rate_hz, max_samples, 0, 0};
    d->ticks = ticks;
    dmdsm_core_init(&d->core, &d->ops, &d->info);
    return d;
}

void dmdsm_pc_free(struct dmdsm_pc *d)
{
    free(d);
}

void dmdsm_pc_set_ticks(struct dmdsm_pc *d, uint32_t ticks)
{
    d->ticks = ticks;
    dmdsm_core_poll(&d->core);
}

void dmdsm_pc_rx(struct dmdsm_pc *d, const uint8_t *p, size_t n)
{
    dmdsm_core_rx(&d->core, p, n);
}

size_t dmdsm_pc_tx(struct dmdsm_pc *d, uint8_t *out, size_t cap)
{
    size_t total = 0;
    while (total < cap) {
        dmdsm_core_poll(&d->core); /* starts the next queued frame when the last is out */
        if (d->tx_left == 0)
            break;
        size_t n = d->tx_left < cap - total ? d->tx_left : cap - total;
        memcpy(out + total, d->tx_ptr, n);
        d->tx_ptr += n;
        d->tx_left -= n;
        total += n;
    }
    return total;
}

int dmdsm_pc_armed(const struct dmdsm_pc *d, struct dmdsm_set_config *cfg)
{
    if (d->armed && cfg != NULL)
        *cfg = d->cfg;
    return d->armed;
}

int dmdsm_pc_takes_shot(struct dmdsm_pc *d, uint32_t edge_ticks)
{
    return d->armed && dmdsm_core_takes_shot(&d->core, edge_ticks);
}

void dmdsm_pc_capture(struct dmdsm_pc *d, const uint16_t *samples, uint32_t edge_ticks,
                      uint16_t phase, int result)
{
    enum dmdsm_capture r = result == DMDSM_CAPTURE_OVERRUN     ? DMDSM_CAPTURE_OVERRUN
                           : result == DMDSM_CAPTURE_INTEGRITY ? DMDSM_CAPTURE_INTEGRITY
                                                               : DMDSM_CAPTURE_OK;
    d->armed = 0; /* the core re-arms for the next shot */
    dmdsm_core_capture_done(&d->core, samples, edge_ticks, phase, r);
}

/* rising edges on motion-sync input `input` (enum dmdsm_sync_input), at 32-bit ticks, in
 * time order */
void dmdsm_pc_sync_edges(struct dmdsm_pc *d, unsigned input, const uint32_t *ticks, size_t n)
{
    for (size_t i = 0; i < n; i++)
        dmdsm_core_sync_edge(&d->core, input, ticks[i]);
}

void dmdsm_pc_set_link_rate(struct dmdsm_pc *d, uint32_t bytes_per_s)
{
    d->info.link_bytes_per_s = bytes_per_s;
}

void dmdsm_pc_poll(struct dmdsm_pc *d)
{
    dmdsm_core_poll(&d->core);
}

uint8_t dmdsm_pc_state(const struct dmdsm_pc *d)
{
    return d->core.state;
}

/* Motion sync: bursts of step pulses on the X and A sync inputs, time-stamped in the waveforms' clock. */
#include "core.h"

/*
 * The stage's X STEP line and its turntable's (A) STEP line are wired to two
 * timer capture inputs on the same counter that time-stamps the laser edges
 * (docs/firmware.md, "Motion sync"). The board's capture interrupt calls
 * dmdsm_core_sync_edge() for every rising edge with the input it came on; a
 * burst is the run of one input's edges of one move, and it ends when that
 * input has been quiet for DMDSM_SYNC_QUIET_MS. poll() then sends one
 * motion_sync with the input, the first and last edge and the count, so the
 * host can check the move's step count; and each waveform carries each
 * input's edges counted before its shots (sync_steps, sync_steps_a), so the
 * host knows where X and the table were at every shot without modelling how
 * the stage's firmware ramps its steps. Both axes step in proportion within
 * one linear move (Marlin's Bresenham), so one counted axis places the others
 * of that move too.
 *
 * The interrupt only writes three words of its input. poll reads and closes
 * them with the board's sync interrupt held off (ops->sync_lock, a few
 * instructions): the hardware latches an edge meanwhile and its interrupt runs
 * right after, so no edge is lost or merged into the wrong burst.
 */

static void lock(struct dmdsm_core *c, bool locked)
{
    if (c->ops->sync_lock)
        c->ops->sync_lock(c->ops->ctx, locked);
}

void dmdsm_core_sync_edge(struct dmdsm_core *c, unsigned input, uint32_t ticks)
{
    if (input >= DMDSM_SYNC_INPUTS)
        return;
    struct dmdsm_sync_line *s = &c->sync[input];
    uint32_t n = s->edges;
    if (n == 0)
        s->first = ticks;
    s->last = ticks;
    s->ring[n % DMDSM_SYNC_RING] = ticks;
    s->edges = n + 1u;
}

uint32_t dmdsm_core_sync_count_at(struct dmdsm_core *c, unsigned input, uint32_t ticks)
{
    if (input >= DMDSM_SYNC_INPUTS)
        return 0;
    struct dmdsm_sync_line *s = &c->sync[input];
    lock(c, true);
    uint32_t n = s->edges, later = 0;
    /* the edges that came after `ticks` are the latest ones: walk back over them */
    while (later < n && later < DMDSM_SYNC_RING &&
           (int32_t)(s->ring[(n - 1u - later) % DMDSM_SYNC_RING] - ticks) > 0)
        later++;
    lock(c, false);
    return n - later;
}

/* report one input's burst if it has been quiet long enough */
static void poll_input(struct dmdsm_core *c, unsigned input, uint64_t now, uint64_t quiet)
{
    struct dmdsm_sync_line *s = &c->sync[input];
    if (s->edges == 0)
        return;
    lock(c, true);
    uint32_t edges = s->edges, first = s->first, last = s->last;
    bool ended = edges != 0 && (uint32_t)((uint32_t)now - last) >= quiet;
    if (ended)
        s->edges = 0;
    lock(c, false);
    if (!ended)
        return;
    struct dmdsm_motion_sync m = {.burst_id = c->sync_burst_id++,
                                  .first_edge = dmdsm_core_extend(now, first),
                                  .last_edge = dmdsm_core_extend(now, last),
                                  .edges = edges, .input = (uint8_t)input};
    uint8_t p[DMDSM_MOTION_SYNC_FIXED_SIZE];
    uint8_t frame[DMDSM_CORE_CTL_FRAME];
    size_t len = dmdsm_pack_motion_sync(&m, p);
    size_t n = dmdsm_frame_encode(frame, sizeof frame, DMDSM_MSG_MOTION_SYNC, 0, c->log_seq++,
                                  p, len);
    if (n)
        dmdsm_core_queue_ctl(c, frame, n);
}

void dmdsm_core_sync_poll(struct dmdsm_core *c)
{
    if (c->sync[DMDSM_SYNC_INPUT_X].edges == 0 && c->sync[DMDSM_SYNC_INPUT_A].edges == 0)
        return;
    uint64_t now = dmdsm_core_now(c);
    uint64_t quiet = (uint64_t)DMDSM_SYNC_QUIET_MS * c->info->tick_hz / 1000u;
    for (unsigned k = 0; k < DMDSM_SYNC_INPUTS; k++)
        poll_input(c, k, now, quiet);
}

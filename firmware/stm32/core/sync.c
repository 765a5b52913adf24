/* Motion sync: bursts of step pulses on the sync input, time-stamped in the waveforms' clock. */
#include "core.h"

/*
 * The stage's X STEP line is wired to a timer capture input on the same
 * counter that time-stamps the laser edges (docs/firmware.md, "Motion sync").
 * The board's capture interrupt calls dmdsm_core_sync_edge() for every rising
 * edge; a burst is the run of edges of one move, and it ends when the input
 * has been quiet for DMDSM_SYNC_QUIET_MS. poll() then sends one motion_sync
 * with the first and last edge and the count, so the host can check the
 * move's step count; and each waveform carries the edges counted before its
 * shots (sync_steps), so the host knows where X was at every shot without
 * modelling how the stage's firmware ramps its steps.
 *
 * The interrupt only writes three words. poll reads and closes them with the
 * board's sync interrupt held off (ops->sync_lock, a few instructions): the
 * hardware latches an edge meanwhile and its interrupt runs right after, so no
 * edge is lost or merged into the wrong burst.
 */

void dmdsm_core_sync_edge(struct dmdsm_core *c, uint32_t ticks)
{
    uint32_t n = c->sync_edges;
    if (n == 0)
        c->sync_first = ticks;
    c->sync_last = ticks;
    c->sync_ring[n % DMDSM_SYNC_RING] = ticks;
    c->sync_edges = n + 1u;
}

uint32_t dmdsm_core_sync_count_at(struct dmdsm_core *c, uint32_t ticks)
{
    if (c->ops->sync_lock)
        c->ops->sync_lock(c->ops->ctx, true);
    uint32_t n = c->sync_edges, later = 0;
    /* the edges that came after `ticks` are the latest ones: walk back over them */
    while (later < n && later < DMDSM_SYNC_RING &&
           (int32_t)(c->sync_ring[(n - 1u - later) % DMDSM_SYNC_RING] - ticks) > 0)
        later++;
    if (c->ops->sync_lock)
        c->ops->sync_lock(c->ops->ctx, false);
    return n - later;
}

void dmdsm_core_sync_poll(struct dmdsm_core *c)
{
    if (c->sync_edges == 0)
        return;
    uint64_t now = dmdsm_core_now(c);
    uint64_t quiet = (uint64_t)DMDSM_SYNC_QUIET_MS * c->info->tick_hz / 1000u;
    if (c->ops->sync_lock)
        c->ops->sync_lock(c->ops->ctx, true);
    uint32_t edges = c->sync_edges, first = c->sync_first, last = c->sync_last;
    bool ended = edges != 0 && (uint32_t)((uint32_t)now - last) >= quiet;
    if (ended)
        c->sync_edges = 0;
    if (c->ops->sync_lock)
        c->ops->sync_lock(c->ops->ctx, false);
    if (!ended)
        return;
    struct dmdsm_motion_sync m = {.burst_id = c->sync_burst_id++,
                                  .first_edge = dmdsm_core_extend(now, first),
                                  .last_edge = dmdsm_core_extend(now, last),
                                  .edges = edges};
    uint8_t p[DMDSM_MOTION_SYNC_FIXED_SIZE];
    uint8_t frame[DMDSM_CORE_CTL_FRAME];
    size_t len = dmdsm_pack_motion_sync(&m, p);
    size_t n = dmdsm_frame_encode(frame, sizeof frame, DMDSM_MSG_MOTION_SYNC, 0, c->log_seq++,
                                  p, len);
    if (n)
        dmdsm_core_queue_ctl(c, frame, n);
}

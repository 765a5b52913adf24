/* Acquisition: arm/disarm, on-board averaging, trigger timeout, clock and the transmit queue. */
#include <string.h>

#include "core.h"

_Static_assert(sizeof(struct dmdsm_config) == sizeof(struct dmdsm_set_config),
               "config and set_config must share one layout");
/* 4096 shots of 16-bit samples fit a 32-bit accumulator: 4096 * 65535 < 2^32 */
_Static_assert(4096ull * 65535ull < (1ull << 32), "accumulator overflow");

void dmdsm_core_init(struct dmdsm_core *c, const struct dmdsm_board_ops *ops,
                     const struct dmdsm_board_info *info)
{
    memset(c, 0, sizeof *c);
    c->ops = ops;
    c->info = info;
    c->cfg = (struct dmdsm_set_config){
        .n_samples = 1024, .sample_rate_div = 1, .n_average = 1, .pretrigger = 0,
        .trigger_edge = DMDSM_TRIGGER_EDGE_RISING, .modality = DMDSM_MODALITY_OA,
        .sample_format = DMDSM_SAMPLE_FORMAT_U16_MEAN, .trigger_timeout_ms = 1000};
    if (c->cfg.n_samples > info->max_samples)
        c->cfg.n_samples = info->max_samples;
    c->state = DMDSM_STATE_IDLE;
    dmdsm_decoder_init(&c->rx, c->rx_buf, sizeof c->rx_buf);
    c->clock_last = ops->now_ticks(ops->ctx);
}

uint64_t dmdsm_core_now(struct dmdsm_core *c)
{
    uint32_t t = c->ops->now_ticks(c->ops->ctx);
    if (t < c->clock_last)
        c->clock_high += (uint64_t)1 << 32;
    c->clock_last = t;
    return c->clock_high | t;
}

uint64_t dmdsm_core_extend(uint64_t now, uint32_t ticks)
{
    return now - (uint32_t)((uint32_t)now - ticks);
}

void dmdsm_core_queue_ctl(struct dmdsm_core *c, const uint8_t *frame, size_t n)
{
    if (c->ctl_count == DMDSM_CORE_CTL_SLOTS || n > DMDSM_CORE_CTL_FRAME) {
        c->count.ctl_dropped++;
        return;
    }
    unsigned slot = (c->ctl_head + c->ctl_count) % DMDSM_CORE_CTL_SLOTS;
    memcpy(c->ctl[slot], frame, n);
    c->ctl_len[slot] = n;
    c->ctl_count++;
    dmdsm_core_poll(c);
}

void dmdsm_core_log(struct dmdsm_core *c, uint8_t level, uint8_t code, const char *text)
{
    struct dmdsm_log m = {.level = level, .code = code, .text = (const uint8_t *)text,
                          .text_len = strlen(text)};
    uint8_t p[DMDSM_LOG_FIXED_SIZE + 200];
    uint8_t frame[DMDSM_CORE_CTL_FRAME];
    if (m.text_len > 200)
        m.text_len = 200;
    if (level >= DMDSM_LOG_LEVEL_ERROR && code != DMDSM_ERROR_NONE)
        c->last_error = code;
    size_t len = dmdsm_pack_log(&m, p);
    size_t n = dmdsm_frame_encode(frame, sizeof frame, DMDSM_MSG_LOG, 0, c->log_seq++, p, len);
    if (n)
        dmdsm_core_queue_ctl(c, frame, n);
}

static void reset_average(struct dmdsm_core *c)
{
    c->n_in_avg = 0;
    c->avg_phase_sum = 0;
    memset(c->avg_sync_steps, 0, sizeof c->avg_sync_steps);
    memset(c->acc, 0, sizeof c->acc[0] * c->cfg.n_samples);
}

bool dmdsm_core_arm(struct dmdsm_core *c, uint32_t n_shots)
{
    c->continuous = n_shots == 0;
    c->shots_remaining = n_shots;
    c->shot_id = 0;
    reset_average(c);
    c->last_edge = 0;
    c->laser_period = 0;
    c->state = DMDSM_STATE_ARMED;
    c->armed_at = dmdsm_core_now(c);
    c->ops->arm_capture(c->ops->ctx, &c->cfg);
    return true;
}

void dmdsm_core_stop(struct dmdsm_core *c)
{
    if (c->state == DMDSM_STATE_ARMED || c->state == DMDSM_STATE_CAPTURING)
        c->ops->disarm_capture(c->ops->ctx);
    reset_average(c); /* a partial average is discarded, never sent */
    c->shots_remaining = 0;
    c->continuous = false;
    c->state = c->wave_count ? DMDSM_STATE_SENDING : DMDSM_STATE_IDLE;
}

/* encode the finished average into the free waveform slot capture_done kept for it */
static void emit_waveform(struct dmdsm_core *c)
{
    const struct dmdsm_set_config *cfg = &c->cfg;
    uint32_t n_avg = c->n_in_avg;
    uint32_t id = c->shot_id++;
    unsigned slot = (c->wave_head + c->wave_count) % DMDSM_CORE_WAVE_SLOTS;
    struct dmdsm_waveform m = {
        .shot_id = id, .timestamp = c->avg_first_edge,
        .trigger_phase = (uint16_t)((c->avg_phase_sum + n_avg / 2u) / n_avg),
        .n_average = (uint16_t)n_avg, .pretrigger = cfg->pretrigger,
        .sample_rate_div = cfg->sample_rate_div, .sample_format = cfg->sample_format,
        .modality = cfg->modality, .triggers_skipped = c->count.triggers_skipped,
        .adc_overruns = c->count.adc_overruns, .integrity_faults = c->count.integrity_faults,
        .sync_steps = c->avg_sync_steps[DMDSM_SYNC_INPUT_X],
        .sync_steps_a = c->avg_sync_steps[DMDSM_SYNC_INPUT_A],
        .samples = NULL, .samples_len = 0};
    uint8_t head[DMDSM_WAVEFORM_FIXED_SIZE];
    struct dmdsm_encoder e;
    dmdsm_enc_begin(&e, c->wave[slot], sizeof c->wave[slot], DMDSM_MSG_WAVEFORM, 0,
                    c->wave_seq++);
    dmdsm_enc_write(&e, head, dmdsm_pack_waveform(&m, head));
    uint8_t chunk[128];
    size_t k = 0;
    for (uint32_t i = 0; i < cfg->n_samples; i++) {
        uint32_t v = c->acc[i];
        if (cfg->sample_format == DMDSM_SAMPLE_FORMAT_U16_MEAN) {
            v = (v + n_avg / 2u) / n_avg; /* mean, rounded to nearest */
            chunk[k++] = (uint8_t)v;
            chunk[k++] = (uint8_t)(v >> 8);
        } else {
            for (unsigned b = 0; b < 4; b++)
                chunk[k++] = (uint8_t)(v >> (8u * b));
        }
        if (k == sizeof chunk) {
            dmdsm_enc_write(&e, chunk, k);
            k = 0;
        }
    }
    dmdsm_enc_write(&e, chunk, k);
    c->wave_len[slot] = dmdsm_enc_end(&e);
    c->wave_count++;
    c->count.shots_sent++;
}

/* ticks the link takes for n bytes (0 when the board does not know its rate) */
static uint64_t wire_ticks(const struct dmdsm_core *c, size_t n)
{
    uint32_t rate = c->info->link_bytes_per_s;
    return rate ? ((uint64_t)n * c->info->tick_hz + rate - 1u) / rate : 0u;
}

/* A new average begun at this edge would wait on the board for the wire longer than one
 * laser period: skip the edge, a later one is ready as the wire frees. The waveform that
 * waits is then never more than one laser period old when it starts out, yet the wire
 * idles at no time (the edge skipped would have been followed by one ready in time). */
static bool too_early(const struct dmdsm_core *c, uint64_t edge, uint32_t period)
{
    if (c->wave_count == 0 || period == 0 || c->info->link_bytes_per_s == 0)
        return false;
    /* when the waiting waveform will be out: it is on the wire, or next after a control frame */
    uint64_t free_at = c->tx_end;
    if (!c->tx_wave)
        free_at = (c->tx_end > edge ? c->tx_end : edge) + wire_ticks(c, c->wave_len[c->wave_head]);
    uint64_t burst = (uint64_t)(c->cfg.n_samples - c->cfg.pretrigger) * c->cfg.sample_rate_div *
                     c->info->tick_hz / c->info->adc_rate_hz;
    uint64_t ready_by = edge + (uint64_t)c->cfg.n_average * period + burst;
    return ready_by < free_at;
}

/* the laser period (ticks) the core measures once an edge at `edge` is in */
static uint32_t period_after(const struct dmdsm_core *c, uint64_t edge)
{
    if (c->last_edge && edge > c->last_edge && edge - c->last_edge < c->info->tick_hz)
        return (uint32_t)(edge - c->last_edge);
    return c->laser_period;
}

/* a good burst at this edge would be skipped: no average is open and every slot waits for
 * the link, or the one waiting leaves too late (too_early) */
static bool skips(const struct dmdsm_core *c, uint64_t edge, uint32_t period)
{
    return c->n_in_avg == 0 &&
           (c->wave_count == DMDSM_CORE_WAVE_SLOTS || too_early(c, edge, period));
}

bool dmdsm_core_takes_shot(struct dmdsm_core *c, uint32_t edge_ticks)
{
    if (c->state != DMDSM_STATE_ARMED && c->state != DMDSM_STATE_CAPTURING)
        return false;
    uint64_t edge = dmdsm_core_extend(dmdsm_core_now(c), edge_ticks);
    return !skips(c, edge, period_after(c, edge));
}

void dmdsm_core_capture_done(struct dmdsm_core *c, const uint16_t *samples,
                             uint32_t edge_ticks, uint16_t phase, enum dmdsm_capture result)
{
    if (c->state != DMDSM_STATE_ARMED && c->state != DMDSM_STATE_CAPTURING)
        return; /* a late burst after disarm */
    c->count.triggers++;
    uint64_t edge = dmdsm_core_extend(dmdsm_core_now(c), edge_ticks);
    c->armed_at = edge;
    c->laser_period = period_after(c, edge);
    c->last_edge = edge;
    if (result == DMDSM_CAPTURE_OVERRUN) {
        c->count.adc_overruns++;
        c->last_error = DMDSM_ERROR_ADC_OVERRUN;
    } else if (result != DMDSM_CAPTURE_OK) { /* never averaged: its samples may be stale */
        c->count.integrity_faults++;
        c->last_error = DMDSM_ERROR_SAMPLE_INTEGRITY;
    } else if (skips(c, edge, c->laser_period)) {
        /* every slot still waits for the link (or the one waiting will be out only later
         * than a later shot could be ready): skip this shot rather than start an average
         * that could not be sent. Only this core fills the slots, so an average begun with
         * one free always has it when it ends: no waveform is ever dropped, and shot ids
         * count waveforms sent. */
        c->count.triggers_skipped++;
    } else {
        if (c->n_in_avg == 0)
            c->avg_first_edge = edge;
        for (uint32_t i = 0; i < c->cfg.n_samples; i++)
            c->acc[i] += samples[i];
        c->avg_phase_sum += phase;
        for (unsigned k = 0; k < DMDSM_SYNC_INPUTS; k++)
            c->avg_sync_steps[k] += dmdsm_core_sync_count_at(c, k, edge_ticks);
        if (++c->n_in_avg == c->cfg.n_average) {
            emit_waveform(c);
            reset_average(c);
            if (!c->continuous && --c->shots_remaining == 0) {
                c->ops->disarm_capture(c->ops->ctx);
                c->state = DMDSM_STATE_SENDING;
                dmdsm_core_poll(c);
                return;
            }
        }
    }
    c->ops->arm_capture(c->ops->ctx, &c->cfg);
    dmdsm_core_poll(c);
}

/* start the next transfer when the link is free: control frames first */
static void pump_tx(struct dmdsm_core *c)
{
    if (c->ops->tx_busy(c->ops->ctx))
        return;
    if (c->tx_ctl) {
        c->ctl_head = (c->ctl_head + 1) % DMDSM_CORE_CTL_SLOTS;
        c->ctl_count--;
        c->tx_ctl = false;
    }
    if (c->tx_wave) {
        c->wave_head = (c->wave_head + 1) % DMDSM_CORE_WAVE_SLOTS;
        c->wave_count--;
        c->tx_wave = false;
    }
    if (c->ctl_count) {
        c->tx_ctl = true;
        c->tx_end = dmdsm_core_now(c) + wire_ticks(c, c->ctl_len[c->ctl_head]);
        c->ops->tx_start(c->ops->ctx, c->ctl[c->ctl_head], c->ctl_len[c->ctl_head]);
    } else if (c->wave_count) {
        c->tx_wave = true;
        c->tx_end = dmdsm_core_now(c) + wire_ticks(c, c->wave_len[c->wave_head]);
        c->ops->tx_start(c->ops->ctx, c->wave[c->wave_head], c->wave_len[c->wave_head]);
    }
}

void dmdsm_core_poll(struct dmdsm_core *c)
{
    pump_tx(c);
    uint64_t now = dmdsm_core_now(c);
    if (c->state == DMDSM_STATE_ARMED && c->cfg.trigger_timeout_ms &&
        now - c->armed_at > (uint64_t)c->cfg.trigger_timeout_ms * c->info->tick_hz / 1000u) {
        c->ops->disarm_capture(c->ops->ctx);
        reset_average(c);
        c->state = DMDSM_STATE_IDLE;
        c->count.no_trigger_timeouts++;
        c->last_error = DMDSM_ERROR_NO_TRIGGER;
        dmdsm_core_log(c, DMDSM_LOG_LEVEL_WARNING, DMDSM_ERROR_NO_TRIGGER,
                       "no trigger within trigger_timeout_ms; disarmed");
    }
    if (c->state == DMDSM_STATE_SENDING && c->wave_count == 0)
        c->state = DMDSM_STATE_IDLE;
    dmdsm_core_sync_poll(c);
}

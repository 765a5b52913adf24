/* Command handling: decode host frames, validate, execute once, answer with one response. */
#include <string.h>

#include "core.h"

/* encode a response frame, remember it for retransmissions and queue it */
static void respond(struct dmdsm_core *c, uint8_t type, uint16_t seq,
                    const uint8_t *payload, size_t len)
{
    size_t n = dmdsm_frame_encode(c->last_resp, sizeof c->last_resp, type,
                                  DMDSM_FLAG_RESPONSE, seq, payload, len);
    c->have_last = n != 0;
    c->last_seq = seq;
    c->last_resp_len = n;
    if (n)
        dmdsm_core_queue_ctl(c, c->last_resp, n);
}

static void ack(struct dmdsm_core *c, const struct dmdsm_frame *f)
{
    struct dmdsm_ack m = {.command = f->type};
    uint8_t p[DMDSM_ACK_FIXED_SIZE];
    respond(c, DMDSM_MSG_ACK, f->seq, p, dmdsm_pack_ack(&m, p));
}

static void nak(struct dmdsm_core *c, const struct dmdsm_frame *f, uint8_t error,
                uint16_t detail)
{
    struct dmdsm_nak m = {.command = f->type, .error = error, .detail = detail};
    uint8_t p[DMDSM_NAK_FIXED_SIZE];
    c->last_error = error;
    respond(c, DMDSM_MSG_NAK, f->seq, p, dmdsm_pack_nak(&m, p));
}

/* 0 if cfg is acceptable, else 1 + index of the first offending field */
static unsigned check_config(const struct dmdsm_core *c, const struct dmdsm_set_config *cfg)
{
    unsigned bad = dmdsm_check_set_config(cfg);
    if (bad)
        return bad;
    if (cfg->n_samples > c->info->max_samples || cfg->n_samples > DMDSM_CORE_MAX_SAMPLES)
        return 1;
    if (cfg->pretrigger >= cfg->n_samples)
        return 4;
    if (cfg->trigger_edge > DMDSM_TRIGGER_EDGE_FALLING)
        return 5;
    if (cfg->modality > DMDSM_MODALITY_US)
        return 6;
    if (cfg->sample_format > DMDSM_SAMPLE_FORMAT_U32_SUM ||
        (cfg->sample_format == DMDSM_SAMPLE_FORMAT_U32_SUM &&
         (size_t)cfg->n_samples * 4u + DMDSM_WAVEFORM_FIXED_SIZE > DMDSM_MAX_PAYLOAD))
        return 7;
    return 0;
}

static void cmd_set_config(struct dmdsm_core *c, const struct dmdsm_frame *f)
{
    struct dmdsm_set_config cfg;
    dmdsm_unpack_set_config(f->payload, f->len, &cfg);
    if (c->state != DMDSM_STATE_IDLE) {
        nak(c, f, DMDSM_ERROR_BUSY, 0);
        return;
    }
    unsigned bad = check_config(c, &cfg);
    if (bad) {
        nak(c, f, DMDSM_ERROR_OUT_OF_RANGE, (uint16_t)bad);
        return;
    }
    c->cfg = cfg;
    ack(c, f);
}

static void cmd_identify(struct dmdsm_core *c, const struct dmdsm_frame *f)
{
    struct dmdsm_identify_reply m = {
        .protocol_version = DMDSM_PROTOCOL_VERSION,
        .fw_major = DMDSM_FW_MAJOR,
        .fw_minor = DMDSM_FW_MINOR,
        .fw_patch = DMDSM_FW_PATCH,
        .spec_hash = DMDSM_SPEC_HASH,
        .tick_hz = c->info->tick_hz,
        .adc_rate_hz = c->info->adc_rate_hz,
        .max_samples = c->info->max_samples < DMDSM_CORE_MAX_SAMPLES
                           ? c->info->max_samples : DMDSM_CORE_MAX_SAMPLES,
        .max_payload = DMDSM_MAX_PAYLOAD,
        .board = (const uint8_t *)c->info->name,
        .board_len = strlen(c->info->name),
    };
    if (m.board_len > 64)
        m.board_len = 64;
    uint8_t p[DMDSM_IDENTIFY_REPLY_FIXED_SIZE + 64];
    respond(c, DMDSM_MSG_IDENTIFY_REPLY, f->seq, p, dmdsm_pack_identify_reply(&m, p));
}

static void cmd_status(struct dmdsm_core *c, const struct dmdsm_frame *f)
{
    uint64_t ms = dmdsm_core_now(c) / (c->info->tick_hz / 1000u ? c->info->tick_hz / 1000u : 1u);
    struct dmdsm_status m = {
        .state = c->state,
        .last_error = c->last_error,
        .uptime_ms = (uint32_t)ms,
        .shots_remaining = c->continuous ? 0 : c->shots_remaining,
        .triggers = c->count.triggers,
        .shots_sent = c->count.shots_sent,
        .triggers_skipped = c->count.triggers_skipped,
        .adc_overruns = c->count.adc_overruns,
        .no_trigger_timeouts = c->count.no_trigger_timeouts,
        .rx_frames = c->count.rx_frames,
        .rx_crc_errors = c->rx.stats.crc_errors,
        .rx_malformed = c->rx.stats.malformed + c->rx.stats.bad_version,
        .rx_oversize = c->rx.stats.oversize,
        .integrity_faults = c->count.integrity_faults,
    };
    uint8_t p[DMDSM_STATUS_FIXED_SIZE];
    respond(c, DMDSM_MSG_STATUS, f->seq, p, dmdsm_pack_status(&m, p));
}

/* execute one decoded command frame */
static void execute(struct dmdsm_core *c, const struct dmdsm_frame *f)
{
    uint8_t p[DMDSM_CLOCK_SYNC_REPLY_FIXED_SIZE + DMDSM_CONFIG_FIXED_SIZE];
    switch (f->type) {
    case DMDSM_MSG_PING: {
        struct dmdsm_ping in;
        dmdsm_unpack_ping(f->payload, f->len, &in);
        struct dmdsm_pong m = {.nonce = in.nonce};
        respond(c, DMDSM_MSG_PONG, f->seq, p, dmdsm_pack_pong(&m, p));
        break;
    }
    case DMDSM_MSG_IDENTIFY:
        cmd_identify(c, f);
        break;
    case DMDSM_MSG_GET_CONFIG: {
        struct dmdsm_config m;
        memcpy(&m, &c->cfg, sizeof m); /* same fields, same order */
        respond(c, DMDSM_MSG_CONFIG, f->seq, p, dmdsm_pack_config(&m, p));
        break;
    }
    case DMDSM_MSG_SET_CONFIG:
        cmd_set_config(c, f);
        break;
    case DMDSM_MSG_ARM: {
        struct dmdsm_arm m;
        dmdsm_unpack_arm(f->payload, f->len, &m);
        if (c->state != DMDSM_STATE_IDLE)
            nak(c, f, DMDSM_ERROR_BUSY, 0);
        else if (c->info->capture_error != DMDSM_ERROR_NONE)
            nak(c, f, c->info->capture_error, 0); /* e.g. adc_failure: nothing would come */
        else if (dmdsm_core_arm(c, m.n_shots))
            ack(c, f);
        break;
    }
    case DMDSM_MSG_DISARM:
        dmdsm_core_stop(c);
        ack(c, f);
        break;
    case DMDSM_MSG_GET_STATUS:
        cmd_status(c, f);
        break;
    case DMDSM_MSG_CLOCK_SYNC: {
        struct dmdsm_clock_sync in;
        dmdsm_unpack_clock_sync(f->payload, f->len, &in);
        struct dmdsm_clock_sync_reply m = {.host_time_ns = in.host_time_ns,
                                           .device_ticks = dmdsm_core_now(c)};
        respond(c, DMDSM_MSG_CLOCK_SYNC_REPLY, f->seq, p,
                dmdsm_pack_clock_sync_reply(&m, p));
        break;
    }
    default: /* a device-to-host type sent to the device */
        nak(c, f, DMDSM_ERROR_UNKNOWN_TYPE, 0);
        break;
    }
}

void dmdsm_core_rx(struct dmdsm_core *c, const uint8_t *p, size_t n)
{
    struct dmdsm_frame f;
    for (size_t i = 0; i < n; i++) {
        enum dmdsm_rx r = dmdsm_decoder_feed(&c->rx, p[i], &f);
        if (r == DMDSM_RX_NONE || r == DMDSM_RX_CRC || r == DMDSM_RX_MALFORMED ||
            r == DMDSM_RX_OVERSIZE)
            continue; /* not answered: the host's timeout and retry cover it */
        c->count.rx_frames++;
        /* only a retransmission (flag set, same seq and type as the last command) is
         * answered from the cache: a new client's first command with an old seq runs */
        if (c->have_last && (f.flags & DMDSM_FLAG_RETRANSMIT) && f.seq == c->last_seq &&
            f.type == c->last_cmd) {
            dmdsm_core_queue_ctl(c, c->last_resp, c->last_resp_len); /* retransmission */
            continue;
        }
        c->last_cmd = f.type;
        if (r == DMDSM_RX_BAD_VERSION)
            nak(c, &f, DMDSM_ERROR_BAD_VERSION, 0);
        else if (r == DMDSM_RX_UNKNOWN_TYPE)
            nak(c, &f, DMDSM_ERROR_UNKNOWN_TYPE, 0);
        else if (r == DMDSM_RX_BAD_LENGTH)
            nak(c, &f, DMDSM_ERROR_BAD_LENGTH, 0);
        else
            execute(c, &f);
    }
}

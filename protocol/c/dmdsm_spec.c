/* Generated from protocol/messages.toml by protocol/gen_c.py: do not edit. */
/* The dmdsm protocol: message packing, checks and the CRC table. */

#include "dmdsm_spec.h"

#include <stdarg.h>
#include <stdio.h>
#include <string.h>

static void put_le(uint8_t *out, uint64_t v, unsigned n)
{
    for (unsigned i = 0; i < n; i++)
        out[i] = (uint8_t)(v >> (8u * i));
}

static uint64_t get_le(const uint8_t *p, unsigned n)
{
    uint64_t v = 0;
    for (unsigned i = 0; i < n; i++)
        v |= (uint64_t)p[i] << (8u * i);
    return v;
}

static uint32_t crc32_of(const uint8_t *p, size_t n)
{
    uint32_t c = 0xFFFFFFFFu;
    while (n--)
        c = dmdsm_crc32_table[(c ^ *p++) & 0xFFu] ^ (c >> 8);
    return c ^ 0xFFFFFFFFu;
}

struct writer {
    char *out;
    size_t cap;
    size_t len;
};

static void put(struct writer *w, const char *fmt, ...)
{
    va_list ap;
    va_start(ap, fmt);
    size_t room = w->len < w->cap ? w->cap - w->len : 0;
    int n = vsnprintf(room ? w->out + w->len : NULL, room, fmt, ap);
    va_end(ap);
    if (n > 0)
        w->len += (size_t)n;
}

static const struct dmdsm_msg_info infos[] = {
    {0x01, 1, 0, 4, 0x81, "ping"},
    {0x02, 1, 0, 0, 0x82, "identify"},
    {0x03, 1, 0, 0, 0x83, "get_config"},
    {0x04, 1, 0, 15, 0xf0, "set_config"},
    {0x05, 1, 0, 4, 0xf0, "arm"},
    {0x06, 1, 0, 0, 0xf0, "disarm"},
    {0x07, 1, 0, 0, 0x87, "get_status"},
    {0x08, 1, 0, 8, 0x88, "clock_sync"},
    {0x81, 0, 0, 4, 0x00, "pong"},
    {0x82, 0, 2, 24, 0x00, "identify_reply"},
    {0x83, 0, 0, 15, 0x00, "config"},
    {0x87, 0, 0, 50, 0x00, "status"},
    {0x88, 0, 0, 16, 0x00, "clock_sync_reply"},
    {0xf0, 0, 0, 1, 0x00, "ack"},
    {0xf1, 0, 0, 4, 0x00, "nak"},
    {0xa0, 0, 3, 42, 0x00, "waveform"},
    {0xa1, 0, 2, 2, 0x00, "log"},
    {0xa2, 0, 0, 25, 0x00, "motion_sync"},
};

const struct dmdsm_msg_info *dmdsm_msg_info(uint8_t type)
{
    for (size_t i = 0; i < sizeof infos / sizeof infos[0]; i++)
        if (infos[i].id == type)
            return &infos[i];
    return NULL;
}

bool dmdsm_payload_ok(uint8_t type, const uint8_t *payload, size_t len)
{
    const struct dmdsm_msg_info *mi = dmdsm_msg_info(type);
    if (mi == NULL || len < mi->fixed_size)
        return false;
    switch (type) {
    case 0xa0:
        switch (payload[20]) {
        case 0:
            return (len - mi->fixed_size) % 2u == 0;
        case 1:
            return (len - mi->fixed_size) % 4u == 0;
        default:
            return false;
        }
    default:
        return mi->tail_kind != 0 || len == mi->fixed_size;
    }
}

size_t dmdsm_pack_ping(const struct dmdsm_ping *m, uint8_t *out)
{
    put_le(out + 0, (uint64_t)(uint32_t)m->nonce, 4);
    return 4u;
}

bool dmdsm_unpack_ping(const uint8_t *p, size_t len, struct dmdsm_ping *m)
{
    if (!dmdsm_payload_ok(0x01, p, len))
        return false;
    m->nonce = (uint32_t)get_le(p + 0, 4);
    return true;
}

size_t dmdsm_pack_identify(const struct dmdsm_identify *m, uint8_t *out)
{
    (void)m;
    (void)out;
    return 0u;
}

bool dmdsm_unpack_identify(const uint8_t *p, size_t len, struct dmdsm_identify *m)
{
    if (!dmdsm_payload_ok(0x02, p, len))
        return false;
    m->unused_ = 0;
    return true;
}

size_t dmdsm_pack_get_config(const struct dmdsm_get_config *m, uint8_t *out)
{
    (void)m;
    (void)out;
    return 0u;
}

bool dmdsm_unpack_get_config(const uint8_t *p, size_t len, struct dmdsm_get_config *m)
{
    if (!dmdsm_payload_ok(0x03, p, len))
        return false;
    m->unused_ = 0;
    return true;
}

size_t dmdsm_pack_set_config(const struct dmdsm_set_config *m, uint8_t *out)
{
    put_le(out + 0, (uint64_t)(uint16_t)m->n_samples, 2);
    put_le(out + 2, (uint64_t)(uint16_t)m->sample_rate_div, 2);
    put_le(out + 4, (uint64_t)(uint16_t)m->n_average, 2);
    put_le(out + 6, (uint64_t)(uint16_t)m->pretrigger, 2);
    put_le(out + 8, (uint64_t)(uint8_t)m->trigger_edge, 1);
    put_le(out + 9, (uint64_t)(uint8_t)m->modality, 1);
    put_le(out + 10, (uint64_t)(uint8_t)m->sample_format, 1);
    put_le(out + 11, (uint64_t)(uint32_t)m->trigger_timeout_ms, 4);
    return 15u;
}

bool dmdsm_unpack_set_config(const uint8_t *p, size_t len, struct dmdsm_set_config *m)
{
    if (!dmdsm_payload_ok(0x04, p, len))
        return false;
    m->n_samples = (uint16_t)get_le(p + 0, 2);
    m->sample_rate_div = (uint16_t)get_le(p + 2, 2);
    m->n_average = (uint16_t)get_le(p + 4, 2);
    m->pretrigger = (uint16_t)get_le(p + 6, 2);
    m->trigger_edge = (uint8_t)get_le(p + 8, 1);
    m->modality = (uint8_t)get_le(p + 9, 1);
    m->sample_format = (uint8_t)get_le(p + 10, 1);
    m->trigger_timeout_ms = (uint32_t)get_le(p + 11, 4);
    return true;
}

unsigned dmdsm_check_set_config(const struct dmdsm_set_config *m)
{
    if (m->n_samples < 16u || m->n_samples > 8192u)
        return 1u;
    if (m->sample_rate_div < 1u || m->sample_rate_div > 1024u)
        return 2u;
    if (m->n_average < 1u || m->n_average > 4096u)
        return 3u;
    if (m->pretrigger > 8191u)
        return 4u;
    return 0;
}

size_t dmdsm_pack_arm(const struct dmdsm_arm *m, uint8_t *out)
{
    put_le(out + 0, (uint64_t)(uint32_t)m->n_shots, 4);
    return 4u;
}

bool dmdsm_unpack_arm(const uint8_t *p, size_t len, struct dmdsm_arm *m)
{
    if (!dmdsm_payload_ok(0x05, p, len))
        return false;
    m->n_shots = (uint32_t)get_le(p + 0, 4);
    return true;
}

size_t dmdsm_pack_disarm(const struct dmdsm_disarm *m, uint8_t *out)
{
    (void)m;
    (void)out;
    return 0u;
}

bool dmdsm_unpack_disarm(const uint8_t *p, size_t len, struct dmdsm_disarm *m)
{
    if (!dmdsm_payload_ok(0x06, p, len))
        return false;
    m->unused_ = 0;
    return true;
}

size_t dmdsm_pack_get_status(const struct dmdsm_get_status *m, uint8_t *out)
{
    (void)m;
    (void)out;
    return 0u;
}

bool dmdsm_unpack_get_status(const uint8_t *p, size_t len, struct dmdsm_get_status *m)
{
    if (!dmdsm_payload_ok(0x07, p, len))
        return false;
    m->unused_ = 0;
    return true;
}

size_t dmdsm_pack_clock_sync(const struct dmdsm_clock_sync *m, uint8_t *out)
{
    put_le(out + 0, (uint64_t)(uint64_t)m->host_time_ns, 8);
    return 8u;
}

bool dmdsm_unpack_clock_sync(const uint8_t *p, size_t len, struct dmdsm_clock_sync *m)
{
    if (!dmdsm_payload_ok(0x08, p, len))
        return false;
    m->host_time_ns = (uint64_t)get_le(p + 0, 8);
    return true;
}

size_t dmdsm_pack_pong(const struct dmdsm_pong *m, uint8_t *out)
{
    put_le(out + 0, (uint64_t)(uint32_t)m->nonce, 4);
    return 4u;
}

bool dmdsm_unpack_pong(const uint8_t *p, size_t len, struct dmdsm_pong *m)
{
    if (!dmdsm_payload_ok(0x81, p, len))
        return false;
    m->nonce = (uint32_t)get_le(p + 0, 4);
    return true;
}

size_t dmdsm_pack_identify_reply(const struct dmdsm_identify_reply *m, uint8_t *out)
{
    put_le(out + 0, (uint64_t)(uint8_t)m->protocol_version, 1);
    put_le(out + 1, (uint64_t)(uint8_t)m->fw_major, 1);
    put_le(out + 2, (uint64_t)(uint8_t)m->fw_minor, 1);
    put_le(out + 3, (uint64_t)(uint8_t)m->fw_patch, 1);
    put_le(out + 4, (uint64_t)(uint64_t)m->spec_hash, 8);
    put_le(out + 12, (uint64_t)(uint32_t)m->tick_hz, 4);
    put_le(out + 16, (uint64_t)(uint32_t)m->adc_rate_hz, 4);
    put_le(out + 20, (uint64_t)(uint16_t)m->max_samples, 2);
    put_le(out + 22, (uint64_t)(uint16_t)m->max_payload, 2);
    if (m->board_len)
        memcpy(out + 24, m->board, m->board_len);
    return 24u + m->board_len;
}

bool dmdsm_unpack_identify_reply(const uint8_t *p, size_t len, struct dmdsm_identify_reply *m)
{
    if (!dmdsm_payload_ok(0x82, p, len))
        return false;
    m->protocol_version = (uint8_t)get_le(p + 0, 1);
    m->fw_major = (uint8_t)get_le(p + 1, 1);
    m->fw_minor = (uint8_t)get_le(p + 2, 1);
    m->fw_patch = (uint8_t)get_le(p + 3, 1);
    m->spec_hash = (uint64_t)get_le(p + 4, 8);
    m->tick_hz = (uint32_t)get_le(p + 12, 4);
    m->adc_rate_hz = (uint32_t)get_le(p + 16, 4);
    m->max_samples = (uint16_t)get_le(p + 20, 2);
    m->max_payload = (uint16_t)get_le(p + 22, 2);
    m->board = p + 24;
    m->board_len = len - 24u;
    return true;
}

size_t dmdsm_pack_config(const struct dmdsm_config *m, uint8_t *out)
{
    put_le(out + 0, (uint64_t)(uint16_t)m->n_samples, 2);
    put_le(out + 2, (uint64_t)(uint16_t)m->sample_rate_div, 2);
    put_le(out + 4, (uint64_t)(uint16_t)m->n_average, 2);
    put_le(out + 6, (uint64_t)(uint16_t)m->pretrigger, 2);
    put_le(out + 8, (uint64_t)(uint8_t)m->trigger_edge, 1);
    put_le(out + 9, (uint64_t)(uint8_t)m->modality, 1);
    put_le(out + 10, (uint64_t)(uint8_t)m->sample_format, 1);
    put_le(out + 11, (uint64_t)(uint32_t)m->trigger_timeout_ms, 4);
    return 15u;
}

bool dmdsm_unpack_config(const uint8_t *p, size_t len, struct dmdsm_config *m)
{
    if (!dmdsm_payload_ok(0x83, p, len))
        return false;
    m->n_samples = (uint16_t)get_le(p + 0, 2);
    m->sample_rate_div = (uint16_t)get_le(p + 2, 2);
    m->n_average = (uint16_t)get_le(p + 4, 2);
    m->pretrigger = (uint16_t)get_le(p + 6, 2);
    m->trigger_edge = (uint8_t)get_le(p + 8, 1);
    m->modality = (uint8_t)get_le(p + 9, 1);
    m->sample_format = (uint8_t)get_le(p + 10, 1);
    m->trigger_timeout_ms = (uint32_t)get_le(p + 11, 4);
    return true;
}

size_t dmdsm_pack_status(const struct dmdsm_status *m, uint8_t *out)
{
    put_le(out + 0, (uint64_t)(uint8_t)m->state, 1);
    put_le(out + 1, (uint64_t)(uint8_t)m->last_error, 1);
    put_le(out + 2, (uint64_t)(uint32_t)m->uptime_ms, 4);
    put_le(out + 6, (uint64_t)(uint32_t)m->shots_remaining, 4);
    put_le(out + 10, (uint64_t)(uint32_t)m->triggers, 4);
    put_le(out + 14, (uint64_t)(uint32_t)m->shots_sent, 4);
    put_le(out + 18, (uint64_t)(uint32_t)m->triggers_skipped, 4);
    put_le(out + 22, (uint64_t)(uint32_t)m->adc_overruns, 4);
    put_le(out + 26, (uint64_t)(uint32_t)m->no_trigger_timeouts, 4);
    put_le(out + 30, (uint64_t)(uint32_t)m->rx_frames, 4);
    put_le(out + 34, (uint64_t)(uint32_t)m->rx_crc_errors, 4);
    put_le(out + 38, (uint64_t)(uint32_t)m->rx_malformed, 4);
    put_le(out + 42, (uint64_t)(uint32_t)m->rx_oversize, 4);
    put_le(out + 46, (uint64_t)(uint32_t)m->integrity_faults, 4);
    return 50u;
}

bool dmdsm_unpack_status(const uint8_t *p, size_t len, struct dmdsm_status *m)
{
    if (!dmdsm_payload_ok(0x87, p, len))
        return false;
    m->state = (uint8_t)get_le(p + 0, 1);
    m->last_error = (uint8_t)get_le(p + 1, 1);
    m->uptime_ms = (uint32_t)get_le(p + 2, 4);
    m->shots_remaining = (uint32_t)get_le(p + 6, 4);
    m->triggers = (uint32_t)get_le(p + 10, 4);
    m->shots_sent = (uint32_t)get_le(p + 14, 4);
    m->triggers_skipped = (uint32_t)get_le(p + 18, 4);
    m->adc_overruns = (uint32_t)get_le(p + 22, 4);
    m->no_trigger_timeouts = (uint32_t)get_le(p + 26, 4);
    m->rx_frames = (uint32_t)get_le(p + 30, 4);
    m->rx_crc_errors = (uint32_t)get_le(p + 34, 4);
    m->rx_malformed = (uint32_t)get_le(p + 38, 4);
    m->rx_oversize = (uint32_t)get_le(p + 42, 4);
    m->integrity_faults = (uint32_t)get_le(p + 46, 4);
    return true;
}

size_t dmdsm_pack_clock_sync_reply(const struct dmdsm_clock_sync_reply *m, uint8_t *out)
{
    put_le(out + 0, (uint64_t)(uint64_t)m->host_time_ns, 8);
    put_le(out + 8, (uint64_t)(uint64_t)m->device_ticks, 8);
    return 16u;
}

bool dmdsm_unpack_clock_sync_reply(const uint8_t *p, size_t len, struct dmdsm_clock_sync_reply *m)
{
    if (!dmdsm_payload_ok(0x88, p, len))
        return false;
    m->host_time_ns = (uint64_t)get_le(p + 0, 8);
    m->device_ticks = (uint64_t)get_le(p + 8, 8);
    return true;
}

size_t dmdsm_pack_ack(const struct dmdsm_ack *m, uint8_t *out)
{
    put_le(out + 0, (uint64_t)(uint8_t)m->command, 1);
    return 1u;
}

bool dmdsm_unpack_ack(const uint8_t *p, size_t len, struct dmdsm_ack *m)
{
    if (!dmdsm_payload_ok(0xf0, p, len))
        return false;
    m->command = (uint8_t)get_le(p + 0, 1);
    return true;
}

size_t dmdsm_pack_nak(const struct dmdsm_nak *m, uint8_t *out)
{
    put_le(out + 0, (uint64_t)(uint8_t)m->command, 1);
    put_le(out + 1, (uint64_t)(uint8_t)m->error, 1);
    put_le(out + 2, (uint64_t)(uint16_t)m->detail, 2);
    return 4u;
}

bool dmdsm_unpack_nak(const uint8_t *p, size_t len, struct dmdsm_nak *m)
{
    if (!dmdsm_payload_ok(0xf1, p, len))
        return false;
    m->command = (uint8_t)get_le(p + 0, 1);
    m->error = (uint8_t)get_le(p + 1, 1);
    m->detail = (uint16_t)get_le(p + 2, 2);
    return true;
}

size_t dmdsm_pack_waveform(const struct dmdsm_waveform *m, uint8_t *out)
{
    put_le(out + 0, (uint64_t)(uint32_t)m->shot_id, 4);
    put_le(out + 4, (uint64_t)(uint64_t)m->timestamp, 8);
    put_le(out + 12, (uint64_t)(uint16_t)m->trigger_phase, 2);
    put_le(out + 14, (uint64_t)(uint16_t)m->n_average, 2);
    put_le(out + 16, (uint64_t)(uint16_t)m->pretrigger, 2);
    put_le(out + 18, (uint64_t)(uint16_t)m->sample_rate_div, 2);
    put_le(out + 20, (uint64_t)(uint8_t)m->sample_format, 1);
    put_le(out + 21, (uint64_t)(uint8_t)m->modality, 1);
    put_le(out + 22, (uint64_t)(uint32_t)m->triggers_skipped, 4);
    put_le(out + 26, (uint64_t)(uint32_t)m->adc_overruns, 4);
    put_le(out + 30, (uint64_t)(uint32_t)m->integrity_faults, 4);
    put_le(out + 34, (uint64_t)(uint32_t)m->sync_steps, 4);
    put_le(out + 38, (uint64_t)(uint32_t)m->sync_steps_a, 4);
    if (m->samples_len)
        memcpy(out + 42, m->samples, m->samples_len);
    return 42u + m->samples_len;
}

bool dmdsm_unpack_waveform(const uint8_t *p, size_t len, struct dmdsm_waveform *m)
{
    if (!dmdsm_payload_ok(0xa0, p, len))
        return false;
    m->shot_id = (uint32_t)get_le(p + 0, 4);
    m->timestamp = (uint64_t)get_le(p + 4, 8);
    m->trigger_phase = (uint16_t)get_le(p + 12, 2);
    m->n_average = (uint16_t)get_le(p + 14, 2);
    m->pretrigger = (uint16_t)get_le(p + 16, 2);
    m->sample_rate_div = (uint16_t)get_le(p + 18, 2);
    m->sample_format = (uint8_t)get_le(p + 20, 1);
    m->modality = (uint8_t)get_le(p + 21, 1);
    m->triggers_skipped = (uint32_t)get_le(p + 22, 4);
    m->adc_overruns = (uint32_t)get_le(p + 26, 4);
    m->integrity_faults = (uint32_t)get_le(p + 30, 4);
    m->sync_steps = (uint32_t)get_le(p + 34, 4);
    m->sync_steps_a = (uint32_t)get_le(p + 38, 4);
    m->samples = p + 42;
    m->samples_len = len - 42u;
    return true;
}

size_t dmdsm_pack_log(const struct dmdsm_log *m, uint8_t *out)
{
    put_le(out + 0, (uint64_t)(uint8_t)m->level, 1);
    put_le(out + 1, (uint64_t)(uint8_t)m->code, 1);
    if (m->text_len)
        memcpy(out + 2, m->text, m->text_len);
    return 2u + m->text_len;
}

bool dmdsm_unpack_log(const uint8_t *p, size_t len, struct dmdsm_log *m)
{
    if (!dmdsm_payload_ok(0xa1, p, len))
        return false;
    m->level = (uint8_t)get_le(p + 0, 1);
    m->code = (uint8_t)get_le(p + 1, 1);
    m->text = p + 2;
    m->text_len = len - 2u;
    return true;
}

size_t dmdsm_pack_motion_sync(const struct dmdsm_motion_sync *m, uint8_t *out)
{
    put_le(out + 0, (uint64_t)(uint32_t)m->burst_id, 4);
    put_le(out + 4, (uint64_t)(uint64_t)m->first_edge, 8);
    put_le(out + 12, (uint64_t)(uint64_t)m->last_edge, 8);
    put_le(out + 20, (uint64_t)(uint32_t)m->edges, 4);
    put_le(out + 24, (uint64_t)(uint8_t)m->input, 1);
    return 25u;
}

bool dmdsm_unpack_motion_sync(const uint8_t *p, size_t len, struct dmdsm_motion_sync *m)
{
    if (!dmdsm_payload_ok(0xa2, p, len))
        return false;
    m->burst_id = (uint32_t)get_le(p + 0, 4);
    m->first_edge = (uint64_t)get_le(p + 4, 8);
    m->last_edge = (uint64_t)get_le(p + 12, 8);
    m->edges = (uint32_t)get_le(p + 20, 4);
    m->input = (uint8_t)get_le(p + 24, 1);
    return true;
}

int dmdsm_msg_format(uint8_t type, const uint8_t *payload, size_t len,
                     char *out, size_t cap)
{
    struct writer w = {out, cap, 0};
    if (cap)
        out[0] = '\0';
    if (!dmdsm_payload_ok(type, payload, len))
        return -1;
    switch (type) {
    case 0x01: {
        put(&w, "nonce=%llu ", (unsigned long long)get_le(payload + 0, 4));
        break;
    }
    case 0x02: {
        break;
    }
    case 0x03: {
        break;
    }
    case 0x04: {
        put(&w, "n_samples=%llu ", (unsigned long long)get_le(payload + 0, 2));
        put(&w, "sample_rate_div=%llu ", (unsigned long long)get_le(payload + 2, 2));
        put(&w, "n_average=%llu ", (unsigned long long)get_le(payload + 4, 2));
        put(&w, "pretrigger=%llu ", (unsigned long long)get_le(payload + 6, 2));
        put(&w, "trigger_edge=%llu ", (unsigned long long)get_le(payload + 8, 1));
        put(&w, "modality=%llu ", (unsigned long long)get_le(payload + 9, 1));
        put(&w, "sample_format=%llu ", (unsigned long long)get_le(payload + 10, 1));
        put(&w, "trigger_timeout_ms=%llu ", (unsigned long long)get_le(payload + 11, 4));
        break;
    }
    case 0x05: {
        put(&w, "n_shots=%llu ", (unsigned long long)get_le(payload + 0, 4));
        break;
    }
    case 0x06: {
        break;
    }
    case 0x07: {
        break;
    }
    case 0x08: {
        put(&w, "host_time_ns=%llu ", (unsigned long long)get_le(payload + 0, 8));
        break;
    }
    case 0x81: {
        put(&w, "nonce=%llu ", (unsigned long long)get_le(payload + 0, 4));
        break;
    }
    case 0x82: {
        put(&w, "protocol_version=%llu ", (unsigned long long)get_le(payload + 0, 1));
        put(&w, "fw_major=%llu ", (unsigned long long)get_le(payload + 1, 1));
        put(&w, "fw_minor=%llu ", (unsigned long long)get_le(payload + 2, 1));
        put(&w, "fw_patch=%llu ", (unsigned long long)get_le(payload + 3, 1));
        put(&w, "spec_hash=%llu ", (unsigned long long)get_le(payload + 4, 8));
        put(&w, "tick_hz=%llu ", (unsigned long long)get_le(payload + 12, 4));
        put(&w, "adc_rate_hz=%llu ", (unsigned long long)get_le(payload + 16, 4));
        put(&w, "max_samples=%llu ", (unsigned long long)get_le(payload + 20, 2));
        put(&w, "max_payload=%llu ", (unsigned long long)get_le(payload + 22, 2));
        put(&w, "board:len=%lu:crc=%08lx ", (unsigned long)(len - 24u),
            (unsigned long)crc32_of(payload + 24, len - 24u));
        break;
    }
    case 0x83: {
        put(&w, "n_samples=%llu ", (unsigned long long)get_le(payload + 0, 2));
        put(&w, "sample_rate_div=%llu ", (unsigned long long)get_le(payload + 2, 2));
        put(&w, "n_average=%llu ", (unsigned long long)get_le(payload + 4, 2));
        put(&w, "pretrigger=%llu ", (unsigned long long)get_le(payload + 6, 2));
        put(&w, "trigger_edge=%llu ", (unsigned long long)get_le(payload + 8, 1));
        put(&w, "modality=%llu ", (unsigned long long)get_le(payload + 9, 1));
        put(&w, "sample_format=%llu ", (unsigned long long)get_le(payload + 10, 1));
        put(&w, "trigger_timeout_ms=%llu ", (unsigned long long)get_le(payload + 11, 4));
        break;
    }
    case 0x87: {
        put(&w, "state=%llu ", (unsigned long long)get_le(payload + 0, 1));
        put(&w, "last_error=%llu ", (unsigned long long)get_le(payload + 1, 1));
        put(&w, "uptime_ms=%llu ", (unsigned long long)get_le(payload + 2, 4));
        put(&w, "shots_remaining=%llu ", (unsigned long long)get_le(payload + 6, 4));
        put(&w, "triggers=%llu ", (unsigned long long)get_le(payload + 10, 4));
        put(&w, "shots_sent=%llu ", (unsigned long long)get_le(payload + 14, 4));
        put(&w, "triggers_skipped=%llu ", (unsigned long long)get_le(payload + 18, 4));
        put(&w, "adc_overruns=%llu ", (unsigned long long)get_le(payload + 22, 4));
        put(&w, "no_trigger_timeouts=%llu ", (unsigned long long)get_le(payload + 26, 4));
        put(&w, "rx_frames=%llu ", (unsigned long long)get_le(payload + 30, 4));
        put(&w, "rx_crc_errors=%llu ", (unsigned long long)get_le(payload + 34, 4));
        put(&w, "rx_malformed=%llu ", (unsigned long long)get_le(payload + 38, 4));
        put(&w, "rx_oversize=%llu ", (unsigned long long)get_le(payload + 42, 4));
        put(&w, "integrity_faults=%llu ", (unsigned long long)get_le(payload + 46, 4));
        break;
    }
    case 0x88: {
        put(&w, "host_time_ns=%llu ", (unsigned long long)get_le(payload + 0, 8));
        put(&w, "device_ticks=%llu ", (unsigned long long)get_le(payload + 8, 8));
        break;
    }
    case 0xf0: {
        put(&w, "command=%llu ", (unsigned long long)get_le(payload + 0, 1));
        break;
    }
    case 0xf1: {
        put(&w, "command=%llu ", (unsigned long long)get_le(payload + 0, 1));
        put(&w, "error=%llu ", (unsigned long long)get_le(payload + 1, 1));
        put(&w, "detail=%llu ", (unsigned long long)get_le(payload + 2, 2));
        break;
    }
    case 0xa0: {
        put(&w, "shot_id=%llu ", (unsigned long long)get_le(payload + 0, 4));
        put(&w, "timestamp=%llu ", (unsigned long long)get_le(payload + 4, 8));
        put(&w, "trigger_phase=%llu ", (unsigned long long)get_le(payload + 12, 2));
        put(&w, "n_average=%llu ", (unsigned long long)get_le(payload + 14, 2));
        put(&w, "pretrigger=%llu ", (unsigned long long)get_le(payload + 16, 2));
        put(&w, "sample_rate_div=%llu ", (unsigned long long)get_le(payload + 18, 2));
        put(&w, "sample_format=%llu ", (unsigned long long)get_le(payload + 20, 1));
        put(&w, "modality=%llu ", (unsigned long long)get_le(payload + 21, 1));
        put(&w, "triggers_skipped=%llu ", (unsigned long long)get_le(payload + 22, 4));
        put(&w, "adc_overruns=%llu ", (unsigned long long)get_le(payload + 26, 4));
        put(&w, "integrity_faults=%llu ", (unsigned long long)get_le(payload + 30, 4));
        put(&w, "sync_steps=%llu ", (unsigned long long)get_le(payload + 34, 4));
        put(&w, "sync_steps_a=%llu ", (unsigned long long)get_le(payload + 38, 4));
        put(&w, "samples:len=%lu:crc=%08lx ", (unsigned long)(len - 42u),
            (unsigned long)crc32_of(payload + 42, len - 42u));
        break;
    }
    case 0xa1: {
        put(&w, "level=%llu ", (unsigned long long)get_le(payload + 0, 1));
        put(&w, "code=%llu ", (unsigned long long)get_le(payload + 1, 1));
        put(&w, "text:len=%lu:crc=%08lx ", (unsigned long)(len - 2u),
            (unsigned long)crc32_of(payload + 2, len - 2u));
        break;
    }
    case 0xa2: {
        put(&w, "burst_id=%llu ", (unsigned long long)get_le(payload + 0, 4));
        put(&w, "first_edge=%llu ", (unsigned long long)get_le(payload + 4, 8));
        put(&w, "last_edge=%llu ", (unsigned long long)get_le(payload + 12, 8));
        put(&w, "edges=%llu ", (unsigned long long)get_le(payload + 20, 4));
        put(&w, "input=%llu ", (unsigned long long)get_le(payload + 24, 1));
        break;
    }
    default:
        return -1;
    }
    if (w.len && w.len <= cap)
        out[w.len - 1] = '\0';
    return w.len ? (int)w.len - 1 : 0;
}

const uint32_t dmdsm_crc32_table[256] = {
    0x00000000u, 0x77073096u, 0xee0e612cu, 0x990951bau, 0x076dc419u, 0x706af48fu,
    0xe963a535u, 0x9e6495a3u, 0x0edb8832u, 0x79dcb8a4u, 0xe0d5e91eu, 0x97d2d988u,
    0x09b64c2bu, 0x7eb17cbdu, 0xe7b82d07u, 0x90bf1d91u, 0x1db71064u, 0x6ab020f2u,
    0xf3b97148u, 0x84be41deu, 0x1adad47du, 0x6ddde4ebu, 0xf4d4b551u, 0x83d385c7u,
    0x136c9856u, 0x646ba8c0u, 0xfd62f97au, 0x8a65c9ecu, 0x14015c4fu, 0x63066cd9u,
    0xfa0f3d63u, 0x8d080df5u, 0x3b6e20c8u, 0x4c69105eu, 0xd56041e4u, 0xa2677172u,
    0x3c03e4d1u, 0x4b04d447u, 0xd20d85fdu, 0xa50ab56bu, 0x35b5a8fau, 0x42b2986cu,
    0xdbbbc9d6u, 0xacbcf940u, 0x32d86ce3u, 0x45df5c75u, 0xdcd60dcfu, 0xabd13d59u,
    0x26d930acu, 0x51de003au, 0xc8d75180u, 0xbfd06116u, 0x21b4f4b5u, 0x56b3c423u,
    0xcfba9599u, 0xb8bda50fu, 0x2802b89eu, 0x5f058808u, 0xc60cd9b2u, 0xb10be924u,
    0x2f6f7c87u, 0x58684c11u, 0xc1611dabu, 0xb6662d3du, 0x76dc4190u, 0x01db7106u,
    0x98d220bcu, 0xefd5102au, 0x71b18589u, 0x06b6b51fu, 0x9fbfe4a5u, 0xe8b8d433u,
    0x7807c9a2u, 0x0f00f934u, 0x9609a88eu, 0xe10e9818u, 0x7f6a0dbbu, 0x086d3d2du,
    0x91646c97u, 0xe6635c01u, 0x6b6b51f4u, 0x1c6c6162u, 0x856530d8u, 0xf262004eu,
    0x6c0695edu, 0x1b01a57bu, 0x8208f4c1u, 0xf50fc457u, 0x65b0d9c6u, 0x12b7e950u,
    0x8bbeb8eau, 0xfcb9887cu, 0x62dd1ddfu, 0x15da2d49u, 0x8cd37cf3u, 0xfbd44c65u,
    0x4db26158u, 0x3ab551ceu, 0xa3bc0074u, 0xd4bb30e2u, 0x4adfa541u, 0x3dd895d7u,
    0xa4d1c46du, 0xd3d6f4fbu, 0x4369e96au, 0x346ed9fcu, 0xad678846u, 0xda60b8d0u,
    0x44042d73u, 0x33031de5u, 0xaa0a4c5fu, 0xdd0d7cc9u, 0x5005713cu, 0x270241aau,
    0xbe0b1010u, 0xc90c2086u, 0x5768b525u, 0x206f85b3u, 0xb966d409u, 0xce61e49fu,
    0x5edef90eu, 0x29d9c998u, 0xb0d09822u, 0xc7d7a8b4u, 0x59b33d17u, 0x2eb40d81u,
    0xb7bd5c3bu, 0xc0ba6cadu, 0xedb88320u, 0x9abfb3b6u, 0x03b6e20cu, 0x74b1d29au,
    0xead54739u, 0x9dd277afu, 0x04db2615u, 0x73dc1683u, 0xe3630b12u, 0x94643b84u,
    0x0d6d6a3eu, 0x7a6a5aa8u, 0xe40ecf0bu, 0x9309ff9du, 0x0a00ae27u, 0x7d079eb1u,
    0xf00f9344u, 0x8708a3d2u, 0x1e01f268u, 0x6906c2feu, 0xf762575du, 0x806567cbu,
    0x196c3671u, 0x6e6b06e7u, 0xfed41b76u, 0x89d32be0u, 0x10da7a5au, 0x67dd4accu,
    0xf9b9df6fu, 0x8ebeeff9u, 0x17b7be43u, 0x60b08ed5u, 0xd6d6a3e8u, 0xa1d1937eu,
    0x38d8c2c4u, 0x4fdff252u, 0xd1bb67f1u, 0xa6bc5767u, 0x3fb506ddu, 0x48b2364bu,
    0xd80d2bdau, 0xaf0a1b4cu, 0x36034af6u, 0x41047a60u, 0xdf60efc3u, 0xa867df55u,
    0x316e8eefu, 0x4669be79u, 0xcb61b38cu, 0xbc66831au, 0x256fd2a0u, 0x5268e236u,
    0xcc0c7795u, 0xbb0b4703u, 0x220216b9u, 0x5505262fu, 0xc5ba3bbeu, 0xb2bd0b28u,
    0x2bb45a92u, 0x5cb36a04u, 0xc2d7ffa7u, 0xb5d0cf31u, 0x2cd99e8bu, 0x5bdeae1du,
    0x9b64c2b0u, 0xec63f226u, 0x756aa39cu, 0x026d930au, 0x9c0906a9u, 0xeb0e363fu,
    0x72076785u, 0x05005713u, 0x95bf4a82u, 0xe2b87a14u, 0x7bb12baeu, 0x0cb61b38u,
    0x92d28e9bu, 0xe5d5be0du, 0x7cdcefb7u, 0x0bdbdf21u, 0x86d3d2d4u, 0xf1d4e242u,
    0x68ddb3f8u, 0x1fda836eu, 0x81be16cdu, 0xf6b9265bu, 0x6fb077e1u, 0x18b74777u,
    0x88085ae6u, 0xff0f6a70u, 0x66063bcau, 0x11010b5cu, 0x8f659effu, 0xf862ae69u,
    0x616bffd3u, 0x166ccf45u, 0xa00ae278u, 0xd70dd2eeu, 0x4e048354u, 0x3903b3c2u,
    0xa7672661u, 0xd06016f7u, 0x4969474du, 0x3e6e77dbu, 0xaed16a4au, 0xd9d65adcu,
    0x40df0b66u, 0x37d83bf0u, 0xa9bcae53u, 0xdebb9ec5u, 0x47b2cf7fu, 0x30b5ffe9u,
    0xbdbdf21cu, 0xcabac28au, 0x53b39330u, 0x24b4a3a6u, 0xbad03605u, 0xcdd70693u,
    0x54de5729u, 0x23d967bfu, 0xb3667a2eu, 0xc4614ab8u, 0x5d681b02u, 0x2a6f2b94u,
    0xb40bbe37u, 0xc30c8ea1u, 0x5a05df1bu, 0x2d02ef8du,
};

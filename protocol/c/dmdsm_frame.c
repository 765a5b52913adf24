/* dmdsm wire framing in C11: CRC-32, COBS, streaming encoder and decoder; no allocation. */
#include "dmdsm_frame.h"

#include <string.h>

#ifdef DMDSM_BOARD_CRC32
/* a board with a CRC unit names its zlib-compatible function here */
uint32_t DMDSM_BOARD_CRC32(uint32_t crc, const uint8_t *p, size_t n);
#endif

uint32_t dmdsm_crc32(uint32_t crc, const uint8_t *p, size_t n)
{
#ifdef DMDSM_BOARD_CRC32
    return DMDSM_BOARD_CRC32(crc, p, n);
#endif
    uint32_t c = crc ^ 0xFFFFFFFFu;
    while (n--)
        c = dmdsm_crc32_table[(c ^ *p++) & 0xFFu] ^ (c >> 8);
    return c ^ 0xFFFFFFFFu;
}

static void put_byte(struct dmdsm_encoder *e, uint8_t b)
{
    if (e->len < e->cap)
        e->out[e->len] = b;
    else
        e->overflow = true;
    e->len++;
}

/* close the current COBS group and open the next one */
static void close_group(struct dmdsm_encoder *e)
{
    if (e->code_pos < e->cap)
        e->out[e->code_pos] = e->code;
    e->code_pos = e->len;
    put_byte(e, 0); /* placeholder for the next code byte */
    e->code = 1;
}

static void stuff(struct dmdsm_encoder *e, const uint8_t *p, size_t n)
{
    for (size_t i = 0; i < n; i++) {
        if (e->code == 0xFF)
            close_group(e); /* a full group is closed only when more data follows */
        if (p[i] == 0) {
            close_group(e);
        } else {
            put_byte(e, p[i]);
            e->code++;
        }
    }
}

void dmdsm_enc_begin(struct dmdsm_encoder *e, uint8_t *out, size_t cap,
                     uint8_t type, uint8_t flags, uint16_t seq)
{
    uint8_t header[DMDSM_HEADER_SIZE] = {
        (uint8_t)DMDSM_PROTOCOL_VERSION, type, flags,
        (uint8_t)(seq & 0xFFu), (uint8_t)(seq >> 8)};
    e->out = out;
    e->cap = cap;
    e->len = 0;
    e->overflow = false;
    put_byte(e, 0); /* leading delimiter */
    e->code_pos = e->len;
    put_byte(e, 0);
    e->code = 1;
    e->crc = 0;
    dmdsm_enc_write(e, header, sizeof header);
}

void dmdsm_enc_write(struct dmdsm_encoder *e, const uint8_t *p, size_t n)
{
    e->crc = dmdsm_crc32(e->crc, p, n);
    stuff(e, p, n);
}

size_t dmdsm_enc_end(struct dmdsm_encoder *e)
{
    uint8_t crc[DMDSM_CRC_SIZE] = {
        (uint8_t)e->crc, (uint8_t)(e->crc >> 8),
        (uint8_t)(e->crc >> 16), (uint8_t)(e->crc >> 24)};
    stuff(e, crc, sizeof crc);
    if (e->code_pos < e->cap)
        e->out[e->code_pos] = e->code; /* the last group ends at the frame end */
    put_byte(e, 0); /* closing delimiter */
    return e->overflow ? 0 : e->len;
}

size_t dmdsm_frame_encode(uint8_t *out, size_t cap, uint8_t type, uint8_t flags,
                          uint16_t seq, const uint8_t *payload, size_t len)
{
    struct dmdsm_encoder e;
    dmdsm_enc_begin(&e, out, cap, type, flags, seq);
    dmdsm_enc_write(&e, payload, len);
    return dmdsm_enc_end(&e);
}

size_t dmdsm_cobs_decode(uint8_t *buf, size_t n)
{
    size_t in = 0, out = 0;
    while (in < n) {
        uint8_t code = buf[in++];
        size_t run = (size_t)code - 1u;
        if (code == 0 || run > n - in)
            return SIZE_MAX;
        memmove(buf + out, buf + in, run);
        out += run;
        in += run;
        if (in < n && code < 0xFF)
            buf[out++] = 0;
    }
    return out;
}

void dmdsm_decoder_init(struct dmdsm_decoder *d, uint8_t *buf, size_t cap)
{
    memset(d, 0, sizeof *d);
    d->buf = buf;
    d->cap = cap;
}

static enum dmdsm_rx finish(struct dmdsm_decoder *d, struct dmdsm_frame *f)
{
    size_t n = dmdsm_cobs_decode(d->buf, d->len);
    d->len = 0;
    if (n == SIZE_MAX || n < DMDSM_HEADER_SIZE + DMDSM_CRC_SIZE) {
        d->stats.malformed++;
        return DMDSM_RX_MALFORMED;
    }
    const uint8_t *b = d->buf;
    size_t body = n - DMDSM_CRC_SIZE;
    uint32_t crc = (uint32_t)b[body] | (uint32_t)b[body + 1] << 8 |
                   (uint32_t)b[body + 2] << 16 | (uint32_t)b[body + 3] << 24;
    if (dmdsm_crc32(0, b, body) != crc) {
        d->stats.crc_errors++;
        return DMDSM_RX_CRC;
    }
    /* the header is trustworthy from here on: fill it so a device can NAK */
    f->version = b[0];
    f->type = b[1];
    f->flags = b[2];
    f->seq = (uint16_t)(b[3] | b[4] << 8);
    f->payload = b + DMDSM_HEADER_SIZE;
    f->len = body - DMDSM_HEADER_SIZE;
    if (b[0] != DMDSM_PROTOCOL_VERSION) {
        d->stats.bad_version++;
        return DMDSM_RX_BAD_VERSION;
    }
    if (dmdsm_msg_info(b[1]) == NULL) {
        d->stats.unknown_type++;
        return DMDSM_RX_UNKNOWN_TYPE;
    }
    if (!dmdsm_payload_ok(f->type, f->payload, f->len)) {
        d->stats.malformed++;
        return DMDSM_RX_BAD_LENGTH;
    }
    d->stats.frames++;
    return DMDSM_RX_FRAME;
}

enum dmdsm_rx dmdsm_decoder_feed(struct dmdsm_decoder *d, uint8_t byte,
                                 struct dmdsm_frame *frame)
{
    if (byte == 0) {
        if (d->discarding) {
            d->discarding = false;
            return DMDSM_RX_NONE;
        }
        if (d->len == 0)
            return DMDSM_RX_NONE; /* empty frame: a second delimiter */
        return finish(d, frame);
    }
    if (d->discarding)
        return DMDSM_RX_NONE;
    if (d->len == d->cap) {
        d->len = 0;
        d->discarding = true;
        d->stats.oversize++;
        return DMDSM_RX_OVERSIZE;
    }
    d->buf[d->len++] = byte;
    return DMDSM_RX_NONE;
}

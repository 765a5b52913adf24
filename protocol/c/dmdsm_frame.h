/* dmdsm wire framing in C11: CRC-32, COBS, streaming encoder and decoder; no allocation. */
#ifndef DMDSM_FRAME_H
#define DMDSM_FRAME_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#include "dmdsm_spec.h" /* DMDSM_MAX_*, dmdsm_payload_ok */

/* A frame on the wire is 0x00 | COBS(header | payload | CRC-32) | 0x00, where
 * header = version u8, type u8, flags u8, seq u16 LE; CRC-32 (zlib) LE over
 * header+payload. Both delimiters are sent so a lost byte costs one frame. */

/* bytes a whole frame with this payload length takes on the wire */
#define DMDSM_WIRE_SIZE(payload_len) \
    (DMDSM_ENCODED_SIZE(DMDSM_HEADER_SIZE + (payload_len) + DMDSM_CRC_SIZE) + 2u)

/* zlib-compatible CRC-32: crc = dmdsm_crc32(0, p, n); chain by passing it back */
uint32_t dmdsm_crc32(uint32_t crc, const uint8_t *p, size_t n);

/* Incremental encoder: begin, write the payload in any number of pieces, end.
 * Lets the firmware send a header and DMA samples without copying them first. */
struct dmdsm_encoder {
    uint8_t *out;
    size_t cap;
    size_t len;      /* bytes written to out */
    size_t code_pos; /* index of the pending COBS code byte */
    uint8_t code;    /* value the pending code byte will get */
    bool overflow;   /* out was too small; end() returns 0 */
    uint32_t crc;    /* running CRC-32 of header and payload (pre-inverted) */
};

void dmdsm_enc_begin(struct dmdsm_encoder *e, uint8_t *out, size_t cap,
                     uint8_t type, uint8_t flags, uint16_t seq);
void dmdsm_enc_write(struct dmdsm_encoder *e, const uint8_t *p, size_t n);
/* appends the CRC and the closing delimiter; returns wire bytes or 0 on overflow */
size_t dmdsm_enc_end(struct dmdsm_encoder *e);
/* one-shot encode; returns wire bytes or 0 if out is too small */
size_t dmdsm_frame_encode(uint8_t *out, size_t cap, uint8_t type, uint8_t flags,
                          uint16_t seq, const uint8_t *payload, size_t len);

/* in-place COBS decode of n bytes (no zero inside); returns the decoded
 * length, or SIZE_MAX if a code byte runs past the end */
size_t dmdsm_cobs_decode(uint8_t *buf, size_t n);

/* result of feeding one byte */
enum dmdsm_rx {
    DMDSM_RX_NONE = 0,     /* nothing complete yet */
    DMDSM_RX_FRAME,        /* *frame is valid until the next feed */
    DMDSM_RX_CRC,          /* CRC-32 mismatch */
    DMDSM_RX_MALFORMED,    /* bad COBS, runt, or payload length wrong for type */
    DMDSM_RX_OVERSIZE,     /* longer than the buffer; discarded up to the next 0x00 */
    DMDSM_RX_UNKNOWN_TYPE, /* CRC good, type not in the spec */
    DMDSM_RX_BAD_VERSION,  /* CRC good, protocol version not ours */
    DMDSM_RX_BAD_LENGTH,   /* CRC good, payload length wrong for the type (counted
                            * as malformed) */
    /* UNKNOWN_TYPE, BAD_VERSION and BAD_LENGTH also fill *frame, so a
     * device can NAK them */
};

struct dmdsm_rx_stats {
    uint32_t frames;
    uint32_t crc_errors;
    uint32_t malformed;
    uint32_t oversize;
    uint32_t unknown_type;
    uint32_t bad_version;
};

struct dmdsm_frame {
    uint8_t version;
    uint8_t type;
    uint8_t flags;
    uint16_t seq;
    const uint8_t *payload;
    size_t len;
};

/* Streaming decoder over a caller-owned buffer of cap bytes; frames whose
 * COBS form is longer than cap are counted as oversize and skipped. */
struct dmdsm_decoder {
    uint8_t *buf;
    size_t cap;
    size_t len;
    bool discarding;
    struct dmdsm_rx_stats stats;
};

void dmdsm_decoder_init(struct dmdsm_decoder *d, uint8_t *buf, size_t cap);
enum dmdsm_rx dmdsm_decoder_feed(struct dmdsm_decoder *d, uint8_t byte,
                                 struct dmdsm_frame *frame);

#endif /* DMDSM_FRAME_H */

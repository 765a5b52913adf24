/* Unit tests of the C frame codec: CRC, COBS, encoder, decoder and the golden vectors. */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "dmdsm_frame.h"
#include "vectors.h"

#include "check.h" /* CHECK, failures */

static uint8_t out[DMDSM_WIRE_SIZE(DMDSM_MAX_PAYLOAD)];
static uint8_t rxbuf[DMDSM_MAX_ENCODED];

static void test_crc32(void)
{
    const uint8_t check[] = "123456789";
    CHECK(dmdsm_crc32(0, check, 9) == 0xCBF43926u);
    /* chaining equals one pass */
    CHECK(dmdsm_crc32(dmdsm_crc32(0, check, 4), check + 4, 5) == 0xCBF43926u);
    CHECK(dmdsm_crc32(0, check, 0) == 0);
}

/* decode a COBS test case and compare with the expected bytes */
static void cobs_case(const uint8_t *enc, size_t n, const uint8_t *dec, size_t m)
{
    uint8_t buf[600];
    memcpy(buf, enc, n);
    size_t got = dmdsm_cobs_decode(buf, n);
    CHECK(got == m);
    CHECK(got == m && memcmp(buf, dec, m) == 0);
}

static void test_cobs(void)
{
    cobs_case((const uint8_t *)"\x01\x01", 2, (const uint8_t *)"\x00", 1);
    cobs_case((const uint8_t *)"\x01\x01\x01", 3, (const uint8_t *)"\x00\x00", 2);
    cobs_case((const uint8_t *)"\x03\x11\x22\x02\x33", 5,
              (const uint8_t *)"\x11\x22\x00\x33", 4);
    cobs_case((const uint8_t *)"\x02\x11\x01\x01\x01", 5,
              (const uint8_t *)"\x11\x00\x00\x00", 4);
    uint8_t enc[300], dec[300];
    enc[0] = 0xFF;
    for (int i = 0; i < 254; i++)
        enc[1 + i] = dec[i] = (uint8_t)(i + 1);
    cobs_case(enc, 255, dec, 254); /* a full group adds no zero at the end */
    enc[255] = 0x02;
    enc[256] = 0x77;
    dec[254] = 0x77;
    cobs_case(enc, 257, dec, 255); /* nor between groups after 0xFF */
    uint8_t bad[] = {0x05, 0x11, 0x22};
    CHECK(dmdsm_cobs_decode(bad, sizeof bad) == SIZE_MAX);
}

/* encode then decode payloads of every length around the 254-byte group size */
static void test_roundtrip_lengths(void)
{
    static uint8_t payload[1100];
    struct dmdsm_decoder d;
    struct dmdsm_frame f;
    for (size_t len = 0; len < sizeof payload; len++) {
        for (size_t i = 0; i < len; i++)
            payload[i] = (uint8_t)((i * 7 + len) % 3 ? i * 13 + 1 : 0);
        if (len > 600)
            memset(payload, 0x55, len); /* long runs without zeros */
        size_t n = dmdsm_frame_encode(out, sizeof out, DMDSM_MSG_LOG, 0, (uint16_t)len,
                                      payload, len);
        CHECK(n == DMDSM_WIRE_SIZE(len) || n < DMDSM_WIRE_SIZE(len));
        CHECK(n >= len + 11);
        dmdsm_decoder_init(&d, rxbuf, sizeof rxbuf);
        size_t frames = 0;
        for (size_t i = 0; i < n; i++) {
            if (dmdsm_decoder_feed(&d, out[i], &f) == DMDSM_RX_FRAME) {
                frames++;
                CHECK(f.seq == (uint16_t)len);
                CHECK(f.len == len);
                CHECK(memcmp(f.payload, payload, len) == 0);
            }
        }
        CHECK(frames == (len >= 2 ? 1u : 0u)); /* log needs level and code */
    }
}

static void test_encoder_overflow(void)
{
    uint8_t small[8];
    uint8_t p[16] = {1};
    CHECK(dmdsm_frame_encode(small, sizeof small, 1, 0, 0, p, sizeof p) == 0);
    /* exact capacity works */
    size_t need = dmdsm_frame_encode(out, sizeof out, 1, 0, 0, p, 4);
    CHECK(dmdsm_frame_encode(small, need <= sizeof small ? need : 0, 1, 0, 0, p, 4) ==
          (need <= sizeof small ? need : 0));
}

static void test_oversize_resync(void)
{
    uint8_t buf[64];
    struct dmdsm_decoder d;
    struct dmdsm_frame f;
    dmdsm_decoder_init(&d, buf, sizeof buf);
    int oversize = 0;
    for (int i = 0; i < 1000; i++)
        oversize += dmdsm_decoder_feed(&d, 0x42, &f) == DMDSM_RX_OVERSIZE;
    CHECK(oversize == 1);
    CHECK(d.stats.oversize == 1);
    uint8_t p[4] = {1, 2, 3, 4};
    size_t n = dmdsm_frame_encode(out, sizeof out, DMDSM_MSG_PING, 0, 9, p, 4);
    int frames = 0;
    for (size_t i = 0; i < n; i++)
        frames += dmdsm_decoder_feed(&d, out[i], &f) == DMDSM_RX_FRAME;
    CHECK(frames == 1);
    CHECK(f.seq == 9);
}

static const char *rx_name(enum dmdsm_rx r)
{
    switch (r) {
    case DMDSM_RX_CRC: return "crc_errors";
    case DMDSM_RX_MALFORMED: return "malformed";
    case DMDSM_RX_BAD_LENGTH: return "malformed";
    case DMDSM_RX_OVERSIZE: return "oversize";
    case DMDSM_RX_UNKNOWN_TYPE: return "unknown_type";
    case DMDSM_RX_BAD_VERSION: return "bad_version";
    case DMDSM_RX_FRAME: return "frame";
    default: return "none";
    }
}

static void test_golden(const char *path)
{
    static struct vector v;
    static char text[VEC_MAX_TEXT];
    FILE *fp = fopen(path, "r");
    CHECK(fp != NULL);
    if (fp == NULL)
        return;
    int count = 0, r;
    while ((r = vector_next(fp, &v)) == 1) {
        struct dmdsm_decoder d;
        struct dmdsm_frame f;
        enum dmdsm_rx last = DMDSM_RX_NONE;
        dmdsm_decoder_init(&d, rxbuf, sizeof rxbuf);
        for (size_t i = 0; i < v.frame_len; i++) {
            enum dmdsm_rx x = dmdsm_decoder_feed(&d, v.frame[i], &f);
            if (x != DMDSM_RX_NONE)
                last = x;
        }
        count++;
        if (strcmp(v.type, "REJECT") == 0) {
            if (strcmp(rx_name(last), v.seq) != 0) {
                fprintf(stderr, "%s: got %s, want %s\n", v.name, rx_name(last), v.seq);
                failures++;
            }
            continue;
        }
        CHECK(last == DMDSM_RX_FRAME);
        if (last != DMDSM_RX_FRAME)
            continue;
        CHECK(f.type == (uint8_t)atoi(v.type));
        CHECK(f.seq == (uint16_t)atoi(v.seq));
        CHECK(f.flags == v.flags);
        CHECK(f.len == v.payload_len && memcmp(f.payload, v.payload, f.len) == 0);
        dmdsm_msg_format(f.type, f.payload, f.len, text, sizeof text);
        if (strcmp(text, v.fields) != 0) {
            fprintf(stderr, "%s: fields\n  C:  %s\n  py: %s\n", v.name, text, v.fields);
            failures++;
        }
        size_t n = dmdsm_frame_encode(out, sizeof out, f.type, f.flags, f.seq,
                                      v.payload, v.payload_len);
        if (n != v.frame_len || memcmp(out, v.frame, n) != 0) {
            fprintf(stderr, "%s: C encoding differs from the golden frame\n", v.name);
            failures++;
        }
    }
    CHECK(r == 0);
    CHECK(count >= 20);
    fclose(fp);
}

static void test_pack_unpack(void)
{
    struct dmdsm_set_config c = {.n_samples = 1024, .sample_rate_div = 1, .n_average = 16,
                                 .pretrigger = 64, .trigger_timeout_ms = 1000};
    uint8_t p[64];
    size_t n = dmdsm_pack_set_config(&c, p);
    CHECK(n == DMDSM_SET_CONFIG_FIXED_SIZE);
    struct dmdsm_set_config back;
    CHECK(dmdsm_unpack_set_config(p, n, &back));
    CHECK(back.n_samples == 1024 && back.trigger_timeout_ms == 1000);
    CHECK(!dmdsm_unpack_set_config(p, n - 1, &back));
    CHECK(dmdsm_check_set_config(&c) == 0);
    c.n_samples = 8;
    CHECK(dmdsm_check_set_config(&c) == 1);
    c.n_samples = 1024;
    c.n_average = 0;
    CHECK(dmdsm_check_set_config(&c) == 3);
    CHECK(dmdsm_msg_info(0x7E) == NULL);
    CHECK(dmdsm_msg_info(DMDSM_MSG_PING)->reply == DMDSM_MSG_PONG);
}

int main(int argc, char **argv)
{
    test_crc32();
    test_cobs();
    test_roundtrip_lengths();
    test_encoder_overflow();
    test_oversize_resync();
    test_pack_unpack();
    test_golden(argc > 1 ? argv[1] : "protocol/vectors/golden.txt");
    if (failures) {
        fprintf(stderr, "test_frame: %d check(s) failed\n", failures);
        return 1;
    }
    printf("test_frame: all checks passed\n");
    return 0;
}

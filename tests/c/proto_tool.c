/* Drives the C codec from the Python tests: `decode [cap]` a byte stream, `encode` lines. */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "dmdsm_frame.h"

static uint8_t rxbuf[DMDSM_MAX_ENCODED];
static uint8_t out[DMDSM_WIRE_SIZE(DMDSM_MAX_PAYLOAD)];
static char text[65536];

static const char *kind(enum dmdsm_rx r)
{
    switch (r) {
    case DMDSM_RX_CRC: return "crc_errors";
    case DMDSM_RX_MALFORMED: return "malformed";
    case DMDSM_RX_BAD_LENGTH: return "malformed";
    case DMDSM_RX_OVERSIZE: return "oversize";
    case DMDSM_RX_UNKNOWN_TYPE: return "unknown_type";
    case DMDSM_RX_BAD_VERSION: return "bad_version";
    default: return "?";
    }
}

/* one line per decoded frame or rejected frame, then the counters */
static int decode(size_t cap)
{
    struct dmdsm_decoder d;
    struct dmdsm_frame f;
    if (cap == 0 || cap > sizeof rxbuf)
        cap = sizeof rxbuf;
    dmdsm_decoder_init(&d, rxbuf, cap);
    int c;
    while ((c = getchar()) != EOF) {
        enum dmdsm_rx r = dmdsm_decoder_feed(&d, (uint8_t)c, &f);
        if (r == DMDSM_RX_FRAME) {
            dmdsm_msg_format(f.type, f.payload, f.len, text, sizeof text);
            printf("FRAME %u %u %u %s\n", f.type, f.seq, f.flags, text);
        } else if (r != DMDSM_RX_NONE) {
            printf("ERR %s\n", kind(r));
        }
    }
    printf("STATS frames=%lu crc_errors=%lu malformed=%lu oversize=%lu "
           "unknown_type=%lu bad_version=%lu\n",
           (unsigned long)d.stats.frames, (unsigned long)d.stats.crc_errors,
           (unsigned long)d.stats.malformed, (unsigned long)d.stats.oversize,
           (unsigned long)d.stats.unknown_type, (unsigned long)d.stats.bad_version);
    return 0;
}

/* "type seq flags payload_hex" per line -> frame hex per line */
static int encode(void)
{
    static char line[2 * DMDSM_MAX_PAYLOAD + 64];
    static uint8_t payload[DMDSM_MAX_PAYLOAD];
    while (fgets(line, sizeof line, stdin) != NULL) {
        unsigned type, seq, flags;
        int pos = 0;
        if (sscanf(line, "%u %u %u %n", &type, &seq, &flags, &pos) != 3)
            return 2;
        size_t n = 0;
        unsigned b;
        while (n < sizeof payload && sscanf(line + pos, "%2x", &b) == 1) {
            payload[n++] = (uint8_t)b;
            pos += 2;
        }
        size_t w = dmdsm_frame_encode(out, sizeof out, (uint8_t)type, (uint8_t)flags,
                                      (uint16_t)seq, payload, n);
        for (size_t i = 0; i < w; i++)
            printf("%02x", out[i]);
        printf("\n");
    }
    return 0;
}

int main(int argc, char **argv)
{
    if (argc > 1 && strcmp(argv[1], "decode") == 0)
        return decode(argc > 2 ? (size_t)strtoul(argv[2], NULL, 10) : 0);
    if (argc > 1 && strcmp(argv[1], "encode") == 0)
        return encode();
    fprintf(stderr, "usage: proto_tool decode [cap] | encode\n");
    return 2;
}

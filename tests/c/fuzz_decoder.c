/* libFuzzer target: the C decoder must never crash, overrun or accept a bad frame. */
#include <stdlib.h>
#include <string.h>

#include "dmdsm_frame.h"

static uint8_t rxbuf[1024];
static uint8_t rxbuf2[DMDSM_ENCODED_SIZE(1024 + 9)];
static uint8_t re[DMDSM_WIRE_SIZE(1024)];

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size);

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    struct dmdsm_decoder d;
    struct dmdsm_frame f;
    static char text[4096];
    dmdsm_decoder_init(&d, rxbuf, sizeof rxbuf);
    for (size_t i = 0; i < size; i++) {
        if (dmdsm_decoder_feed(&d, data[i], &f) != DMDSM_RX_FRAME)
            continue;
        /* every accepted frame re-encodes to a frame that decodes the same */
        if (f.len > sizeof rxbuf || !dmdsm_payload_ok(f.type, f.payload, f.len))
            abort();
        dmdsm_msg_format(f.type, f.payload, f.len, text, sizeof text);
        size_t n = dmdsm_frame_encode(re, sizeof re, f.type, f.flags, f.seq,
                                      f.payload, f.len);
        if (n == 0 || n > DMDSM_WIRE_SIZE(f.len))
            abort();
        struct dmdsm_decoder d2;
        struct dmdsm_frame f2;
        enum dmdsm_rx r = DMDSM_RX_NONE;
        dmdsm_decoder_init(&d2, rxbuf2, sizeof rxbuf2);
        for (size_t k = 0; k < n && r == DMDSM_RX_NONE; k++)
            r = dmdsm_decoder_feed(&d2, re[k], &f2);
        if (r != DMDSM_RX_FRAME || f2.type != f.type || f2.seq != f.seq ||
            f2.len != f.len || memcmp(f2.payload, f.payload, f.len) != 0)
            abort();
    }
    if (d.len > d.cap)
        abort();
    return 0;
}

/* Reads protocol/vectors/golden.txt for the C tests (one vector per line, '|' separated). */
#ifndef TEST_VECTORS_H
#define TEST_VECTORS_H

#include <stddef.h>
#include <stdint.h>

#define VEC_MAX_BYTES 20000
#define VEC_MAX_TEXT 1024

struct vector {
    char name[64];
    char type[16];  /* decimal type id, or REJECT */
    char seq[32];   /* decimal seq, or the counter a REJECT must bump */
    unsigned flags;
    uint8_t payload[VEC_MAX_BYTES];
    size_t payload_len;
    uint8_t frame[VEC_MAX_BYTES];
    size_t frame_len;
    char fields[VEC_MAX_TEXT];
};

/* next vector from f; 1 if read, 0 at end, -1 on a malformed line */
int vector_next(void *file, struct vector *v);

#endif

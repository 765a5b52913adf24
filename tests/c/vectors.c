/* Reads protocol/vectors/golden.txt for the C tests (one vector per line, '|' separated). */
#include "vectors.h"

#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static int hex_to_bytes(const char *hex, uint8_t *out, size_t cap, size_t *len)
{
    size_t n = strlen(hex);
    if (n % 2 || n / 2 > cap)
        return -1;
    for (size_t i = 0; i < n / 2; i++) {
        unsigned b;
        if (sscanf(hex + 2 * i, "%2x", &b) != 1)
            return -1;
        out[i] = (uint8_t)b;
    }
    *len = n / 2;
    return 0;
}

static void copy_field(char *dst, size_t cap, const char *src)
{
    snprintf(dst, cap, "%s", src);
}

int vector_next(void *file, struct vector *v)
{
    static char line[3 * VEC_MAX_BYTES + VEC_MAX_TEXT];
    for (;;) {
        if (fgets(line, sizeof line, (FILE *)file) == NULL)
            return 0;
        if (line[0] != '#' && line[0] != '\n')
            break;
    }
    line[strcspn(line, "\r\n")] = '\0';
    char *cols[7];
    int n = 0;
    char *p = line;
    cols[n++] = p;
    while (n < 7 && (p = strchr(p, '|')) != NULL) {
        *p++ = '\0';
        cols[n++] = p;
    }
    if (n != 7)
        return -1;
    copy_field(v->name, sizeof v->name, cols[0]);
    copy_field(v->type, sizeof v->type, cols[1]);
    copy_field(v->seq, sizeof v->seq, cols[2]);
    v->flags = (unsigned)strtoul(cols[3], NULL, 10);
    copy_field(v->fields, sizeof v->fields, cols[6]);
    if (hex_to_bytes(cols[4], v->payload, sizeof v->payload, &v->payload_len) ||
        hex_to_bytes(cols[5], v->frame, sizeof v->frame, &v->frame_len))
        return -1;
    return 1;
}

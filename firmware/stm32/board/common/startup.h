/* Interface between the common startup code and each ARM board. */
#ifndef DMDSM_STARTUP_H
#define DMDSM_STARTUP_H

#include <stdint.h>

#define FAULT_MAGIC 0xFA17EDu

struct fault_record {
    uint32_t magic;
    uint32_t pc, lr, cfsr, hfsr, bfar;
};

/* called first in Reset_Handler, before .data/.bss exist (errata, clocks that must be early) */
void board_early_init(void);
/* 1 and the record if the previous run ended in a HardFault (cleared once taken) */
int fault_take(struct fault_record *out);

#define FAULT_TEXT_SIZE 96
/* "reset after HardFault: pc=... lr=... cfsr=... hfsr=..." without printf */
void fault_format(const struct fault_record *f, char out[FAULT_TEXT_SIZE]);

void Reset_Handler(void);
void HardFault_Handler(void);
void Default_Handler(void);
void fault_capture(const uint32_t *frame);

#endif

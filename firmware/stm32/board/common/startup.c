/* Reset handler and vector-table entries common to the ARM boards: data/bss init, FPU, faults. */
#include <stdint.h>
#include <string.h>

#include "armv7m.h"
#include "startup.h"

extern uint32_t _sidata, _sdata, _edata, _sbss, _ebss, _estack;
int main(void);

/* survives a reset (NOLOAD section): why the last run ended */
__attribute__((section(".noinit"))) struct fault_record fault_record;

void Reset_Handler(void)
{
    board_early_init();
    size_t data = (size_t)((uintptr_t)&_edata - (uintptr_t)&_sdata);
    size_t bss = (size_t)((uintptr_t)&_ebss - (uintptr_t)&_sbss);
    memcpy(&_sdata, &_sidata, data);
    memset(&_sbss, 0, bss);
    SCB_CPACR |= 0xFu << 20; /* CP10/CP11 full access: the FPU */
    dsb();
    isb();
    main();
    for (;;) {
    }
}

/* record the stacked PC and fault status, then reset; reported after boot */
void fault_capture(const uint32_t *frame)
{
    fault_record.magic = FAULT_MAGIC;
    fault_record.pc = frame[6];
    fault_record.lr = frame[5];
    fault_record.cfsr = SCB_CFSR;
    fault_record.hfsr = SCB_HFSR;
    fault_record.bfar = SCB_BFAR;
    system_reset();
}

__attribute__((naked)) void HardFault_Handler(void)
{
    __asm__ volatile(
        "tst lr, #4\n"
        "ite eq\n"
        "mrseq r0, msp\n"
        "mrsne r0, psp\n"
        "b fault_capture\n");
}

void Default_Handler(void)
{
    for (;;) {
    }
}

int fault_take(struct fault_record *out)
{
    if (fault_record.magic != FAULT_MAGIC)
        return 0;
    *out = fault_record;
    fault_record.magic = 0;
    return 1;
}

static char *put_hex(char *p, const char *label, uint32_t v)
{
    while (*label)
        *p++ = *label++;
    for (int i = 7; i >= 0; i--)
        *p++ = "0123456789abcdef"[(v >> (4 * i)) & 0xFu];
    return p;
}

void fault_format(const struct fault_record *f, char out[FAULT_TEXT_SIZE])
{
    char *p = out;
    p = put_hex(p, "reset after HardFault: pc=", f->pc);
    p = put_hex(p, " lr=", f->lr);
    p = put_hex(p, " cfsr=", f->cfsr);
    p = put_hex(p, " hfsr=", f->hfsr);
    *p = '\0';
}

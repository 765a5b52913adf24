/* Caches and MPU of the NUCLEO board, set up as ST recommends: a background MPU region, then the I- and D-cache. */
#include "armv7m.h"
#include "nucleo.h"

/*
 * ST's usual MPU_Config (AN4838, the CubeH7 examples): region 0 covers the
 * whole 4 GiB as no access, execute-never, strongly ordered (TEX 0, C 0, B 0)
 * and shareable, with sub-regions 0, 1, 2 and 7 disabled (SRD 0x87), so it
 * applies only to 0x60000000-0xDFFFFFFF, the external-memory windows (FMC,
 * QUADSPI) this board has nothing behind. The Cortex-M7 may read normal memory
 * speculatively; without this region it could start a read there. Flash, the
 * TCMs, AXI SRAM, SRAM1-4, the peripherals and the system space keep the
 * default map (PRIVDEFENA). MemManage stays disabled, so an access to the
 * region escalates to HardFault, which records it and resets (startup.c).
 */
void mpu_config(void)
{
    if (MPU_TYPE_DREGION(MPU_TYPE) == 0)
        return; /* no MPU (not on an H743) */
    dmb();
    MPU_CTRL = 0; /* regions are changed with the MPU off */
    MPU_RNR = 0;
    MPU_RBAR = 0x00000000u;
    MPU_RASR = MPU_RASR_XN | MPU_RASR_AP_NONE | MPU_RASR_TEX(0) | MPU_RASR_S |
               MPU_RASR_SRD(0x87u) | MPU_RASR_SIZE(32u) | MPU_RASR_ENABLE;
    MPU_CTRL = MPU_CTRL_PRIVDEFENA | MPU_CTRL_ENABLE;
    dsb();
    isb();
}

/* ST's SCB_EnableICache, then SCB_EnableDCache: invalidate all by set/way first */
void caches_enable(void)
{
    dsb();
    isb();
    SCB_ICIALLU = 0;
    dsb();
    isb();
    SCB_CCR |= SCB_CCR_IC;
    dsb();
    isb();

    SCB_CSSELR = 0; /* L1 data cache */
    dsb();
    uint32_t ccsidr = SCB_CCSIDR;
    uint32_t sets = ((ccsidr >> 13) & 0x7FFFu) + 1u;
    uint32_t ways = ((ccsidr >> 3) & 0x3FFu) + 1u;
    for (uint32_t s = 0; s < sets; s++)
        for (uint32_t w = 0; w < ways; w++)
            SCB_DCISW = (s << 5) | (w << 30); /* 32-byte lines, 4 ways: H743's L1 */
    dsb();
    SCB_CCR |= SCB_CCR_DC;
    dsb();
    isb();
}

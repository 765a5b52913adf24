/* Cortex-M7 core registers shared by the ARM boards (SCB, SysTick, NVIC, MPU, cache), from the ARMv7-M ARM. */
#ifndef DMDSM_ARMV7M_H
#define DMDSM_ARMV7M_H

#include <stdint.h>

#define REG32(addr) (*(volatile uint32_t *)(addr))

/* System control block */
#define SCB_CPUID REG32(0xE000ED00u)
#define SCB_ICSR REG32(0xE000ED04u)
#define SCB_VTOR REG32(0xE000ED08u)
#define SCB_AIRCR REG32(0xE000ED0Cu)
#define SCB_CCR REG32(0xE000ED14u)
#define SCB_CFSR REG32(0xE000ED28u)
#define SCB_HFSR REG32(0xE000ED2Cu)
#define SCB_MMFAR REG32(0xE000ED34u)
#define SCB_BFAR REG32(0xE000ED38u)
#define SCB_CPACR REG32(0xE000ED88u)
#define SCB_ICSR_PENDSTSET (1u << 26)
#define SCB_AIRCR_VECTKEY (0x05FAu << 16)
#define SCB_AIRCR_SYSRESETREQ (1u << 2)
#define SCB_CCR_DC (1u << 16)
#define SCB_CCR_IC (1u << 17)

/* cache maintenance by address (write-only) and the cache size registers */
#define SCB_CSSELR REG32(0xE000ED84u)
#define SCB_CCSIDR REG32(0xE000ED80u)
#define SCB_ICIALLU REG32(0xE000EF50u)
#define SCB_DCIMVAC REG32(0xE000EF5Cu)
#define SCB_DCISW REG32(0xE000EF60u)
#define SCB_DCCMVAC REG32(0xE000EF68u)
#define SCB_DCCIMVAC REG32(0xE000EF70u)
#define DCACHE_LINE 32u

/* MPU (ARMv7-M B3.5): region number, base and attributes/size of the selected region */
#define MPU_TYPE REG32(0xE000ED90u)
#define MPU_CTRL REG32(0xE000ED94u)
#define MPU_RNR REG32(0xE000ED98u)
#define MPU_RBAR REG32(0xE000ED9Cu)
#define MPU_RASR REG32(0xE000EDA0u)
#define MPU_TYPE_DREGION(t) (((t) >> 8) & 0xFFu) /* data regions; 0: no MPU */
#define MPU_CTRL_ENABLE (1u << 0)
#define MPU_CTRL_PRIVDEFENA (1u << 2) /* the default map where no region matches */
#define MPU_RASR_ENABLE (1u << 0)
#define MPU_RASR_SIZE(log2_bytes) (((log2_bytes) - 1u) << 1) /* region of 2^log2 bytes */
#define MPU_RASR_SRD(mask) ((uint32_t)(mask) << 8) /* sub-regions (eighths) disabled */
#define MPU_RASR_B (1u << 16)
#define MPU_RASR_C (1u << 17)
#define MPU_RASR_S (1u << 18)
#define MPU_RASR_TEX(t) ((uint32_t)(t) << 19)
#define MPU_RASR_AP_NONE (0u << 24) /* no access, privileged or not */
#define MPU_RASR_XN (1u << 28)

/* SysTick */
#define SYST_CSR REG32(0xE000E010u)
#define SYST_RVR REG32(0xE000E014u)
#define SYST_CVR REG32(0xE000E018u)
#define SYST_CSR_ENABLE (1u << 0)
#define SYST_CSR_TICKINT (1u << 1)
#define SYST_CSR_CLKSOURCE (1u << 2)

/* NVIC */
#define NVIC_ISER(n) REG32(0xE000E100u + 4u * (n))
#define NVIC_ICER(n) REG32(0xE000E180u + 4u * (n))
#define NVIC_IPR8(n) (*(volatile uint8_t *)(0xE000E400u + (n)))

static inline void nvic_enable(unsigned irq)
{
    NVIC_ISER(irq / 32u) = 1u << (irq % 32u);
}

static inline void dmb(void) { __asm__ volatile("dmb 0xF" ::: "memory"); }
static inline void dsb(void) { __asm__ volatile("dsb 0xF" ::: "memory"); }
static inline void isb(void) { __asm__ volatile("isb 0xF" ::: "memory"); }
static inline void irq_disable(void) { __asm__ volatile("cpsid i" ::: "memory"); }
static inline void irq_enable(void) { __asm__ volatile("cpsie i" ::: "memory"); }

/* write back the D-cache lines of [p, p+n) before a DMA reads them */
static inline void dcache_clean(const void *p, uint32_t n)
{
    uintptr_t a = (uintptr_t)p & ~(uintptr_t)(DCACHE_LINE - 1u);
    uintptr_t end = (uintptr_t)p + n;
    dsb();
    for (; a < end; a += DCACHE_LINE)
        SCB_DCCMVAC = (uint32_t)a;
    dsb();
    isb();
}

/* drop the D-cache lines of [p, p+n) after a DMA wrote them (32-byte aligned buffers only) */
static inline void dcache_invalidate(const void *p, uint32_t n)
{
    uintptr_t a = (uintptr_t)p & ~(uintptr_t)(DCACHE_LINE - 1u);
    uintptr_t end = (uintptr_t)p + n;
    dsb();
    for (; a < end; a += DCACHE_LINE)
        SCB_DCIMVAC = (uint32_t)a;
    dsb();
    isb();
}

static inline void system_reset(void)
{
    dsb();
    SCB_AIRCR = SCB_AIRCR_VECTKEY | SCB_AIRCR_SYSRESETREQ;
    dsb();
    for (;;) {
    }
}

#endif /* DMDSM_ARMV7M_H */

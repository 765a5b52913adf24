/* STM32H743 register maps used by this board, hand-written from RM0433 rev 8, offsets checked at compile time. */
#ifndef DMDSM_H743_REGS_H
#define DMDSM_H743_REGS_H

#include <stddef.h>
#include <stdint.h>

#define RW volatile uint32_t
#define CHECK_OFFSET(type, field, off) \
    _Static_assert(offsetof(type, field) == (off), #type "." #field " offset")

/* ---------------------------------------------------------------- RCC (RM0433 8.7) */
struct rcc {
    RW CR;        /* 0x000 */
    RW HSICFGR;   /* 0x004 */
    RW CRRCR;     /* 0x008 */
    RW CSICFGR;   /* 0x00C */
    RW CFGR;      /* 0x010 */
    RW res0;      /* 0x014 */
    RW D1CFGR;    /* 0x018 */
    RW D2CFGR;    /* 0x01C */
    RW D3CFGR;    /* 0x020 */
    RW res1;      /* 0x024 */
    RW PLLCKSELR; /* 0x028 */
    RW PLLCFGR;   /* 0x02C */
    RW PLL1DIVR;  /* 0x030 */
    RW PLL1FRACR; /* 0x034 */
    RW PLL2DIVR;  /* 0x038 */
    RW PLL2FRACR; /* 0x03C */
    RW PLL3DIVR;  /* 0x040 */
    RW PLL3FRACR; /* 0x044 */
    RW res2;      /* 0x048 */
    RW D1CCIPR;   /* 0x04C */
    RW D2CCIP1R;  /* 0x050 */
    RW D2CCIP2R;  /* 0x054 */
    RW D3CCIPR;   /* 0x058 */
    RW res3[29];  /* 0x05C..0x0CC */
    RW RSR;       /* 0x0D0 */
    RW AHB3ENR;   /* 0x0D4 */
    RW AHB1ENR;   /* 0x0D8 */
    RW AHB2ENR;   /* 0x0DC */
    RW AHB4ENR;   /* 0x0E0 */
    RW APB3ENR;   /* 0x0E4 */
    RW APB1LENR;  /* 0x0E8 */
    RW APB1HENR;  /* 0x0EC */
    RW APB2ENR;   /* 0x0F0 */
    RW APB4ENR;   /* 0x0F4 */
};
CHECK_OFFSET(struct rcc, CFGR, 0x010);
CHECK_OFFSET(struct rcc, PLLCKSELR, 0x028);
CHECK_OFFSET(struct rcc, PLL2DIVR, 0x038);
CHECK_OFFSET(struct rcc, D3CCIPR, 0x058);
CHECK_OFFSET(struct rcc, RSR, 0x0D0);
CHECK_OFFSET(struct rcc, AHB4ENR, 0x0E0);
CHECK_OFFSET(struct rcc, APB4ENR, 0x0F4);
#define RCC ((struct rcc *)0x58024400u)
#define RCC_CR_HSIDIV_SHIFT 3u
#define RCC_CR_HSEON (1u << 16)
#define RCC_CR_HSERDY (1u << 17)
#define RCC_CR_HSEBYP (1u << 18)
#define RCC_CR_PLL1ON (1u << 24)
#define RCC_CR_PLL1RDY (1u << 25)
#define RCC_CR_PLL2ON (1u << 26)
#define RCC_CR_PLL2RDY (1u << 27)
#define RCC_CFGR_SW_MASK 7u
#define RCC_CFGR_SW_PLL1 3u
#define RCC_CFGR_SWS_SHIFT 3u
#define RCC_CFGR_SWS_MASK (7u << 3)
#define RCC_AHB1ENR_DMA1EN (1u << 0)
#define RCC_AHB1ENR_ADC12EN (1u << 5)
#define RCC_AHB4ENR_GPIOAEN (1u << 0)
#define RCC_AHB4ENR_GPIOBEN (1u << 1)
#define RCC_AHB4ENR_GPIODEN (1u << 3)
#define RCC_AHB4ENR_GPIOEEN (1u << 4)
#define RCC_AHB4ENR_CRCEN (1u << 19)
#define RCC_APB1LENR_TIM2EN (1u << 0)
#define RCC_APB1LENR_USART3EN (1u << 18)
#define RCC_APB2ENR_TIM8EN (1u << 1)
#define RCC_APB4ENR_SYSCFGEN (1u << 1)

/* ---------------------------------------------------------------- PWR (RM0433 6.8) */
struct pwr {
    RW CR1;   /* 0x00 */
    RW CSR1;  /* 0x04 */
    RW CR2;   /* 0x08 */
    RW CR3;   /* 0x0C */
    RW CPUCR; /* 0x10 */
    RW res0;  /* 0x14 */
    RW D3CR;  /* 0x18 */
};
CHECK_OFFSET(struct pwr, CR3, 0x0C);
CHECK_OFFSET(struct pwr, D3CR, 0x18);
#define PWR ((struct pwr *)0x58024800u)
#define PWR_CR3_LDOEN (1u << 1)
#define PWR_CR3_SCUEN (1u << 2)
#define PWR_CSR1_ACTVOSRDY (1u << 13)
#define PWR_CSR1_ACTVOS_SHIFT 14u
#define PWR_CSR1_ACTVOS_MASK (3u << 14)
#define PWR_VOS1 3u /* VOS field code of scale 1 (VOS0 = scale 1 + SYSCFG_PWRCR.ODEN) */
#define PWR_D3CR_VOS_SHIFT 14u
#define PWR_D3CR_VOSRDY (1u << 13)

/* ---------------------------------------------------------------- FLASH, SYSCFG, DBGMCU */
#define FLASH_ACR (*(RW *)0x52002000u)
#define FLASH_ACR_LATENCY_MASK 0xFu
struct syscfg {
    RW res0;      /* 0x00 */
    RW PMCR;      /* 0x04 */
    RW EXTICR[4]; /* 0x08..0x14 */
    RW res1[5];   /* 0x18..0x28 */
    RW PWRCR;     /* 0x2C */
};
CHECK_OFFSET(struct syscfg, EXTICR, 0x08);
CHECK_OFFSET(struct syscfg, PWRCR, 0x2C);
#define SYSCFG ((struct syscfg *)0x58000400u)
#define SYSCFG_PWRCR_ODEN (1u << 0)
#define DBGMCU_IDCODE (*(RW *)0x5C001000u)
#define REV_ID_Y 0x1003u
#define REV_ID_V 0x2003u
/* rev V as ST's HAL decides it: any REV_ID above rev Y's 0x1003 */
static inline int rev_is_v(void)
{
    return (DBGMCU_IDCODE >> 16) > REV_ID_Y;
}
/* ES0392 2.2.9: rev Y AXI SRAM read corruption workaround (AXI_TARG7_FN_MOD) */
#define AXI_TARG7_FN_MOD (*(RW *)0x51008108u)

/* ---------------------------------------------------------------- GPIO (RM0433 11.4) */
struct gpio {
    RW MODER;   /* 0x00 */
    RW OTYPER;  /* 0x04 */
    RW OSPEEDR; /* 0x08 */
    RW PUPDR;   /* 0x0C */
    RW IDR;     /* 0x10 */
    RW ODR;     /* 0x14 */
    RW BSRR;    /* 0x18 */
    RW LCKR;    /* 0x1C */
    RW AFR[2];  /* 0x20, 0x24 */
};
CHECK_OFFSET(struct gpio, BSRR, 0x18);
CHECK_OFFSET(struct gpio, AFR, 0x20);
#define GPIOA ((struct gpio *)0x58020000u)
#define GPIOB ((struct gpio *)0x58020400u)
#define GPIOD ((struct gpio *)0x58020C00u)
#define GPIOE ((struct gpio *)0x58021000u)

/* ---------------------------------------------------------------- USART (RM0433 48.8) */
struct usart {
    RW CR1;   /* 0x00 */
    RW CR2;   /* 0x04 */
    RW CR3;   /* 0x08 */
    RW BRR;   /* 0x0C */
    RW GTPR;  /* 0x10 */
    RW RTOR;  /* 0x14 */
    RW RQR;   /* 0x18 */
    RW ISR;   /* 0x1C */
    RW ICR;   /* 0x20 */
    RW RDR;   /* 0x24 */
    RW TDR;   /* 0x28 */
    RW PRESC; /* 0x2C */
};
CHECK_OFFSET(struct usart, ISR, 0x1C);
CHECK_OFFSET(struct usart, TDR, 0x28);
#define USART3 ((struct usart *)0x40004800u)
#define USART_CR1_UE (1u << 0)
#define USART_CR1_RE (1u << 2)
#define USART_CR1_TE (1u << 3)
#define USART_CR1_RXNEIE (1u << 5)
#define USART_CR1_FIFOEN (1u << 29)
#define USART_CR3_DMAT (1u << 7)
#define USART_ISR_FE (1u << 1)
#define USART_ISR_NE (1u << 2)
#define USART_ISR_ORE (1u << 3)
#define USART_ISR_RXNE (1u << 5)
#define USART_ISR_TC (1u << 6)
#define USART_ICR_ALL 0x0000FFFFu

/* ---------------------------------------------------------------- CRC (RM0433 21.4) */
struct crc {
    RW DR;   /* 0x00 */
    RW IDR;  /* 0x04 */
    RW CR;   /* 0x08 */
    RW res;  /* 0x0C */
    RW INIT; /* 0x10 */
    RW POL;  /* 0x14 */
};
CHECK_OFFSET(struct crc, INIT, 0x10);
#define CRC_UNIT ((struct crc *)0x58024C00u)
#define CRC_CR_RESET (1u << 0)
#define CRC_CR_REV_IN_BYTE (1u << 5)
#define CRC_CR_REV_OUT (1u << 7)

/* ---------------------------------------------------------------- IRQ numbers (RM0433 Table 143) */
#define IRQ_TIM2 28u
#define IRQ_USART3 39u
#define N_IRQ 150u

#include "h743_capture_regs.h" /* DMA1, DMAMUX1, ADC1, TIM2, TIM8 */

#endif /* DMDSM_H743_REGS_H */

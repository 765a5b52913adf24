/* STM32H743 registers of the capture path (DMA1/DMAMUX1, ADC1/2, TIM2/TIM8), from RM0433 rev 8; included by h743_regs.h. */
#ifndef DMDSM_H743_CAPTURE_REGS_H
#define DMDSM_H743_CAPTURE_REGS_H

#ifndef DMDSM_H743_REGS_H
#error "include h743_regs.h"
#endif

/* ---------------------------------------------------------------- DMA1/2, DMAMUX1 (RM0433 15, 17) */
struct dma_stream {
    RW CR;   /* 0x00 */
    RW NDTR; /* 0x04 */
    RW PAR;  /* 0x08 */
    RW M0AR; /* 0x0C */
    RW M1AR; /* 0x10 */
    RW FCR;  /* 0x14 */
};
struct dma {
    RW LISR;  /* 0x00 */
    RW HISR;  /* 0x04 */
    RW LIFCR; /* 0x08 */
    RW HIFCR; /* 0x0C */
    struct dma_stream S[8]; /* 0x10 + 0x18 * n */
};
CHECK_OFFSET(struct dma, S, 0x10);
_Static_assert(sizeof(struct dma_stream) == 0x18, "DMA stream stride");
#define DMA1 ((struct dma *)0x40020000u)
#define DMAMUX1_CCR(ch) (*(RW *)(0x40020800u + 4u * (ch)))
#define DMA_CR_EN (1u << 0)
#define DMA_CR_DIR_M2P (1u << 6)
#define DMA_CR_CIRC (1u << 8)
#define DMA_CR_MINC (1u << 10)
#define DMA_CR_PSIZE_16 (1u << 11)
#define DMA_CR_MSIZE_16 (1u << 13)
#define DMA_CR_PL_HIGH (2u << 16)
#define DMAMUX_REQ_ADC1 9u
#define DMAMUX_REQ_USART3_TX 46u
/* all flags of streams 0 and 1 in LIFCR */
#define DMA_LIFCR_S0 0x0000003Du
#define DMA_LIFCR_S1 0x00000F40u

/* ---------------------------------------------------------------- ADC (RM0433 25.6) */
struct adc {
    RW ISR;      /* 0x00 */
    RW IER;      /* 0x04 */
    RW CR;       /* 0x08 */
    RW CFGR;     /* 0x0C */
    RW CFGR2;    /* 0x10 */
    RW SMPR1;    /* 0x14 */
    RW SMPR2;    /* 0x18 */
    RW PCSEL;    /* 0x1C */
    RW LTR1;     /* 0x20 */
    RW HTR1;     /* 0x24 */
    RW res0[2];  /* 0x28, 0x2C */
    RW SQR1;     /* 0x30 */
    RW SQR2;     /* 0x34 */
    RW SQR3;     /* 0x38 */
    RW SQR4;     /* 0x3C */
    RW DR;       /* 0x40 */
    RW res1[31]; /* 0x44..0xBC */
    RW DIFSEL;   /* 0xC0 */
    RW CALFACT;  /* 0xC4 */
};
CHECK_OFFSET(struct adc, SQR1, 0x30);
CHECK_OFFSET(struct adc, DR, 0x40);
CHECK_OFFSET(struct adc, DIFSEL, 0xC0);
struct adc_common {
    RW CSR; /* 0x00 */
    RW res; /* 0x04 */
    RW CCR; /* 0x08 */
    RW CDR; /* 0x0C */
};
CHECK_OFFSET(struct adc_common, CCR, 0x08);
#define ADC1 ((struct adc *)0x40022000u)
#define ADC12_COMMON ((struct adc_common *)0x40022300u)
#define ADC_ISR_ADRDY (1u << 0)
#define ADC_ISR_OVR (1u << 4)
#define ADC_CR_ADEN (1u << 0)
#define ADC_CR_ADSTART (1u << 2)
#define ADC_CR_ADSTP (1u << 4)
#define ADC_CR_BOOST_SHIFT 8u
#define ADC_CR_ADCALLIN (1u << 16)
#define ADC_CR_ADVREGEN (1u << 28)
#define ADC_CR_DEEPPWD (1u << 29)
#define ADC_CR_ADCAL (1u << 31)
#define ADC_CFGR_DMNGT_CIRC 3u
#define ADC_CFGR_EXTSEL_SHIFT 5u
#define ADC_CFGR_EXTEN_RISING (1u << 10)
#define ADC_CFGR_OVRMOD (1u << 12)
#define ADC_EXTSEL_TIM8_TRGO 7u

/* ---------------------------------------------------------------- TIM2, TIM8 (RM0433 38, 39) */
struct tim {
    RW CR1;   /* 0x00 */
    RW CR2;   /* 0x04 */
    RW SMCR;  /* 0x08 */
    RW DIER;  /* 0x0C */
    RW SR;    /* 0x10 */
    RW EGR;   /* 0x14 */
    RW CCMR1; /* 0x18 */
    RW CCMR2; /* 0x1C */
    RW CCER;  /* 0x20 */
    RW CNT;   /* 0x24 */
    RW PSC;   /* 0x28 */
    RW ARR;   /* 0x2C */
    RW RCR;   /* 0x30 */
    RW CCR1;  /* 0x34 */
    RW CCR2;  /* 0x38 */
    RW CCR3;  /* 0x3C */
    RW CCR4;  /* 0x40 */
    RW BDTR;  /* 0x44 */
};
CHECK_OFFSET(struct tim, CNT, 0x24);
CHECK_OFFSET(struct tim, CCR1, 0x34);
CHECK_OFFSET(struct tim, BDTR, 0x44);
#define TIM2 ((struct tim *)0x40000000u)
#define TIM8 ((struct tim *)0x40010400u)
#define TIM_CR1_CEN (1u << 0)
#define TIM_CR2_MMS_ENABLE (1u << 4)
#define TIM_CR2_MMS_UPDATE (2u << 4)
#define TIM_SMCR_SMS_TRIGGER 6u
#define TIM_SMCR_TS_ITR1 (1u << 4)
#define TIM_DIER_CC1IE (1u << 1)
#define TIM_SR_CC1IF (1u << 1)
#define TIM_SR_CC1OF (1u << 9)
#define TIM_EGR_UG (1u << 0)
#define TIM_CCMR1_CC1S_TI1 1u
#define TIM_CCMR1_IC1F_SHIFT 4u
#define TIM_CCER_CC1E (1u << 0)
#define TIM_CCER_CC1P (1u << 1)
#define TIM_DIER_CC2IE (1u << 2)
#define TIM_SR_CC2IF (1u << 2)
#define TIM_SR_CC2OF (1u << 10)
#define TIM_CCMR1_CC2S_TI2 (1u << 8)
#define TIM_CCMR1_IC2F_SHIFT 12u
#define TIM_CCER_CC2E (1u << 4)
#define TIM_DIER_CC3IE (1u << 3)
#define TIM_SR_CC3IF (1u << 3)
#define TIM_SR_CC3OF (1u << 11)
#define TIM_CCMR2_CC3S_TI3 1u
#define TIM_CCMR2_IC3F_SHIFT 4u
#define TIM_CCER_CC3E (1u << 8)
#define TIM_BDTR_MOE (1u << 15)

#endif /* DMDSM_H743_CAPTURE_REGS_H */

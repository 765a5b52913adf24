/* Start-up sequences for the rehost's rule checks: -DCASE=n picks one; case 0 does it right.
 * A case that must run through (no rule broken) ends with DONE(), which the test looks for. */
#include <stdint.h>

#define R(a) (*(volatile uint32_t *)(a))
#define RCC_CR 0x58024400u
#define RCC_CFGR 0x58024410u
#define RCC_PLLCKSELR 0x58024428u
#define RCC_D1CFGR 0x58024418u
#define RCC_PLLCFGR 0x5802442Cu
#define RCC_PLL1DIVR 0x58024430u
#define RCC_PLL2DIVR 0x58024438u
#define RCC_AHB4ENR 0x580244E0u
#define RCC_APB1LENR 0x580244E8u
#define USART3_CR1 0x40004800u
#define USART3_BRR 0x4000480Cu
#define ADC1_SMPR1 0x40022014u
#define DMA1_S0M1AR 0x40020020u
#define SCB_DCISW 0xE000EF60u
#define RCC_AHB1ENR 0x580244D8u
#define RCC_APB4ENR 0x580244F4u
#define PWR_D3CR 0x58024818u
#define FLASH_ACR 0x52002000u
#define SYSCFG_PWRCR 0x5800042Cu
#define ADC1_ISR 0x40022000u
#define ADC1_CR 0x40022008u
#define ADC1_CFGR 0x4002200Cu
#define DMA1_S0CR 0x40020010u
#define DMA1_S0NDTR 0x40020014u
#define DMA1_S0PAR 0x40020018u
#define DMA1_S0M0AR 0x4002001Cu
#define DMAMUX1_C0 0x40020800u
#define TIM8_CR1 0x40010400u
#define TIM8_ARR 0x4001042Cu
#define RCC_APB2ENR 0x580244F0u
#define SCB_CPACR 0xE000ED88u
#define SCB_CCR 0xE000ED14u
#define SCB_DCIMVAC 0xE000EF5Cu

extern uint32_t _estack;
void Reset_Handler(void);
__attribute__((section(".isr_vector"), used)) static void (*const vectors[2])(void) = {
    (void (*)(void))&_estack, Reset_Handler};

static uint16_t dma_buf[256] __attribute__((section(".dma_buffers"), aligned(32), unused));
static uint16_t dma_buf2[256] __attribute__((section(".dma_buffers"), aligned(32), unused));
static uint16_t dma_buf3[256] __attribute__((section(".dma_buffers"), aligned(32), unused));
static uint16_t dtcm_buf[256] __attribute__((unused));
volatile float f = 1.5f;

__attribute__((unused)) static void spin(uint32_t n)
{
    for (volatile uint32_t i = 0; i < n; i++) {
    }
}

/* the case ran to its end: GPIOK's clock, which nothing else uses */
#define DONE() (R(RCC_AHB4ENR) |= 1u << 10)

__attribute__((unused)) static void hse_on(void)
{
    R(RCC_CR) |= 1u << 18; /* HSEBYP while HSE is off */
    R(RCC_CR) |= 1u << 16;
    while (!(R(RCC_CR) & (1u << 17))) {
    }
}

/* PLL2 P = HSE / 4 * 144 / 4 = 72 MHz, the ADC's kernel clock, as clock.c sets it */
__attribute__((unused)) static void pll2_for_adc(uint32_t divm2)
{
    hse_on();
    R(RCC_PLLCKSELR) = 2u | (4u << 4) | (divm2 << 12);
    R(RCC_PLLCFGR) = (1u << 16) | (1u << 19); /* DIVP1EN, DIVP2EN */
    R(RCC_PLL2DIVR) = (144u - 1u) | ((4u - 1u) << 9);
    R(RCC_CR) |= 1u << 26;
    while (divm2 && !(R(RCC_CR) & (1u << 27))) {
    }
}

/* PLL1 from HSE / 4 = 2 MHz: n x 2 MHz VCO / 2 */
__attribute__((unused)) static void pll1_on(uint32_t n)
{
    R(RCC_PLL1DIVR) = (n - 1u) | (1u << 9);
    R(RCC_CR) |= 1u << 24;
    while (!(R(RCC_CR) & (1u << 25))) {
    }
}

__attribute__((unused)) static void vos1(void)
{
    R(PWR_D3CR) = 3u << 14;
    while (!(R(PWR_D3CR) & (1u << 13))) {
    }
}

/* 480 MHz VCO / 2 with D1CPRE /2: a 240 MHz CPU and AXI on VOS1, 4 flash wait states */
__attribute__((unused)) static void cpu_240_of_480(void)
{
    hse_on();
    R(RCC_PLLCKSELR) = 2u | (4u << 4);
    R(RCC_PLLCFGR) = 1u << 16;
    pll1_on(480u);
    vos1();
    R(FLASH_ACR) = 4u;
    R(RCC_D1CFGR) = 8u << 8; /* D1CPRE /2 */
    R(RCC_CFGR) = 3u;
}

/* clocks on (PLL2 with this DIVM2), out of deep power-down, regulator settled */
__attribute__((unused)) static void adc_regulator_on(uint32_t divm2)
{
    pll2_for_adc(divm2);
    R(RCC_AHB1ENR) |= (1u << 5) | 1u; /* ADC12, DMA1 */
    (void)R(RCC_AHB1ENR);
    R(ADC1_CR) = 0;                   /* out of deep power-down */
    R(ADC1_CR) = 1u << 28;            /* ADVREGEN */
    spin(20000);                      /* > 10 us at 64 MHz */
}

__attribute__((unused)) static void adc_calibrate(void)
{
    R(ADC1_CR) |= 1u << 31;
    while (R(ADC1_CR) & (1u << 31)) {
    }
}

__attribute__((unused)) static void adc_ready(int calibrate)
{
    adc_regulator_on(4u);
    if (calibrate)
        adc_calibrate();
    R(ADC1_CR) |= 1u; /* ADEN */
    while (!(R(ADC1_ISR) & 1u)) {
    }
}

/* TIM8 paces ADC1 into buf through DMA1 stream 0, circular (cr: extra S0CR bits, m1: M1AR) */
__attribute__((unused)) static void pacing_with(uint16_t *buf, uint32_t cr, uint16_t *m1)
{
    R(RCC_APB2ENR) |= 1u << 1;
    (void)R(RCC_APB2ENR);
    R(DMAMUX1_C0) = 9u;
    R(DMA1_S0PAR) = ADC1_CR + 0x38u; /* ADC1_DR */
    R(DMA1_S0M0AR) = (uint32_t)(uintptr_t)buf;
    R(DMA1_S0M1AR) = (uint32_t)(uintptr_t)m1;
    R(DMA1_S0NDTR) = 256u;
    R(DMA1_S0CR) = (1u << 8) | (1u << 10) | (1u << 11) | (1u << 13) | cr | 1u;
    R(ADC1_CFGR) = 3u | (7u << 5) | (1u << 10) | (1u << 12);
    R(ADC1_CR) |= 1u << 2; /* ADSTART */
    R(TIM8_ARR) = 63u;     /* 1 us at 64 MHz */
    R(TIM8_CR1) = 1u;
}

__attribute__((unused)) static void pacing(uint16_t *buf)
{
    pacing_with(buf, 0u, dma_buf2);
}

/* until the DMA has gone round the buffer once more: dma_buf[0] was rewritten */
__attribute__((unused)) static void wait_wrap(void)
{
    while (R(DMA1_S0NDTR) > 100u) {
    }
    while (R(DMA1_S0NDTR) < 200u) {
    }
    while (R(DMA1_S0NDTR) > 250u) { /* NDTR reloads before index 0 is written again */
    }
}

/* SCB_EnableDCache: invalidate every set and way (128 x 4, 32-byte lines), then DC */
__attribute__((unused)) static void dcache_on(void)
{
    for (uint32_t set = 0; set < 128u; set++)
        for (uint32_t way = 0; way < 4u; way++)
            R(SCB_DCISW) = (set << 5) | (way << 30);
    R(SCB_CCR) |= 1u << 16;
}

void Reset_Handler(void)
{
#if CASE != 7
    R(SCB_CPACR) |= 0xFu << 20;
#endif
#if CASE == 0 /* every sequence right: FPU, ADC, DMA into AXI SRAM, invalidate before reads */
    f = f * 2.0f;
    adc_ready(1);
    dcache_on();
    pacing(dma_buf);
    uint16_t a = *(volatile uint16_t *)dma_buf;
    wait_wrap();
    R(SCB_DCIMVAC) = (uint32_t)(uintptr_t)dma_buf;
    a = (uint16_t)(a + *(volatile uint16_t *)dma_buf);
    f = a;
#elif CASE == 1 /* ADEN without a calibration */
    adc_ready(0);
#elif CASE == 2 /* ADSTP while no conversion runs */
    adc_ready(1);
    R(ADC1_CR) |= 1u << 4;
#elif CASE == 3 /* switch to PLL1 right after raising VOS, before VOSRDY */
    R(RCC_CR) |= (1u << 16) | (1u << 18);
    while (!(R(RCC_CR) & (1u << 17))) {
    }
    R(RCC_PLLCKSELR) = 2u | (4u << 4);
    R(RCC_PLL1DIVR) = (200u - 1u) | (1u << 9); /* 400 MHz VCO / 2 = 200 MHz */
    R(RCC_CR) |= 1u << 24;
    while (!(R(RCC_CR) & (1u << 25))) {
    }
    R(FLASH_ACR) = 2u;
    R(PWR_D3CR) = 3u << 14; /* VOS1 */
    R(RCC_CFGR) = 3u;
#elif CASE == 4 /* DMA into DTCM */
    adc_ready(1);
    pacing(dtcm_buf);
#elif CASE == 5 /* read a DMA-written line again without invalidating it */
    adc_ready(1);
    dcache_on();
    pacing(dma_buf);
    uint16_t a = *(volatile uint16_t *)dma_buf;
    wait_wrap();
    a = (uint16_t)(a + *(volatile uint16_t *)dma_buf);
    f = a;
#elif CASE == 7 /* FPU before CPACR */
    f = f * 2.0f;
#elif CASE == 8 /* read where nothing answers (FMC bank 1, not enabled) */
    (void)R(0x60000000u);
#elif CASE == 9 /* SYSCFG written right after its clock enable */
    R(RCC_APB4ENR) |= 1u << 1;
    R(SYSCFG_PWRCR) |= 1u;
#elif CASE == 10 /* D-cache on without the invalidate-all that must come first */
    R(SCB_CCR) |= 1u << 16;
#elif CASE == 11 /* PLL1 and HSE off and on again, waiting for each RDY to clear, as HAL does */
    hse_on();
    R(RCC_PLLCKSELR) = 2u | (4u << 4);
    pll1_on(200u);
    R(RCC_CR) &= ~(1u << 24);
    while (R(RCC_CR) & (1u << 25)) {
    }
    pll1_on(160u);
    R(RCC_CR) &= ~(1u << 24);
    while (R(RCC_CR) & (1u << 25)) {
    }
    R(RCC_CR) &= ~(1u << 16);
    while (R(RCC_CR) & (1u << 17)) {
    }
    R(RCC_CR) |= 1u << 16;
    while (!(R(RCC_CR) & (1u << 17))) {
    }
    DONE();
#elif CASE == 12 /* DIVM2 = 0: PLL2 (the ADC's clock) prescaler off; the ADC's registers read */
    pll2_for_adc(0u);
    R(RCC_AHB1ENR) |= 1u << 5;
    (void)R(RCC_AHB1ENR);
    (void)R(ADC1_ISR);
    DONE();
#elif CASE == 13 /* DIVM2 = 0 and the ADC calibrated anyway: ADCAL would never end */
    adc_regulator_on(0u);
    R(ADC1_CR) |= 1u << 31;
#elif CASE == 14 /* ADEN during a second calibration */
    adc_ready(1);
    R(ADC1_CR) |= 1u << 1; /* ADDIS */
    R(ADC1_CR) |= 1u << 31;
    R(ADC1_CR) |= 1u;
#elif CASE == 15 /* the CPU clock raised after the switch: D1CPRE /2 -> /1 gives 480 MHz on VOS1 */
    cpu_240_of_480();
    R(RCC_D1CFGR) = 8u; /* D1CPRE /1, HPRE /2 */
#elif CASE == 16 /* flash wait states lowered after the switch */
    cpu_240_of_480();
    R(FLASH_ACR) = 1u;
#elif CASE == 17 /* 480 MHz on VOS0 (ODEN): right on rev V, beyond a rev Y part */
    hse_on();
    R(RCC_PLLCKSELR) = 2u | (4u << 4);
    R(RCC_PLLCFGR) = 1u << 16;
    pll1_on(480u);
    vos1();
    R(RCC_APB4ENR) |= 1u << 1;
    (void)R(RCC_APB4ENR);
    R(SYSCFG_PWRCR) |= 1u;
    while (!(R(PWR_D3CR) & (1u << 13))) {
    }
    R(FLASH_ACR) = 4u;
    R(RCC_D1CFGR) = 8u; /* D1CPRE /1, HPRE /2: 480 MHz CPU, 240 MHz AXI */
    R(RCC_CFGR) = 3u;
    DONE();
#elif CASE == 18 /* double-buffer mode with memory 1 in DTCM */
    adc_ready(1);
    pacing_with(dma_buf, 1u << 18, dtcm_buf);
#elif CASE == 19 /* CIRC cleared in S0CR while the stream runs */
    adc_ready(1);
    pacing(dma_buf);
    R(DMA1_S0CR) &= ~(1u << 8);
#elif CASE == 20 /* double buffer: M1AR updated while CT = 0 (legal), then M0AR (not) */
    adc_ready(1);
    pacing_with(dma_buf, 1u << 18, dma_buf2);
    R(DMA1_S0M1AR) = (uint32_t)(uintptr_t)dma_buf3;
    DONE();
    R(DMA1_S0M0AR) = (uint32_t)(uintptr_t)dma_buf2;
#elif CASE == 21 /* the sampling time changed while conversions run */
    adc_ready(1);
    pacing(dma_buf);
    R(ADC1_SMPR1) = 7u << 9;
#elif CASE == 22 /* TIM8 written right after its clock enable */
    R(RCC_APB2ENR) |= 1u << 1;
    R(TIM8_ARR) = 63u;
#elif CASE == 23 /* the switch to PLL1 before it locked */
    hse_on();
    R(RCC_PLLCKSELR) = 2u | (4u << 4);
    R(RCC_PLL1DIVR) = (200u - 1u) | (1u << 9);
    R(RCC_CR) |= 1u << 24;
    R(RCC_CFGR) = 3u;
#elif CASE == 24 /* USART3 BRR written with UE = 1 */
    R(RCC_APB1LENR) |= 1u << 18;
    (void)R(RCC_APB1LENR);
    R(USART3_CR1) = 1u;
    R(USART3_BRR) = 0x78u;
#elif CASE == 25 /* PLL1's dividers rewritten while PLL1 runs */
    hse_on();
    R(RCC_PLLCKSELR) = 2u | (4u << 4);
    pll1_on(200u);
    R(RCC_PLL1DIVR) = (100u - 1u) | (1u << 9);
#elif CASE == 26 /* PLL1 configured while PLL2 runs: legal, each PLL has its own fields */
    pll2_for_adc(4u);
    R(RCC_PLL1DIVR) = (200u - 1u) | (1u << 9);
    R(RCC_CR) |= 1u << 24;
    while (!(R(RCC_CR) & (1u << 25))) {
    }
    DONE();
#elif CASE == 27 /* ADCAL before the regulator's start-up time */
    pll2_for_adc(4u);
    R(RCC_AHB1ENR) |= 1u << 5;
    (void)R(RCC_AHB1ENR);
    R(ADC1_CR) = 0;
    R(ADC1_CR) = 1u << 28;
    R(ADC1_CR) |= 1u << 31;
#elif CASE == 28 /* ADCAL with ADEN = 1 */
    adc_ready(1);
    R(ADC1_CR) |= 1u << 31;
#elif CASE == 29 /* ADDIS while conversions run */
    adc_ready(1);
    pacing(dma_buf);
    R(ADC1_CR) |= 1u << 1;
#elif CASE == 30 /* the regulator enabled while still in deep power-down */
    pll2_for_adc(4u);
    R(RCC_AHB1ENR) |= 1u << 5;
    (void)R(RCC_AHB1ENR);
    R(ADC1_CR) = (1u << 29) | (1u << 28);
#elif CASE == 31 /* ADSTART right after ADEN, before ADRDY */
    adc_regulator_on(4u);
    adc_calibrate();
    R(ADC1_CR) |= 1u;
    R(ADC1_CR) |= 1u << 2;
#elif CASE == 32 /* ODEN from VOS3 (the reset scale), not VOS1 */
    R(RCC_APB4ENR) |= 1u << 1;
    (void)R(RCC_APB4ENR);
    R(SYSCFG_PWRCR) |= 1u;
#elif CASE == 33 /* ADC1 touched with its bus clock off */
    (void)R(ADC1_ISR);
#elif CASE == 34 /* PLL1 enabled before HSE, its input, is ready */
    R(RCC_PLLCKSELR) = 2u | (4u << 4);
    R(RCC_CR) |= 1u << 16;
    R(RCC_CR) |= 1u << 24;
#elif CASE == 35 /* VOS lowered to VOS3 under a 240 MHz clock */
    cpu_240_of_480();
    R(PWR_D3CR) = 1u << 14;
#elif CASE == 36 /* a write-only cache maintenance register read */
    (void)R(SCB_DCIMVAC);
#elif CASE == 37 /* a branch to EXC_RETURN in thread mode */
    ((void (*)(void))0xFFFFFFF9u)();
#elif CASE == 38 /* USART3 transmit DMA started with the USART disabled */
    R(RCC_AHB1ENR) |= 1u;
    R(RCC_APB1LENR) |= 1u << 18;
    (void)R(RCC_APB1LENR);
    R(DMAMUX1_C0 + 4u) = 46u;
    R(DMA1_S0CR + 0x18u + 8u) = USART3_CR1 + 0x28u; /* S1PAR = USART3_TDR */
    R(DMA1_S0CR + 0x18u + 0xCu) = (uint32_t)(uintptr_t)dma_buf;
    R(DMA1_S0CR + 0x18u + 4u) = 16u;
    R(DMA1_S0CR + 0x18u) = (1u << 6) | (1u << 10) | 1u;
#endif
    for (;;) {
    }
}

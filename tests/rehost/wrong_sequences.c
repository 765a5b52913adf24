/* Start-up sequences for the rehost's rule checks: -DCASE=n picks one; case 0 does it right. */
#include <stdint.h>

#define R(a) (*(volatile uint32_t *)(a))
#define RCC_CR 0x58024400u
#define RCC_CFGR 0x58024410u
#define RCC_PLLCKSELR 0x58024428u
#define RCC_PLL1DIVR 0x58024430u
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
static uint16_t dtcm_buf[256] __attribute__((unused));
volatile float f = 1.5f;

__attribute__((unused)) static void spin(uint32_t n)
{
    for (volatile uint32_t i = 0; i < n; i++) {
    }
}

__attribute__((unused)) static void adc_ready(int calibrate)
{
    R(RCC_AHB1ENR) |= (1u << 5) | 1u; /* ADC12, DMA1 */
    (void)R(RCC_AHB1ENR);
    R(ADC1_CR) = 0;                   /* out of deep power-down */
    R(ADC1_CR) = 1u << 28;            /* ADVREGEN */
    spin(20000);                      /* > 10 us at 64 MHz */
    if (calibrate) {
        R(ADC1_CR) |= 1u << 31;
        while (R(ADC1_CR) & (1u << 31)) {
        }
    }
    R(ADC1_CR) |= 1u; /* ADEN */
    while (!(R(ADC1_ISR) & 1u)) {
    }
}

/* TIM8 paces ADC1 into dma_buf (or dtcm_buf) through DMA1 stream 0, circular */
__attribute__((unused)) static void pacing(uint16_t *buf)
{
    R(RCC_APB2ENR) |= 1u << 1;
    (void)R(RCC_APB2ENR);
    R(DMAMUX1_C0) = 9u;
    R(DMA1_S0PAR) = ADC1_CR + 0x38u; /* ADC1_DR */
    R(DMA1_S0M0AR) = (uint32_t)(uintptr_t)buf;
    R(DMA1_S0NDTR) = 256u;
    R(DMA1_S0CR) = (1u << 8) | (1u << 10) | (1u << 11) | (1u << 13) | 1u;
    R(ADC1_CFGR) = 3u | (7u << 5) | (1u << 10) | (1u << 12);
    R(ADC1_CR) |= 1u << 2; /* ADSTART */
    R(TIM8_ARR) = 63u;     /* 1 us at 64 MHz */
    R(TIM8_CR1) = 1u;
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

__attribute__((unused)) static void dcache_on(void)
{
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
#endif
    for (;;) {
    }
}

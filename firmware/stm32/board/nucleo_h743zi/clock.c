/* Clocks of the NUCLEO-H743ZI: 8 MHz HSE bypass from the ST-LINK, PLL1 to 480 MHz (rev V) or 400 MHz (rev Y). */
#include "h743_regs.h"
#include "nucleo.h"

/*
 * rev V: VOS0, SYSCLK 480 MHz, AHB 240 MHz, APB1/2/3/4 120 MHz, timers 240 MHz.
 * rev Y: VOS1, SYSCLK 400 MHz, AHB 200 MHz, APB 100 MHz, timers 200 MHz.
 * PLL2_P feeds the ADC kernel clock: 72 MHz on rev V (the ADC halves it: 36 MHz),
 * 36 MHz on rev Y; a 16-bit conversion takes 10 ADC cycles (277.8 ns), and capture.c
 * paces them every 300 ns (3.333 MS/s).
 */
struct clocks clocks;

static void wait_set(const volatile uint32_t *reg, uint32_t mask)
{
    for (uint32_t n = 0; !(*reg & mask) && n < 10000000u; n++) {
    }
}

void clock_init(void)
{
    uint32_t rev = DBGMCU_IDCODE >> 16;
    clocks.rev_v = rev != REV_ID_Y;
    clocks.failure = DMDSM_ERROR_NONE;
    clocks.sysclk_hz = clocks.rev_v ? 480000000u : 400000000u;
    clocks.hclk_hz = clocks.sysclk_hz / 2u;
    clocks.pclk_hz = clocks.hclk_hz / 2u;
    clocks.timclk_hz = clocks.hclk_hz; /* APB prescaler 2: timers run at 2 x PCLK */

    /* supply: LDO, then voltage scale 1 (and 0 through ODEN on rev V) */
    PWR->CR3 = (PWR->CR3 & ~0x7u) | PWR_CR3_LDOEN | PWR_CR3_SCUEN;
    wait_set(&PWR->CSR1, PWR_CSR1_ACTVOSRDY);
    PWR->D3CR = 3u << PWR_D3CR_VOS_SHIFT; /* VOS1 */
    wait_set(&PWR->D3CR, PWR_D3CR_VOSRDY);
    if (clocks.rev_v) {
        RCC->APB4ENR |= RCC_APB4ENR_SYSCFGEN;
        SYSCFG->PWRCR |= SYSCFG_PWRCR_ODEN; /* VOS0 for 480 MHz */
        wait_set(&PWR->D3CR, PWR_D3CR_VOSRDY);
    }
    /* flash: 4 wait states, programming delay 2 (RM0433 Table 17, AXI <= 240 MHz) */
    FLASH_ACR = 4u | (2u << 4);
    while ((FLASH_ACR & 0xFu) != 4u) {
    }

    RCC->CR |= RCC_CR_HSEBYP | RCC_CR_HSEON;
    wait_set(&RCC->CR, RCC_CR_HSERDY);

    /* PLL1 and PLL2 from HSE / 4 = 2 MHz, input range 2-4 MHz, wide VCO */
    RCC->PLLCKSELR = 2u | (4u << 4) | (4u << 12);
    RCC->PLLCFGR = (1u << 2) | (1u << 6) | (1u << 16) | (1u << 17) | (1u << 18) | (1u << 19);
    uint32_t n1 = clocks.rev_v ? 480u : 400u; /* VCO 960 / 800 MHz */
    RCC->PLL1DIVR = (n1 - 1u) | ((2u - 1u) << 9) | ((8u - 1u) << 16) | ((2u - 1u) << 24);
    uint32_t p2 = clocks.rev_v ? 4u : 8u; /* VCO 288 MHz -> 72 / 36 MHz */
    RCC->PLL2DIVR = (144u - 1u) | ((p2 - 1u) << 9) | ((2u - 1u) << 16) | ((2u - 1u) << 24);
    RCC->CR |= RCC_CR_PLL1ON | RCC_CR_PLL2ON;
    wait_set(&RCC->CR, RCC_CR_PLL1RDY);
    wait_set(&RCC->CR, RCC_CR_PLL2RDY);

    /* bus prescalers before the switch: HPRE /2, D1PPRE /2, D2PPRE1/2 /2, D3PPRE /2 */
    RCC->D1CFGR = 0x8u | (0x4u << 4);
    RCC->D2CFGR = (0x4u << 4) | (0x4u << 8);
    RCC->D3CFGR = 0x4u << 4;
    RCC->CFGR = (RCC->CFGR & ~0x7u) | RCC_CFGR_SW_PLL1;
    while (((RCC->CFGR >> RCC_CFGR_SWS_SHIFT) & 0x7u) != RCC_CFGR_SW_PLL1) {
    }
    /* ADC kernel clock = pll2_p (ADCSEL = 0); USART3 stays on pclk1 */
    RCC->D3CCIPR &= ~(3u << 16);
    clocks.adc_hz = 36000000u; /* rev V: 72 MHz halved by the ADC; rev Y: 36 MHz */
    wait_init(clocks.sysclk_hz);
}

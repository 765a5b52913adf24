/* Clocks of the NUCLEO-H743ZI: 8 MHz HSE bypass from the ST-LINK, PLL1 to 480 MHz (rev V) or 400 MHz (rev Y). */
#include "h743_regs.h"
#include "nucleo.h"

/*
 * rev V: VOS0, SYSCLK 480 MHz, AHB 240 MHz, APB1/2/3/4 120 MHz, timers 240 MHz.
 * rev Y: VOS1, SYSCLK 400 MHz, AHB 200 MHz, APB 100 MHz, timers 200 MHz.
 * PLL2_P feeds the ADC kernel clock: 72 MHz on rev V (the ADC halves it: 36 MHz),
 * 36 MHz on rev Y; a 16-bit conversion takes 10 ADC cycles (277.8 ns), and capture.c
 * paces them every 300 ns (3.333 MS/s).
 *
 * Every wait is bounded (wait.c, timed by SysTick): 10 ms for the supply, each voltage
 * scale, HSE, each PLL and the clock switch (tens to hundreds of us expected),
 * 1 ms for the flash latency. A step that fails is recorded (boot.c: an error
 * log and LD3's blink code) and the board goes on safely: VOS0 not confirmed ->
 * 400 MHz at VOS1; anything else -> the reset clock, HSI 64 MHz, with no
 * acquisition. clocks.* is then read back from RCC, so USART3 and TIM2 are right.
 */
#define POWER_US 10000u
#define OSC_US 10000u
#define FLASH_US 1000u
#define HSI_HZ 64000000u
#define HSE_HZ 8000000u
#define ACR_LATENCY 4u /* wait states for AXI <= 240 MHz (RM0433 Table 17) */
#define ACR_WRHIGHFREQ (2u << 4)

struct clocks clocks;

#define FALLBACK "; running on HSI 64 MHz, no acquisition"

/* LDO supply and VOS1, confirmed by ACTVOSRDY, VOSRDY and ACTVOS */
static bool power_vos1(void)
{
    PWR->CR3 = (PWR->CR3 & ~0x7u) | PWR_CR3_LDOEN | PWR_CR3_SCUEN;
    if (!wait_bits(&PWR->CSR1, PWR_CSR1_ACTVOSRDY, PWR_CSR1_ACTVOSRDY, POWER_US)) {
        boot_fail(BOOT_SUPPLY, DMDSM_ERROR_POWER_FAILURE,
                  "boot: LDO supply not ready (PWR_CSR1.ACTVOSRDY) after 10 ms" FALLBACK);
        return false;
    }
    PWR->D3CR = PWR_VOS1 << PWR_D3CR_VOS_SHIFT;
    if (!wait_bits(&PWR->D3CR, PWR_D3CR_VOSRDY, PWR_D3CR_VOSRDY, POWER_US) ||
        !wait_bits(&PWR->CSR1, PWR_CSR1_ACTVOS_MASK | PWR_CSR1_ACTVOSRDY,
                   (PWR_VOS1 << PWR_CSR1_ACTVOS_SHIFT) | PWR_CSR1_ACTVOSRDY, POWER_US)) {
        boot_fail(BOOT_VOS1, DMDSM_ERROR_POWER_FAILURE, "boot: VOS1 not confirmed "
                  "(PWR_D3CR.VOSRDY, PWR_CSR1.ACTVOS = VOS1) after 10 ms" FALLBACK);
        return false;
    }
    return true;
}

/* VOS0 on rev V: the overdrive of VOS1 (SYSCFG_PWRCR.ODEN), each step read back */
static bool power_vos0(void)
{
    RCC->APB4ENR |= RCC_APB4ENR_SYSCFGEN;
    if (!(RCC->APB4ENR & RCC_APB4ENR_SYSCFGEN)) { /* read back before SYSCFG (ES0392) */
        boot_fail(BOOT_VOS0, DMDSM_ERROR_POWER_FAILURE, "boot: VOS0: SYSCFG clock "
                  "(RCC_APB4ENR.SYSCFGEN) not read back; running at 400 MHz on VOS1");
        return false;
    }
    SYSCFG->PWRCR |= SYSCFG_PWRCR_ODEN;
    if (!(SYSCFG->PWRCR & SYSCFG_PWRCR_ODEN)) {
        boot_fail(BOOT_VOS0, DMDSM_ERROR_POWER_FAILURE, "boot: VOS0: SYSCFG_PWRCR.ODEN did "
                  "not read back as set; running at 400 MHz on VOS1");
        return false;
    }
    if (!wait_bits(&PWR->D3CR, PWR_D3CR_VOSRDY, PWR_D3CR_VOSRDY, POWER_US) ||
        !wait_bits(&PWR->CSR1, PWR_CSR1_ACTVOS_MASK | PWR_CSR1_ACTVOSRDY,
                   (PWR_VOS1 << PWR_CSR1_ACTVOS_SHIFT) | PWR_CSR1_ACTVOSRDY, POWER_US)) {
        SYSCFG->PWRCR &= ~SYSCFG_PWRCR_ODEN; /* back to plain VOS1 */
        (void)wait_bits(&PWR->D3CR, PWR_D3CR_VOSRDY, PWR_D3CR_VOSRDY, POWER_US);
        boot_fail(BOOT_VOS0, DMDSM_ERROR_POWER_FAILURE, "boot: VOS0 not confirmed "
                  "(PWR_D3CR.VOSRDY, PWR_CSR1.ACTVOS) 10 ms after ODEN; running at 400 MHz "
                  "on VOS1");
        return false;
    }
    return true;
}

/* HSE bypass, PLL1 (sysclk) and PLL2 (ADC) from HSE / 4 = 2 MHz, then the switch */
static bool to_pll(uint32_t sysclk_mhz)
{
    FLASH_ACR = ACR_LATENCY | ACR_WRHIGHFREQ;
    if (!wait_bits(&FLASH_ACR, FLASH_ACR_LATENCY_MASK, ACR_LATENCY, FLASH_US)) {
        boot_fail(BOOT_FLASH, DMDSM_ERROR_CLOCK_FAILURE, "boot: flash latency "
                  "(FLASH_ACR.LATENCY = 4) not read back after 1 ms" FALLBACK);
        return false;
    }
    RCC->CR |= RCC_CR_HSEBYP; /* while HSE is off */
    RCC->CR |= RCC_CR_HSEON;
    if (!wait_bits(&RCC->CR, RCC_CR_HSERDY, RCC_CR_HSERDY, OSC_US)) {
        RCC->CR &= ~RCC_CR_HSEON;
        boot_fail(BOOT_HSE, DMDSM_ERROR_CLOCK_FAILURE,
                  "boot: HSE not ready (RCC_CR.HSERDY) after 10 ms" FALLBACK);
        return false;
    }
    /* input range 2-4 MHz, wide VCO; VCO1 960 / 800 MHz, VCO2 288 MHz -> 72 / 36 MHz */
    RCC->PLLCKSELR = 2u | (4u << 4) | (4u << 12);
    RCC->PLLCFGR = (1u << 2) | (1u << 6) | (1u << 16) | (1u << 17) | (1u << 18) | (1u << 19);
    uint32_t n1 = sysclk_mhz;
    RCC->PLL1DIVR = (n1 - 1u) | ((2u - 1u) << 9) | ((8u - 1u) << 16) | ((2u - 1u) << 24);
    uint32_t p2 = clocks.rev_v ? 4u : 8u;
    RCC->PLL2DIVR = (144u - 1u) | ((p2 - 1u) << 9) | ((2u - 1u) << 16) | ((2u - 1u) << 24);
    RCC->CR |= RCC_CR_PLL1ON | RCC_CR_PLL2ON;
    bool pll1 = wait_bits(&RCC->CR, RCC_CR_PLL1RDY, RCC_CR_PLL1RDY, OSC_US);
    bool pll2 = pll1 && wait_bits(&RCC->CR, RCC_CR_PLL2RDY, RCC_CR_PLL2RDY, OSC_US);
    if (!pll2) {
        RCC->CR &= ~(RCC_CR_PLL1ON | RCC_CR_PLL2ON);
        boot_fail(BOOT_PLL, DMDSM_ERROR_CLOCK_FAILURE, pll1
                  ? "boot: PLL2 not locked (RCC_CR.PLL2RDY) after 10 ms" FALLBACK
                  : "boot: PLL1 not locked (RCC_CR.PLL1RDY) after 10 ms" FALLBACK);
        return false;
    }
    /* bus prescalers before the switch: HPRE /2, D1PPRE /2, D2PPRE1/2 /2, D3PPRE /2 */
    RCC->D1CFGR = 0x8u | (0x4u << 4);
    RCC->D2CFGR = (0x4u << 4) | (0x4u << 8);
    RCC->D3CFGR = 0x4u << 4;
    RCC->CFGR = (RCC->CFGR & ~RCC_CFGR_SW_MASK) | RCC_CFGR_SW_PLL1;
    if (!wait_bits(&RCC->CFGR, RCC_CFGR_SWS_MASK, RCC_CFGR_SW_PLL1 << RCC_CFGR_SWS_SHIFT,
                   OSC_US)) {
        RCC->CFGR &= ~RCC_CFGR_SW_MASK; /* HSI */
        (void)wait_bits(&RCC->CFGR, RCC_CFGR_SWS_MASK, 0, OSC_US);
        RCC->D1CFGR = 0;
        RCC->D2CFGR = 0;
        RCC->D3CFGR = 0;
        boot_fail(BOOT_SWITCH, DMDSM_ERROR_CLOCK_FAILURE, "boot: switch to PLL1 not "
                  "confirmed (RCC_CFGR.SWS) after 10 ms" FALLBACK);
        return false;
    }
    /* ADC kernel clock = pll2_p (ADCSEL = 0); USART3 stays on pclk1 */
    RCC->D3CCIPR &= ~(3u << 16);
    return true;
}

/* AHB/APB prescaler codes (RM0433 8.7.7): 0xxx = /1, 1000 = /2 ... */
static uint32_t ahb_div(uint32_t code)
{
    static const uint16_t div[8] = {2, 4, 8, 16, 64, 128, 256, 512};
    return code < 8u ? 1u : div[code - 8u];
}

static uint32_t apb_div(uint32_t code)
{
    return code < 4u ? 1u : 2u << (code - 4u);
}

/* clocks.* from what RCC reports: the system clock source, PLL1 and the prescalers */
static void clocks_read(void)
{
    uint32_t sws = (RCC->CFGR & RCC_CFGR_SWS_MASK) >> RCC_CFGR_SWS_SHIFT;
    uint32_t hsi = HSI_HZ >> ((RCC->CR >> RCC_CR_HSIDIV_SHIFT) & 3u);
    uint32_t sys = hsi;
    if (sws == RCC_CFGR_SW_PLL1) {
        uint32_t sel = RCC->PLLCKSELR, div = RCC->PLL1DIVR;
        uint32_t src = (sel & 3u) == 2u ? HSE_HZ : (sel & 3u) == 1u ? 4000000u : hsi;
        uint32_t m = (sel >> 4) & 0x3Fu;
        sys = (uint32_t)((uint64_t)src / (m ? m : 1u) * ((div & 0x1FFu) + 1u) /
                         (((div >> 9) & 0x7Fu) + 1u));
    } else if (sws == 2u) {
        sys = HSE_HZ;
    }
    uint32_t d1 = RCC->D1CFGR, ppre1 = apb_div((RCC->D2CFGR >> 4) & 7u);
    clocks.sysclk_hz = sys / ahb_div((d1 >> 8) & 0xFu); /* the CPU clock */
    clocks.hclk_hz = clocks.sysclk_hz / ahb_div(d1 & 0xFu);
    clocks.pclk_hz = clocks.hclk_hz / ppre1;
    clocks.timclk_hz = ppre1 == 1u ? clocks.pclk_hz : 2u * clocks.pclk_hz; /* TIMPRE = 0 */
    bool pll2 = (RCC->CR & RCC_CR_PLL2RDY) != 0;
    clocks.adc_hz = pll2 && clocks.failure == 0 ? 36000000u : 0u; /* pll2_p (/2 on rev V) */
}

void clock_init(void)
{
    clocks.rev_v = rev_is_v();
    clocks.failure = DMDSM_ERROR_NONE;
    if (!power_vos1()) {
        clocks.failure = DMDSM_ERROR_POWER_FAILURE;
    } else {
        bool vos0 = clocks.rev_v && power_vos0();
        if (!to_pll(vos0 ? 480u : 400u))
            clocks.failure = DMDSM_ERROR_CLOCK_FAILURE;
    }
    clocks_read();
    wait_init(clocks.sysclk_hz);
}

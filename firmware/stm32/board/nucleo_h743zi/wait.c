/* Bounded busy-waits of the NUCLEO board: SysTick times them until TIM2 (the device clock) runs. */
#include "armv7m.h"
#include "h743_regs.h"
#include "nucleo.h"

/*
 * Before and during the clock set-up, SysTick counts CPU cycles (CLKSOURCE = 1,
 * so rev Y's missing /8 divider does not matter; no interrupt); from
 * capture_init on, TIM2 counts timer ticks. A wait ends when its condition
 * holds or `us` microseconds have passed on that clock. It also ends after
 * us x (counts per us) / 4 polls: a poll (a bus read, a clock read, the loop)
 * takes more than 4 counts, so this only acts if the clock did not count, and
 * then still bounds the wait.
 */
#define COUNTS_PER_POLL 4u

static struct {
    bool tim2;        /* TIM2 is the clock, else SysTick */
    uint32_t per_us;  /* counts per microsecond */
} clk = {false, 64u}; /* HSI 64 MHz after reset */

void wait_init(uint32_t cpu_hz)
{
    clk.tim2 = false;
    clk.per_us = cpu_hz / 1000000u ? cpu_hz / 1000000u : 1u;
    SYST_RVR = 0xFFFFFFu;
    SYST_CVR = 0;
    SYST_CSR = SYST_CSR_ENABLE | SYST_CSR_CLKSOURCE;
}

void wait_use_tim2(uint32_t timclk_hz)
{
    clk.tim2 = true;
    clk.per_us = timclk_hz / 1000000u ? timclk_hz / 1000000u : 1u;
}

/* an up-counting clock reading; only differences masked by clock_mask() are used */
static uint32_t clock_now(void)
{
    return clk.tim2 ? TIM2->CNT : 0u - SYST_CVR; /* SysTick counts down */
}

static uint32_t clock_mask(void)
{
    return clk.tim2 ? 0xFFFFFFFFu : 0xFFFFFFu;
}

/* poll (*reg & mask) == want (reg NULL: never true) for at most us microseconds */
static bool wait(const volatile uint32_t *reg, uint32_t mask, uint32_t want, uint32_t us)
{
    uint32_t budget = us * clk.per_us; /* us <= 1 s keeps this < 2^32 at 480 MHz */
    uint32_t last = clock_now(), elapsed = 0, m = clock_mask();
    for (uint32_t polls = 0; polls < budget / COUNTS_PER_POLL && elapsed < budget; polls++) {
        if (reg != NULL && (*reg & mask) == want)
            return true;
        uint32_t now = clock_now();
        elapsed += (now - last) & m; /* read often: SysTick wraps every 2^24 cycles */
        last = now;
    }
    return reg != NULL && (*reg & mask) == want;
}

bool wait_bits(const volatile uint32_t *reg, uint32_t mask, uint32_t want, uint32_t us)
{
    return wait(reg, mask, want, us);
}

void delay_us(uint32_t us)
{
    (void)wait(NULL, 0, 0, us);
}

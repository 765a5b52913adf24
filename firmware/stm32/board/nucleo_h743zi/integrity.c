/* Sample-integrity check of the NUCLEO capture: is the DMA's position in the ring where the timer says? */
#include "nucleo.h"

/*
 * Each poll reads TIM2's CNT (c1), DMA1 stream 0's NDTR, then CNT again (c2),
 * with interrupts off. Sample k is triggered at t0 + (k + 1) T and is in the
 * ring W ticks later (W: trigger resynchronisation into the ADC clock, 10 ADC
 * cycles of conversion, the DMA write). NDTR was read between c1 and c2, so with
 * `done` samples triggered by c1, `written` = (RING - NDTR) mod RING stored by
 * the DMA, lag = done - written (mod RING, from -RING/2), phase = (c1 - t0) mod T and
 * skew = c2 - c1:
 *
 *     phase + (lag - 1) T  <  W  <=  phase + lag T + skew
 *
 * (the upper bound once something was written). W is a property of the
 * hardware, so the bounds of all polls since pacing started must overlap up to
 * JITTER_NS; a missed or late trigger moves the implied W up by a whole period
 * (T >= 300 ns > JITTER_NS), a stalled TIM8, ADC or DMA moves it up without
 * limit (beyond MAX_NS), a DMA ahead of the timer (samples nobody triggered)
 * makes it negative. A
 * slow poll (a large skew) only widens its own bounds: it can never fail.
 */
#define JITTER_NS 150u /* peak-to-peak spread of W allowed: ADC clock resync, bus waits */
#define MAX_NS 1500u   /* longest W: about 0.45 us expected (0.3-0.45 us at 36 MHz) */

static uint32_t ticks(uint32_t timclk_hz, uint32_t ns)
{
    return (uint32_t)(((uint64_t)timclk_hz * ns + 999999999u) / 1000000000u);
}

void integrity_reset(struct integrity *g, uint32_t timclk_hz)
{
    g->lo = -((int64_t)1 << 40); /* no bound yet; W >= 0 in fact */
    g->hi = INT64_MAX;
    g->jitter = ticks(timclk_hz, JITTER_NS);
    g->max = ticks(timclk_hz, MAX_NS);
}

bool integrity_observe(struct integrity *g, uint32_t phase, int32_t lag, uint32_t skew,
                       bool written, uint32_t T)
{
    int64_t lower = (int64_t)phase + ((int64_t)lag - 1) * T;
    int64_t upper = (int64_t)phase + (int64_t)lag * T + skew;
    if (lower > g->lo)
        g->lo = lower;
    if (written && upper < g->hi)
        g->hi = upper;
    int64_t j = g->jitter;
    return g->lo <= g->max && g->lo - j <= g->hi && g->hi >= -j;
}

/* Shot capture: TIM8 paces ADC1 into a circular DMA ring; TIM2 latches the laser edge; no CPU in the sampling path. */
#include <string.h>

#include "armv7m.h"
#include "h743_regs.h"
#include "nucleo.h"

/*
 * TIM2 (32 bit, timer clock) runs free and is the device clock. TIM8 is
 * started by TIM2's enable (slave trigger mode on ITR1), so sample k is taken
 * at TIM2 tick t0 + (k + 1) * T, where T = sample period in timer ticks. ADC1
 * converts on each TIM8 update and DMA1 stream 0 writes ring[k mod RING].
 *
 * The photodiode edge on PA0 is captured by TIM2 CH1 in hardware (CCR1). Its
 * interrupt only does arithmetic: the first sample after the edge is
 * k = ceil((E - t0) / T) - 1 and the trigger phase is the time from E to that
 * sample, so pre-trigger samples come from the ring and the host can remove
 * the sub-sample start jitter. The main loop copies the burst out once the
 * ring holds it; if the ring lapped the burst first, it is an overrun.
 */
#define RING 16384u /* samples: twice the longest burst */
#define T_MIN 67u   /* ticks at 240 MHz: 3.58 MS/s (56 at 200 MHz on rev Y) */

static uint16_t ring[RING] __attribute__((section(".dma_buffers"), aligned(32)));
static uint16_t burst[8192] __attribute__((aligned(32)));

static struct {
    uint32_t T;        /* sample period, timer ticks */
    uint32_t t0;       /* TIM2 tick of "sample -1": sample k at t0 + (k + 1) T */
    uint32_t k0;       /* sample index at t0 (advances when t0 is re-based) */
    struct dmdsm_set_config cfg;
    volatile int armed;
    volatile int edge;  /* an edge was latched and its burst is being collected */
    volatile uint32_t edge_ticks;
    volatile uint32_t start; /* absolute sample index of the burst's first sample */
    volatile uint16_t phase;
} cap;

uint32_t capture_now(void)
{
    return TIM2->CNT;
}

uint32_t capture_adc_rate_hz(void)
{
    return clocks.timclk_hz / (clocks.rev_v ? T_MIN : 56u);
}

/* (re)start sampling with period T ticks: both timers stop, then start together */
static void pacing_start(uint32_t T)
{
    TIM2->CR1 = 0;
    TIM8->CR1 = 0;
    ADC1->CR |= ADC_CR_ADSTP;
    while (ADC1->CR & ADC_CR_ADSTART) {
    }
    struct dma_stream *s = &DMA1->S[0];
    s->CR = 0;
    while (s->CR & DMA_CR_EN) {
    }
    DMA1->LIFCR = DMA_LIFCR_S0;
    s->PAR = (uint32_t)(uintptr_t)&ADC1->DR;
    s->M0AR = (uint32_t)(uintptr_t)ring;
    s->NDTR = RING;
    s->CR = DMA_CR_CIRC | DMA_CR_MINC | DMA_CR_PSIZE_16 | DMA_CR_MSIZE_16 | DMA_CR_PL_HIGH |
            DMA_CR_EN;
    ADC1->ISR = ADC_ISR_OVR;
    ADC1->CR |= ADC_CR_ADSTART; /* waits for TIM8 triggers */
    TIM8->ARR = T - 1u;
    TIM8->CNT = 0;
    TIM2->CNT = 0;
    cap.T = T;
    cap.t0 = 0;
    cap.k0 = 0;
    TIM2->CR1 = TIM_CR1_CEN; /* TRGO (enable) starts TIM8 in the same cycle */
}

void capture_init(void)
{
    RCC->AHB4ENR |= RCC_AHB4ENR_GPIOAEN;
    RCC->AHB1ENR |= RCC_AHB1ENR_DMA1EN | RCC_AHB1ENR_ADC12EN;
    RCC->APB1LENR |= RCC_APB1LENR_TIM2EN;
    RCC->APB2ENR |= RCC_APB2ENR_TIM8EN;
    (void)RCC->APB2ENR;
    /* PA0 = TIM2_CH1 (AF1), PA6 analog */
    GPIOA->MODER = (GPIOA->MODER & ~3u) | 2u;
    GPIOA->AFR[0] = (GPIOA->AFR[0] & ~0xFu) | 1u;
    GPIOA->MODER |= 3u << (2 * 6);

    /* ADC1: out of deep power-down, regulator on, calibrate, enable */
    ADC12_COMMON->CCR = 0; /* asynchronous kernel clock (pll2_p), no prescaler */
    ADC1->CR = 0;
    ADC1->CR = ADC_CR_ADVREGEN;
    for (volatile uint32_t i = 0; i < 100000u; i++) {
    }
    ADC1->CR = ADC_CR_ADVREGEN | (clocks.rev_v ? 3u << ADC_CR_BOOST_SHIFT
                                                : 1u << ADC_CR_BOOST_SHIFT);
    ADC1->CR |= ADC_CR_ADCALLIN | ADC_CR_ADCAL; /* offset and linearity calibration */
    while (ADC1->CR & ADC_CR_ADCAL) {
    }
    ADC1->ISR = ADC_ISR_ADRDY;
    ADC1->CR |= ADC_CR_ADEN;
    while (!(ADC1->ISR & ADC_ISR_ADRDY)) {
    }
    ADC1->PCSEL = 1u << 3;          /* preselect INP3 */
    ADC1->SQR1 = 3u << 6;           /* one conversion: channel 3 */
    ADC1->SMPR1 = 0;                /* 1.5 cycles sampling */
    ADC1->CFGR = ADC_CFGR_DMNGT_CIRC | (ADC_EXTSEL_TIM8_TRGO << ADC_CFGR_EXTSEL_SHIFT) |
                 ADC_CFGR_EXTEN_RISING | ADC_CFGR_OVRMOD; /* 16 bit: RES = 0 */
    DMAMUX1_CCR(0) = DMAMUX_REQ_ADC1;

    /* TIM2: free-running 32-bit clock, CH1 input capture, TRGO on enable */
    TIM2->PSC = 0;
    TIM2->ARR = 0xFFFFFFFFu;
    TIM2->CR2 = TIM_CR2_MMS_ENABLE;
    TIM2->CCMR1 = TIM_CCMR1_CC1S_TI1 | (2u << TIM_CCMR1_IC1F_SHIFT); /* 4-sample filter */
    TIM2->CCER = TIM_CCER_CC1E;
    /* TIM8: update every T ticks -> TRGO -> ADC; started by TIM2 (ITR1) */
    TIM8->PSC = 0;
    TIM8->CR2 = TIM_CR2_MMS_UPDATE;
    TIM8->SMCR = TIM_SMCR_TS_ITR1 | TIM_SMCR_SMS_TRIGGER;
    TIM8->EGR = TIM_EGR_UG;
    nvic_enable(IRQ_TIM2);
    pacing_start(clocks.rev_v ? T_MIN : 56u);
}

void capture_arm(const struct dmdsm_set_config *cfg)
{
    uint32_t T = (clocks.rev_v ? T_MIN : 56u) * cfg->sample_rate_div;
    if (T != cap.T)
        pacing_start(T);
    cap.cfg = *cfg;
    TIM2->CCER = TIM_CCER_CC1E | (cfg->trigger_edge ? TIM_CCER_CC1P : 0u);
    TIM2->SR = ~(TIM_SR_CC1IF | TIM_SR_CC1OF);
    cap.edge = 0;
    cap.armed = 1;
    TIM2->DIER = TIM_DIER_CC1IE;
}

void capture_disarm(void)
{
    TIM2->DIER = 0;
    cap.armed = 0;
    cap.edge = 0;
}

/* the laser edge: hardware latched CCR1; compute where the burst lies in the ring */
void TIM2_IRQHandler(void)
{
    uint32_t e = TIM2->CCR1; /* reading CCR1 clears CC1IF */
    TIM2->DIER = 0;          /* one edge per burst; re-armed by the core */
    if (!cap.armed)
        return;
    uint32_t since = e - cap.t0;
    uint32_t k = since / cap.T; /* samples 0..k-1 were taken at or before the edge */
    uint32_t next_at = (k + 1u) * cap.T;
    cap.phase = (uint16_t)(next_at - since);
    cap.start = cap.k0 + k - cap.cfg.pretrigger;
    cap.edge_ticks = e;
    cap.armed = 0;
    cap.edge = 1;
}

int capture_poll(const uint16_t **samples, uint32_t *edge, uint16_t *phase, bool *overrun)
{
    uint32_t since = capture_now() - cap.t0;
    if (since > 0x40000000u && !cap.edge) {
        /* keep t0 recent so 32-bit tick differences never wrap; the ring index of
         * t0 + RING * T is the same as t0's */
        cap.t0 += RING * cap.T;
        cap.k0 += RING;
        since = capture_now() - cap.t0;
    }
    if (!cap.edge)
        return 0;
    uint32_t done = cap.k0 + since / cap.T; /* samples written so far */
    uint32_t end = cap.start + cap.cfg.n_samples;
    if ((int32_t)(done - end) < 2)
        return 0; /* DMA still filling the burst */
    bool lapped = (done - cap.start) > RING - 64u;
    dcache_invalidate(ring, sizeof ring);
    for (uint32_t i = 0; i < cap.cfg.n_samples; i++)
        burst[i] = ring[(cap.start + i) % RING];
    *overrun = lapped || (ADC1->ISR & ADC_ISR_OVR) != 0;
    ADC1->ISR = ADC_ISR_OVR;
    *samples = burst;
    *edge = cap.edge_ticks;
    *phase = cap.phase;
    cap.edge = 0;
    return 1;
}

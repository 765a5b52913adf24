/* ADC1 of the NUCLEO board: power-up, self-calibration and enable with bounded waits; start and stop. */
#include "h743_regs.h"
#include "nucleo.h"

/*
 * Limits of the waits (RM0433 25.4.6-25.4.9; DS12110 for the regulator):
 * the regulator needs tADCVREG_STUP = 10 us, offset + linearity calibration a
 * few ms at 36 MHz, ADRDY a few ADC cycles, and ADSTP ends the conversion in
 * flight (< 1 us). Each limit is at least ten times that.
 */
#define ADC_VREG_US 50u
#define ADC_CAL_US 100000u
#define ADC_RDY_US 10000u
#define ADC_STOP_US 1000u

/* ADC_CR's "rs" bits (set by software, cleared by hardware): a write carries 0 in those
 * that are not being set, as ST's drivers do, so a start never repeats a pending ADCAL,
 * ADSTP or ADDIS; ADEN is written back as read (writing 1 over 1 changes nothing) */
#define ADC_CR_RS_BITS 0x8000003Eu /* ADCAL, JADSTP, ADSTP, JADSTART, ADSTART, ADDIS */

static void cr_set(uint32_t bits)
{
    ADC1->CR = (ADC1->CR & ~ADC_CR_RS_BITS) | bits;
}

bool adc_init(void)
{
    RCC->AHB1ENR |= RCC_AHB1ENR_ADC12EN;
    (void)RCC->AHB1ENR; /* read back: the clock is on before the first ADC access */
    ADC12_COMMON->CCR = 0; /* asynchronous kernel clock (pll2_p), no prescaler */
    ADC1->CR = 0;          /* out of deep power-down */
    ADC1->CR = ADC_CR_ADVREGEN;
    delay_us(ADC_VREG_US);
    ADC1->CR = ADC_CR_ADVREGEN | (clocks.rev_v ? 3u << ADC_CR_BOOST_SHIFT
                                                : 1u << ADC_CR_BOOST_SHIFT);
    cr_set(ADC_CR_ADCALLIN | ADC_CR_ADCAL); /* offset and linearity calibration */
    if (!wait_bits(&ADC1->CR, ADC_CR_ADCAL, 0, ADC_CAL_US)) {
        boot_fail(BOOT_ADC, DMDSM_ERROR_ADC_FAILURE, "boot: ADC calibration (ADC_CR.ADCAL) "
                  "did not finish after 100 ms; acquisition unavailable");
        return false;
    }
    ADC1->ISR = ADC_ISR_ADRDY;
    cr_set(ADC_CR_ADEN);
    if (!wait_bits(&ADC1->ISR, ADC_ISR_ADRDY, ADC_ISR_ADRDY, ADC_RDY_US)) {
        boot_fail(BOOT_ADC, DMDSM_ERROR_ADC_FAILURE, "boot: ADC not ready (ADC_ISR.ADRDY) "
                  "10 ms after ADEN; acquisition unavailable");
        return false;
    }
    ADC1->PCSEL = 1u << 3; /* preselect INP3 */
    ADC1->SQR1 = 3u << 6;  /* one conversion: channel 3 */
    ADC1->SMPR1 = 0;       /* 1.5 cycles sampling */
    ADC1->CFGR = ADC_CFGR_DMNGT_CIRC | (ADC_EXTSEL_TIM8_TRGO << ADC_CFGR_EXTSEL_SHIFT) |
                 ADC_CFGR_EXTEN_RISING | ADC_CFGR_OVRMOD; /* 16 bit: RES = 0 */
    DMAMUX1_CCR(0) = DMAMUX_REQ_ADC1;
    return true;
}

/* regular conversions on, each waiting for a TIM8 trigger; a stale overrun flag cleared */
void adc_start(void)
{
    ADC1->ISR = ADC_ISR_OVR;
    cr_set(ADC_CR_ADSTART);
}

/* ADSTP is allowed only while ADSTART is set (RM0433): stop only a started ADC, then wait
 * (1 ms at most) for ADSTART to clear; false if it did not */
bool adc_stop(void)
{
    if (!(ADC1->CR & ADC_CR_ADSTART))
        return true;
    cr_set(ADC_CR_ADSTP);
    return wait_bits(&ADC1->CR, ADC_CR_ADSTART, 0, ADC_STOP_US);
}

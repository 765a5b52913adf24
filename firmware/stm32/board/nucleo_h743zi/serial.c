/* USART3 on PD8/PD9 (ST-LINK virtual COM port): DMA1 stream 1 transmit, interrupt-fed receive ring. */
#include "armv7m.h"
#include "h743_regs.h"
#include "nucleo.h"

#define RX_RING 512u /* bytes; commands are at most 64 B of payload */
#define TX_STREAM 1u

static volatile uint8_t rx_ring[RX_RING];
static volatile uint32_t rx_head, rx_tail, rx_overflow;

static void pin_af(struct gpio *port, unsigned pin, unsigned af)
{
    port->MODER = (port->MODER & ~(3u << (2 * pin))) | (2u << (2 * pin));
    port->OSPEEDR |= 3u << (2 * pin);
    port->AFR[pin / 8] = (port->AFR[pin / 8] & ~(0xFu << (4 * (pin % 8)))) |
                         (af << (4 * (pin % 8)));
}

void serial_init(uint32_t baud)
{
    RCC->AHB4ENR |= RCC_AHB4ENR_GPIODEN;
    RCC->AHB1ENR |= RCC_AHB1ENR_DMA1EN;
    RCC->APB1LENR |= RCC_APB1LENR_USART3EN;
    (void)RCC->APB1LENR;
    pin_af(GPIOD, 8, 7);
    pin_af(GPIOD, 9, 7);
    USART3->CR1 = 0;
    USART3->BRR = (clocks.pclk_hz + baud / 2u) / baud; /* oversampling 16 */
    USART3->CR3 = USART_CR3_DMAT;
    USART3->CR1 = USART_CR1_FIFOEN | USART_CR1_RXNEIE | USART_CR1_TE | USART_CR1_RE |
                  USART_CR1_UE;
    DMAMUX1_CCR(TX_STREAM) = DMAMUX_REQ_USART3_TX;
    DMA1->S[TX_STREAM].PAR = (uint32_t)(uintptr_t)&USART3->TDR;
    nvic_enable(IRQ_USART3);
}

void USART3_IRQHandler(void)
{
    uint32_t isr = USART3->ISR;
    if (isr & (USART_ISR_ORE | USART_ISR_FE | USART_ISR_NE)) {
        USART3->ICR = USART_ISR_ORE | USART_ISR_FE | USART_ISR_NE;
        rx_overflow++; /* the frame's CRC check will reject the damaged frame */
    }
    while (USART3->ISR & USART_ISR_RXNE) {
        uint8_t b = (uint8_t)USART3->RDR;
        uint32_t next = (rx_head + 1u) % RX_RING;
        if (next == rx_tail) {
            rx_overflow++;
            continue;
        }
        rx_ring[rx_head] = b;
        rx_head = next;
    }
}

size_t serial_read(uint8_t *out, size_t cap)
{
    size_t n = 0;
    while (n < cap && rx_tail != rx_head) {
        out[n++] = rx_ring[rx_tail];
        rx_tail = (rx_tail + 1u) % RX_RING;
    }
    return n;
}

/* the frame lives in AXI SRAM: write its cache lines back before the DMA reads it */
void serial_tx_start(const uint8_t *p, size_t n)
{
    struct dma_stream *s = &DMA1->S[TX_STREAM];
    s->CR = 0;
    (void)wait_bits(&s->CR, DMA_CR_EN, 0, 1000u); /* idle or finishing one byte: < 1 us */
    dcache_clean(p, (uint32_t)n);
    DMA1->LIFCR = DMA_LIFCR_S1;
    USART3->ICR = 1u << 6; /* TCCF */
    s->M0AR = (uint32_t)(uintptr_t)p;
    s->NDTR = (uint32_t)n;
    s->FCR = 0;
    s->CR = DMA_CR_DIR_M2P | DMA_CR_MINC | DMA_CR_PL_HIGH | DMA_CR_EN;
}

bool serial_tx_busy(void)
{
    return (DMA1->S[TX_STREAM].CR & DMA_CR_EN) || !(USART3->ISR & USART_ISR_TC);
}

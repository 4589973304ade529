/*
 * uart.c — the serial transport: USART2 (BOARD_UART=2, the ST-LINK virtual COM port) or USART1
 * (BOARD_UART=1, the sheet's RS-485 multi-drop bus with its driver enable on PA8). RX interrupt into a
 * ring (the ISR writes the head, the main loop the tail), blocking TX. See board.h.
 *
 * Baud: oversampling by 8, baud = 2 fck / USARTDIV with fck = PCLK = 64 MHz, so up to 8 Mbaud and
 * exact at 8, 4, 2 and 1 Mbaud; 3 Mbaud is 2.977 Mbaud (USARTDIV 43, -0.78 %) (RM0444 "USART baud
 * rate generation"). The FIFO mode's 8-byte RX FIFO gives the ISR
 * eight byte times (10 µs at 8 Mbaud) of slack.
 *
 * Unlike QEMU's UART, this one cannot hold input back: when the ring is full a byte is dropped and
 * counted (uart_lost), as are overrun, framing and noise errors; the chip's stream decoder then counts
 * the frame they broke in rx_errors, which the host reads in STATUS.
 */
#include "board.h"

#if BOARD_UART == 1
#define UART_BASE USART1_BASE
#define UART_IRQ IRQ_USART1
#else
#define UART_BASE USART2_BASE
#define UART_IRQ IRQ_USART2
#endif

static volatile uint8_t rx_ring[UART_RX_RING_SIZE];
static volatile uint32_t rx_head; /* written by the ISR only */
static volatile uint32_t rx_tail; /* written by the main loop only */
static volatile uint32_t rx_lost; /* written by the ISR only */

void uart_init(uint32_t baud)
{
    uint32_t div = (2u * PCLK_HZ + baud / 2u) / baud;
    if (div < 16u) {
        div = 16u; /* the fastest the part can do: fck / 8 */
    }
#if BOARD_UART == 1
    RCC_APBENR2 |= RCC_APBENR2_USART1EN;
    gpio_out(GPIOA_BASE, 8u, false); /* RS-485 driver enable: off (receive) */
    gpio_af(GPIOC_BASE, 4u, 1u);     /* USART1_TX */
    gpio_af(GPIOC_BASE, 5u, 1u);     /* USART1_RX */
#else
    RCC_APBENR1 |= RCC_APBENR1_USART2EN;
    gpio_af(GPIOA_BASE, 2u, 1u); /* USART2_TX */
    gpio_af(GPIOA_BASE, 3u, 1u); /* USART2_RX */
#endif
    USART_CR1(UART_BASE) = 0u;
    USART_BRR(UART_BASE) = (div & 0xFFF0u) | ((div & 0xFu) >> 1); /* OVER8: BRR[3] stays 0 */
    USART_CR3(UART_BASE) = USART_CR3_EIE;
    /* FIFOEN and OVER8 are written while UE = 0 (RM0444 USART_CR1), then the USART is enabled */
    USART_CR1(UART_BASE) = USART_CR1_FIFOEN | USART_CR1_OVER8 | USART_CR1_RXFNEIE | USART_CR1_TE | USART_CR1_RE;
    USART_CR1(UART_BASE) |= USART_CR1_UE;
    NVIC_ISER = 1u << UART_IRQ;
}

void usart_irq(void)
{
    uint32_t isr = USART_ISR(UART_BASE);
    if ((isr & (USART_ISR_ORE | USART_ISR_FE | USART_ISR_NE | USART_ISR_PE)) != 0u) {
        rx_lost = rx_lost + 1u;
        USART_ICR(UART_BASE) = USART_ICR_ERRORS;
    }
    while ((isr & USART_ISR_RXFNE) != 0u) {
        const uint8_t byte = (uint8_t)(USART_RDR(UART_BASE) & 0xFFu);
        const uint32_t head = rx_head;
        if (head - rx_tail >= UART_RX_RING_SIZE) {
            rx_lost = rx_lost + 1u;
        } else {
            rx_ring[head & (UART_RX_RING_SIZE - 1u)] = byte;
            rx_head = head + 1u; /* a 32-bit store: atomic on Cortex-M */
        }
        isr = USART_ISR(UART_BASE);
    }
}

size_t uart_read(uint8_t *out, size_t cap)
{
    size_t n = 0;
    uint32_t tail = rx_tail;
    const uint32_t head = rx_head;
    while (tail != head && n < cap) {
        out[n++] = rx_ring[tail & (UART_RX_RING_SIZE - 1u)];
        tail++;
    }
    rx_tail = tail;
    return n;
}

void uart_write(const uint8_t *data, size_t len)
{
    size_t i;
#if BOARD_UART == 1
    gpio_write(GPIOA_BASE, 8u, true);
#endif
    for (i = 0; i < len; i++) {
        while ((USART_ISR(UART_BASE) & USART_ISR_TXFNF) == 0u) {
        }
        USART_TDR(UART_BASE) = data[i];
    }
    while ((USART_ISR(UART_BASE) & USART_ISR_TC) == 0u) {
    }
#if BOARD_UART == 1
    gpio_write(GPIOA_BASE, 8u, false); /* the stop bit is out: release the bus */
#endif
}

bool uart_pending(void)
{
    return rx_head != rx_tail;
}

uint32_t uart_lost(void)
{
    return rx_lost;
}

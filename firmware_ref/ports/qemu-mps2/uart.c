/* uart.c — CMSDK APB UART0 driver: RX interrupt into a ring buffer, blocking TX. See board.h. */
#include "board.h"

static volatile uint8_t rx_ring[UART_RX_RING_SIZE];
static volatile uint32_t rx_head; /* written by the ISR only */
static volatile uint32_t rx_tail; /* written by the main loop only */
static volatile uint32_t rx_stalled; /* the ISR found the ring full and stopped */

void uart_init(void)
{
    UART_BAUDDIV(UART0_BASE) = 16u; /* any value >= 16; QEMU ignores the rate */
    UART_CTRL(UART0_BASE) = UART_CTRL_TX_EN | UART_CTRL_RX_EN | UART_CTRL_RX_INT_EN;
    NVIC_ISER0 = 1u << 0; /* IRQ 0: UART0 RX */
}

/* RX interrupt: move every received byte into the ring. When the ring is full the byte stays in the
 * UART (which then holds back further input, as hardware flow control would) and the interrupt is
 * disabled; uart_read turns it back on once there is room. So no byte is ever dropped. */
void uart0_rx_irq(void)
{
    UART_INTSTATUS(UART0_BASE) = UART_INT_RX;
    while (UART_STATE(UART0_BASE) & UART_STATE_RX_FULL) {
        const uint32_t head = rx_head;
        if (head - rx_tail >= UART_RX_RING_SIZE) {
            UART_CTRL(UART0_BASE) = UART_CTRL_TX_EN | UART_CTRL_RX_EN; /* full: stop until drained */
            rx_stalled = 1u;
            return;
        }
        rx_ring[head & (UART_RX_RING_SIZE - 1u)] = (uint8_t)(UART_DATA(UART0_BASE) & 0xFFu);
        rx_head = head + 1u; /* a 32-bit store: atomic on Cortex-M */
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
    if (rx_stalled && n > 0u) {
        /* room again: take what waits in the UART and let the interrupt run again */
        __asm volatile("cpsid i" ::: "memory");
        rx_stalled = 0u;
        UART_CTRL(UART0_BASE) = UART_CTRL_TX_EN | UART_CTRL_RX_EN | UART_CTRL_RX_INT_EN;
        uart0_rx_irq();
        __asm volatile("cpsie i" ::: "memory");
    }
    return n;
}

void uart_write(const uint8_t *data, size_t len)
{
    size_t i;
    for (i = 0; i < len; i++) {
        while (UART_STATE(UART0_BASE) & UART_STATE_TX_FULL) {
        }
        UART_DATA(UART0_BASE) = data[i];
    }
}


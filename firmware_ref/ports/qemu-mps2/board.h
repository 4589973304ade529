/*
 * board.h — the QEMU mps2-an385 port of the reference firmware: registers and the port's API.
 *
 * Peripherals (ARM AN385 application note; QEMU hw/arm/mps2.c, hw/char/cmsdk-apb-uart.c,
 * hw/misc/mps2-fpgaio.c):
 *   UART0  0x40004000  CMSDK APB UART; IRQ 0 = RX, IRQ 1 = TX
 *   FPGAIO 0x40028000  COUNTER (0x18) counts at 25 MHz / (PRESCALE + 1); PRESCALE (0x1C) = 24
 *                      gives the 1 MHz time base of the chip
 *   SysTick            1 kHz, only to wake the core from WFI (time is never counted in ticks:
 *                      a tick lost while the emulator's host is busy would lose time)
 *
 * Concurrency: the UART RX interrupt is the only ISR that touches shared data; it writes the RX
 * ring (uart.c) and nothing else. Every capsheet_chip_* call runs in the main loop, never in an
 * ISR (the library is not reentrant; see firmware_ref/README.md "Integration rules").
 */
#ifndef CAPSHEET_BOARD_H
#define CAPSHEET_BOARD_H

#include <stddef.h>
#include <stdint.h>

#define REG32(addr) (*(volatile uint32_t *)(uintptr_t)(addr))

#define SYSCLK_HZ 25000000u

#define UART0_BASE 0x40004000u
#define UART_DATA(b) REG32((b) + 0x000u)
#define UART_STATE(b) REG32((b) + 0x004u)
#define UART_CTRL(b) REG32((b) + 0x008u)
#define UART_INTSTATUS(b) REG32((b) + 0x00Cu) /* write 1 to clear */
#define UART_BAUDDIV(b) REG32((b) + 0x010u)
#define UART_STATE_TX_FULL 0x1u
#define UART_STATE_RX_FULL 0x2u
#define UART_CTRL_TX_EN 0x1u
#define UART_CTRL_RX_EN 0x2u
#define UART_CTRL_RX_INT_EN 0x8u
#define UART_INT_RX 0x2u

#define FPGAIO_BASE 0x40028000u
#define FPGAIO_COUNTER REG32(FPGAIO_BASE + 0x18u)
#define FPGAIO_PRESCALE REG32(FPGAIO_BASE + 0x1Cu)

#define NVIC_ISER0 REG32(0xE000E100u)
#define SYST_CSR REG32(0xE000E010u)
#define SYST_RVR REG32(0xE000E014u)
#define SYST_CVR REG32(0xE000E018u)

#define STACK_PAINT 0xDEADBEEFu

/* RX ring: power of two, written by the ISR only, read by the main loop only. */
#define UART_RX_RING_SIZE 256u

void uart_init(void);
/* Copy up to `cap` received bytes out of the RX ring; returns how many (0 if none). A full ring
 * holds input back in the UART (no byte is dropped) until this makes room. */
size_t uart_read(uint8_t *out, size_t cap);
/* Blocking write: returns once every byte is in the UART (so `data` may be reused at once). */
void uart_write(const uint8_t *data, size_t len);
void uart0_rx_irq(void);

void clock_init(void);
/* Microseconds since clock_init, from the free-running FPGAIO counter, extended to 64 bits.
 * Call it from the main loop only (at least once every 71 minutes, which the loop does). */
uint64_t clock_us(void);
void systick_irq(void);

#endif

/*
 * startup.c — reset and vector table for QEMU mps2-an385 (Cortex-M3; the code is Cortex-M0+
 * compatible C). Copies .data, zeroes .bss, paints the stack with STACK_PAINT (so its high-water
 * mark can be measured), then calls main(). Unused exceptions and IRQs spin in default_handler.
 */
#include <stdint.h>

#include "board.h"

extern uint32_t __data_load, __data_start, __data_end, __bss_start, __bss_end;
extern uint32_t __stack_bottom[], __stack_top[];

int main(void);
void reset_handler(void);
void default_handler(void);

void default_handler(void)
{
    for (;;) {
    }
}

void reset_handler(void)
{
    uint32_t *src = &__data_load;
    uint32_t *dst = &__data_start;
    volatile uint32_t marker = 0u;
    uintptr_t a;
    const uintptr_t end = (uintptr_t)&marker - 64u; /* this function's frame stays unpainted */
    while (dst < &__data_end) {
        *dst++ = *src++;
    }
    for (dst = &__bss_start; dst < &__bss_end; dst++) {
        *dst = 0u;
    }
    /* paint the stack below the current frame (a few words are in use by this function) */
    for (a = (uintptr_t)__stack_bottom; a < end; a += 4u) {
        *(volatile uint32_t *)a = STACK_PAINT;
    }
    (void)main();
    for (;;) {
    }
}

typedef void (*vector_t)(void);

/* 16 exception vectors, then the AN385 IRQs: 0 UART0 RX, 1 UART0 TX, ... (QEMU hw/arm/mps2.c) */
__attribute__((section(".vectors"), used)) static const vector_t vectors[16 + 32] = {
    (vector_t)(uintptr_t)__stack_top, /* initial SP */
    reset_handler,
    default_handler, /* NMI */
    default_handler, /* HardFault */
    default_handler, /* MemManage */
    default_handler, /* BusFault */
    default_handler, /* UsageFault */
    0, 0, 0, 0,
    default_handler, /* SVCall */
    default_handler, /* DebugMon */
    0,
    default_handler, /* PendSV */
    systick_irq,     /* SysTick: wakes the core from WFI (time is the FPGAIO counter) */
    uart0_rx_irq,    /* IRQ 0: UART0 RX */
    default_handler, default_handler, default_handler, default_handler, default_handler, default_handler,
    default_handler, default_handler, default_handler, default_handler, default_handler, default_handler,
    default_handler, default_handler, default_handler, default_handler, default_handler, default_handler,
    default_handler, default_handler, default_handler, default_handler, default_handler, default_handler,
    default_handler, default_handler, default_handler, default_handler, default_handler, default_handler,
    default_handler,
};

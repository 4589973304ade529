/*
 * startup.c — reset and vector table for the STM32G0B1RE (Cortex-M0+). Copies .data, zeroes .bss,
 * paints the stack with STACK_PAINT (so its high-water mark can be read with a debugger), then calls
 * main(). Unused exceptions and IRQs spin in default_handler (a debugger shows which).
 *
 * Vector table: 16 Cortex-M0+ exception entries (Armv6-M ARM B1.5.3), then the 32 IRQs of RM0444
 * "Nested vectored interrupt controller (NVIC)", vector table (21: TIM16 / FDCAN1 interrupt line 0,
 * 27: USART1, 28: USART2 / LPUART2). The core boots from 0x08000000 (BOOT0 low, the option bytes'
 * reset state on a Nucleo) and reads the initial SP and the reset vector there.
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
    for (a = (uintptr_t)__stack_bottom; a < end; a += 4u) {
        *(volatile uint32_t *)a = STACK_PAINT;
    }
    (void)main();
    for (;;) {
    }
}

typedef void (*vector_t)(void);

#define D default_handler
#if BOARD_TRANSPORT_CAN
#define V_FDCAN1 fdcan1_irq
#define V_USART1 D
#define V_USART2 D
#elif BOARD_UART == 1
#define V_FDCAN1 D
#define V_USART1 usart_irq
#define V_USART2 D
#else
#define V_FDCAN1 D
#define V_USART1 D
#define V_USART2 usart_irq
#endif
__attribute__((section(".vectors"), used)) static const vector_t vectors[16 + 32] = {
    (vector_t)(uintptr_t)__stack_top, /* initial SP */
    reset_handler,
    D, /* NMI (also a flash double ECC error) */
    D, /* HardFault */
    0, 0, 0, 0, 0, 0, 0,
    D, /* SVCall */
    0, 0,
    D, /* PendSV */
    systick_irq, /* SysTick: wakes the core from WFI (time is TIM2) */
    /* IRQ 0..20 */
    D, D, D, D, D, D, D, D, D, D, D, D, D, D, D, D, D, D, D, D, D,
    V_FDCAN1, /* 21: TIM16, FDCAN1 interrupt line 0 */
    D, D, D, D, D, /* 22..26 */
    V_USART1, /* 27: USART1 */
    V_USART2, /* 28: USART2, LPUART2 */
    D, D, D, /* 29..31 */
};

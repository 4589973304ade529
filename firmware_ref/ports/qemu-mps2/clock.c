/* clock.c — the chip's time base: the FPGAIO free-running counter at 1 MHz. See board.h. */
#include "board.h"

#ifndef CLOCK_DIVIDER
#define CLOCK_DIVIDER 1u /* a mutant build (-DCLOCK_DIVIDER=2) runs its clock at half speed */
#endif

static uint32_t start; /* counter value at clock_init */
static uint32_t last;
static uint64_t high;

void clock_init(void)
{
    FPGAIO_PRESCALE = SYSCLK_HZ / 1000000u - 1u;
    start = FPGAIO_COUNTER;
    last = start;
    high = 0;
    /* SysTick at 1 kHz only wakes the core from WFI; it counts nothing */
    SYST_RVR = SYSCLK_HZ / 1000u - 1u;
    SYST_CVR = 0u;
    SYST_CSR = 0x7u; /* enable, interrupt, processor clock */
}

uint64_t clock_us(void)
{
    const uint32_t now = FPGAIO_COUNTER;
    if (now < last) {
        high += (uint64_t)1u << 32;
    }
    last = now;
    return ((high | now) - start) / CLOCK_DIVIDER;
}

void systick_irq(void) {}

/* gpio.c — pin set-up (RM0444 "GPIO registers": MODER, OSPEEDR, AFRL/AFRH, BSRR). See board.h. */
#include "board.h"

static void set2(volatile uint32_t *reg, unsigned pin, uint32_t value)
{
    *reg = (*reg & ~(3u << (2u * pin))) | (value << (2u * pin));
}

void gpio_af(uint32_t port, unsigned pin, unsigned af)
{
    volatile uint32_t *afr = pin < 8u ? &GPIO_AFRL(port) : &GPIO_AFRH(port);
    const unsigned shift = 4u * (pin & 7u);
    *afr = (*afr & ~(0xFu << shift)) | ((uint32_t)af << shift);
    set2(&GPIO_OSPEEDR(port), pin, 3u); /* very high speed: SPI at 8 MHz, UART at 8 Mbaud */
    set2(&GPIO_MODER(port), pin, GPIO_MODE_AF);
}

void gpio_write(uint32_t port, unsigned pin, bool high)
{
    GPIO_BSRR(port) = high ? (1u << pin) : (1u << (pin + 16u));
}

void gpio_out(uint32_t port, unsigned pin, bool high)
{
    gpio_write(port, pin, high); /* the level first, so the pin never glitches */
    set2(&GPIO_OSPEEDR(port), pin, 3u);
    set2(&GPIO_MODER(port), pin, GPIO_MODE_OUT);
}

/*
 * spi.c — SPI1 master for the link's sensors: mode 3 (CPOL 1, CPHA 1), 8-bit frames, fPCLK / 8 =
 * 8 MHz, software chip selects on PB0 (the ICM-42688-P) and PB1 (the magnetometer). See board.h.
 *
 * RM0444 "SPI registers" (SPI_CR1, SPI_CR2, SPI_SR, SPI_DR) and "Communication using polling"; an
 * 8-bit frame is written and read with a byte access to SPI_DR (a 16-bit access would pack two), and
 * FRXTH = 1 raises RXNE at one byte. 8 MHz is under both parts' limits: the ICM-42688-P's 24 MHz SPI
 * clock (DS-000347 "SPI interface", modes 0 and 3) and a magnetometer's 10 MHz.
 *
 * Polled, byte by byte (a transaction is a register address and at most a few dozen bytes): a burst
 * of 15 bytes takes ~17 µs. A byte that does not complete within ~64 µs is a bus fault (-2).
 */
#include "board.h"

#define SPI_SPIN_LIMIT 1024u /* polls of SPI_SR per byte, ~64 µs at 64 MHz: a byte takes 1 µs */

static const unsigned cs_pin[2] = {0u, 1u}; /* PB0, PB1 */

/* Configure with SPE = 0, then enable (RM0444 "Configuration of SPI"); also the recovery after a mode
 * fault, which clears SPE and MSTR. */
static void configure(void)
{
    SPI1_CR1 = 0u;
    SPI1_CR2 = SPI_CR2_DS_8BIT | SPI_CR2_FRXTH;
    SPI1_CR1 = SPI_CR1_CPOL | SPI_CR1_CPHA | SPI_CR1_MSTR | (2u << SPI_CR1_BR_SHIFT) | SPI_CR1_SSM | SPI_CR1_SSI;
    SPI1_CR1 |= SPI_CR1_SPE;
}

void spi_init(void)
{
    RCC_APBENR2 |= RCC_APBENR2_SPI1EN;
    gpio_out(GPIOB_BASE, cs_pin[0], true);
    gpio_out(GPIOB_BASE, cs_pin[1], true);
    gpio_af(GPIOA_BASE, 5u, 0u); /* SPI1_SCK */
    gpio_af(GPIOA_BASE, 6u, 0u); /* SPI1_MISO */
    gpio_af(GPIOA_BASE, 7u, 0u); /* SPI1_MOSI */
    configure();
}

static bool wait_sr(uint32_t mask)
{
    uint32_t n;
    for (n = 0; n < SPI_SPIN_LIMIT; n++) {
        if ((SPI1_SR & mask) != 0u) {
            return true;
        }
    }
    return false;
}

static void drain(void)
{
    while ((SPI1_SR & SPI_SR_FRLVL_MASK) != 0u) {
        (void)SPI1_DR8;
    }
}

int32_t spi_transfer(uint8_t cs, const uint8_t *tx, uint8_t *rx, size_t len)
{
    size_t i;
    int32_t rc = 0;
    uint32_t n;
    if (cs > 1u || len == 0u || tx == NULL) {
        return -1;
    }
    drain();
    gpio_write(GPIOB_BASE, cs_pin[cs], false);
    for (i = 0; i < len; i++) {
        uint8_t byte;
        if (!wait_sr(SPI_SR_TXE)) {
            rc = -2;
            break;
        }
        SPI1_DR8 = tx[i];
        if (!wait_sr(SPI_SR_RXNE)) {
            rc = -2;
            break;
        }
        byte = SPI1_DR8;
        if (rx != NULL) {
            rx[i] = byte;
        }
    }
    for (n = 0; n < SPI_SPIN_LIMIT && (SPI1_SR & SPI_SR_BSY) != 0u; n++) {
    }
    if ((SPI1_SR & (SPI_SR_MODF | SPI_SR_OVR | SPI_SR_BSY)) != 0u) {
        rc = -2;
    }
    gpio_write(GPIOB_BASE, cs_pin[cs], true);
    if (rc != 0) {
        drain();
        configure(); /* the SR read above and this CR1 write clear MODF */
    }
    return rc;
}

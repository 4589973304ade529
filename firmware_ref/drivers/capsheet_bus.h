/*
 * capsheet_bus.h — a link MCU's sensor bus, below every sensor driver of firmware_ref/drivers/.
 *
 * One SPI transaction per chip select (full duplex: `len` bytes out of `tx`, `len` bytes into `rx`,
 * chip select asserted for the whole transaction), and an I2C write-then-read (a repeated start
 * between the two; `rx_len` 0 is a plain write, `tx_len` 0 a plain read). The port implements the
 * callbacks (a real board: its SPI/I2C peripheral; the SIL build: the register emulators of
 * virtual_sheet/parts/). A driver never touches hardware otherwise.
 *
 * Return values: 0 (or any non-negative value) on success; negative on a bus error (a NAK, a
 * timeout, a stuck line): the driver maps it to a sensor fault, never to a reading.
 *
 * delay_us is optional: when it is NULL a driver never blocks, and answers "busy, call again at
 * now + t" instead of waiting (time is always passed in, never read).
 */
#ifndef CAPSHEET_BUS_H
#define CAPSHEET_BUS_H

#include <stddef.h>
#include <stdint.h>

#include "capsheet_fw.h"

#ifdef __cplusplus
extern "C" {
#endif

typedef struct {
    void *user;
    CAPSHEET_WARN_UNUSED int32_t (*spi_transfer)(void *user, uint8_t cs, const uint8_t *tx, uint8_t *rx, size_t len);
    CAPSHEET_WARN_UNUSED int32_t (*i2c_write_read)(void *user, uint8_t addr7, const uint8_t *tx, size_t tx_len,
                                                   uint8_t *rx, size_t rx_len);
    void (*delay_us)(void *user, uint32_t us);   /* optional; NULL: the driver returns "busy, try at now+t" instead */
} capsheet_bus_t;

#ifdef __cplusplus
}
#endif

#endif /* CAPSHEET_BUS_H */

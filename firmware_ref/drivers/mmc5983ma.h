/*
 * mmc5983ma.h — driver for the MEMSIC MMC5983MA 3-axis magnetometer on 4-wire SPI (datasheet
 * "MMC5983MA Rev A", 4/3/2019; register and bit names in mmc5983ma_reg.h, each cited there).
 *
 * C99, no dynamic memory, time passed in (`now_us`), every failure a negative return code. The
 * driver never blocks: a step that must wait answers how long (a positive number of µs) and is
 * called again then; mmc5983ma_run waits with the bus's delay_us instead.
 *
 * Life of a part:
 *   mmc5983ma_init  -> the state, nothing on the bus
 *   mmc5983ma_step  -> power-on time (10 ms + 20 %), probe (Product ID1 0x30), SW_RST and its wait, the
 *                      OTP check, bandwidth, self-test (SET, measure, RESET, measure: the bridge
 *                      offset, which must be within the datasheet's 0.5 G null-field output and off
 *                      the rails), a temperature measurement, SET and the first measurement; 0 once
 *                      running.
 *   mmc5983ma_read  -> one burst of Xout0..Status; a finished measurement is taken (its bridge offset
 *                      removed) and the next one started (SET, then TM_M: one measurement per call,
 *                      at most one in flight); the latest field scaled to the protocol's 16-bit
 *                      counts at a CONFIG_IMU mag_range code (docs/protocol.md §16.1).
 *
 * Every read checks that the part answers like an MMC5983MA (Status's reserved bits 0, OTP_Rd_Done
 * set, XYZout2's two low bits 0): a part gone from the bus (SDO floating high or stuck low), reset
 * behind the driver's back, or one whose measurement never finishes is a sticky error — the chip
 * reports a sensor fault, never a frozen value.
 *
 * What each outcome becomes on the wire (docs/protocol.md §16.1, §8.6), through link_sensors.c:
 *   a reading, in range                  counts, no status bit
 *   the part's output at its 18-bit rail SATURATED, the count at -32768 / +32767 (its sign)
 *   a field beyond the mag_range code    SATURATED, the count at its rail
 *   no new measurement since the last    the last output again, no STALE (the part's rate is its own)
 *   any negative return (BUS, PRODUCT_ID, OTP, SELF_TEST, TIMEOUT, GONE, NOT_READY)
 *                                        a sensor fault: INVALID record, the chip in FAULT
 * Not used: the INT pin (Meas_M_Done is polled in the same burst as the data), Auto_SR_en and
 * continuous mode (one SET + TM_M per measurement keeps the offset's polarity known), 16-bit
 * operation, the St_enp / St_enm coil (the datasheet gives no size for its field, so no limit to
 * test it against).
 */
#ifndef MMC5983MA_H
#define MMC5983MA_H

#include <stdbool.h>
#include <stdint.h>

#include "capsheet_fw.h"
#include "capsheet_bus.h"
#include "link_sensors.h"

#ifdef __cplusplus
extern "C" {
#endif

/* Error codes: negative, beside capsheet_fw.h's (to -12) and icm42688p.h's (-20..-26). */
#define MMC5983MA_ERR_BUS (-40)         /* the bus callback failed */
#define MMC5983MA_ERR_PRODUCT_ID (-41)  /* Product ID1 is not 0x30: not this part, or a bus reading garbage */
#define MMC5983MA_ERR_OTP (-42)         /* OTP_Rd_Done not set after the reset: the part could not read its memory */
#define MMC5983MA_ERR_SELF_TEST (-43)   /* the SET/RESET offset is outside 0.5 G, or a bridge sits at its rail */
#define MMC5983MA_ERR_TIMEOUT (-44)     /* a measurement did not finish in 4x its time + 1 ms */
#define MMC5983MA_ERR_GONE (-45)        /* the part stopped answering like an MMC5983MA (floating/stuck SDO, reset) */
#define MMC5983MA_ERR_NOT_READY (-46)   /* read before the bring-up finished */
#define MMC5983MA_ERR_ARGUMENT (-47)    /* an argument out of its documented domain */

typedef struct {
    const capsheet_bus_t *bus;
    uint8_t cs;               /* SPI chip select (on SPI) */
    uint8_t i2c_addr;         /* 7-bit I2C address, 0x30 (on I2C: mmc5983ma_init_i2c) */
    bool on_i2c;
    uint8_t bw;               /* Internal control 1 BW code: 0 8 ms, 1 4 ms, 2 2 ms, 3 0.5 ms */
    int8_t axes[3];           /* sensor-frame axis i = sign * part axis |axes[i]| - 1 (1, 2, 3 = x, y, z) */
    uint8_t phase;            /* bring-up phase (mmc5983ma.c) */
    bool pending;             /* a field measurement was started and not yet taken */
    bool have_field;
    uint8_t railed;           /* bit i: part axis i's last output sat at 0 or 262143 (saturated) */
    uint64_t wait_until_us;   /* the phase's wait ends */
    uint64_t start_us;        /* the measurement in flight started (its TM_M was written) */
    uint64_t latch_us;        /* the latest field's instant: the middle of its measurement window */
    int32_t error;            /* sticky: the first failure (0: none) */
    uint32_t raw_set[3];      /* self-test: outputs after SET and after RESET */
    uint32_t raw_reset[3];
    int32_t offset2[3];       /* twice the bridge offset, 18-bit counts (Output1 + Output2 - 2 * 131072) */
    int32_t field2[3];        /* twice the latest field, 18-bit counts, offset removed, part axes */
    uint8_t tout;             /* Tout of the bring-up's temperature measurement */
    uint32_t measurements;    /* field measurements taken since the bring-up */
} mmc5983ma_t;

/* Initialise `d` for the part on chip select `cs` with bandwidth code `bw` (0..3); nothing goes on
 * the bus. MMC5983MA_ERR_ARGUMENT for a NULL pointer, a bus without spi_transfer or bw > 3. */
CAPSHEET_WARN_UNUSED int32_t mmc5983ma_init(mmc5983ma_t *d, const capsheet_bus_t *bus, uint8_t cs, uint8_t bw);

/* The same on I2C at 7-bit address `addr7` (the part's is 0x30, DS Rev A p.9); ARGUMENT for a bus
 * without i2c_write_read. SPI_CS must be tied to VDDIO (p.11). Over I2C a part that is gone does not
 * acknowledge: the bus callback fails (BUS). */
CAPSHEET_WARN_UNUSED int32_t mmc5983ma_init_i2c(mmc5983ma_t *d, const capsheet_bus_t *bus, uint8_t addr7, uint8_t bw);

/* The part's mounting: sensor-frame axis i is part axis |axes[i]| (1..3), negated when axes[i] < 0.
 * The default is {1, 2, 3}. ARGUMENT unless the three name each part axis once. */
CAPSHEET_WARN_UNUSED int32_t mmc5983ma_set_axes(mmc5983ma_t *d, const int8_t axes[3]);

/* Advance the bring-up, then (running) take a finished measurement and start the next. 0: running
 * and nothing due; > 0: call again in that many µs; negative: failed (sticky until mmc5983ma_init). */
CAPSHEET_WARN_UNUSED int32_t mmc5983ma_step(mmc5983ma_t *d, uint64_t now_us);

/* mmc5983ma_step until running, waiting with the bus's delay_us (ARGUMENT without one); *now_us
 * advances by the time waited. */
CAPSHEET_WARN_UNUSED int32_t mmc5983ma_run(mmc5983ma_t *d, uint64_t *now_us);

/* The latest field as 16-bit counts at mag_range code r (0..3: ±4 (r+1) gauss, 32768 / (4 (r+1))
 * counts per gauss), sensor frame. A saturated axis (the part's output at its rail, or a count
 * beyond the range) is sent at its rail, -32768 or +32767, and *status gets SATURATED; the
 * magnetometer never sets STALE (§16.1: its own rate is the part's business). *latch_us (may be
 * NULL): the reading's instant. NOT_READY before the bring-up; BUS, GONE, TIMEOUT (sticky). */
CAPSHEET_WARN_UNUSED int32_t mmc5983ma_read(mmc5983ma_t *d, uint64_t now_us, uint8_t mag_range, int16_t mag[3],
                                            uint8_t *status, uint64_t *latch_us);

/* The bring-up's die temperature, deci-°C (Tout: -75 °C + 0.8 °C per code). */
int32_t mmc5983ma_temperature_dc(const mmc5983ma_t *d);

/* Fill `out` so the link glue (link_sensors.h) reads this magnetometer: poll = mmc5983ma_step,
 * read = mmc5983ma_read. */
void mmc5983ma_mag_driver(mmc5983ma_t *d, capsheet_mag_driver_t *out);

/* Register access: over SPI the read bit and address as the datasheet's command byte (p.5-7); over
 * I2C the register address written, then the bytes read or written (p.17). */
CAPSHEET_WARN_UNUSED int32_t mmc5983ma_read_regs(mmc5983ma_t *d, uint8_t reg, uint8_t *buf, size_t len);
CAPSHEET_WARN_UNUSED int32_t mmc5983ma_write_reg(mmc5983ma_t *d, uint8_t reg, uint8_t value);

#ifdef __cplusplus
}
#endif

#endif /* MMC5983MA_H */

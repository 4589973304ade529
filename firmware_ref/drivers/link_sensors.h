/*
 * link_sensors.h — the glue between a link's sensor drivers and the chip's HAL (capsheet_fw.h):
 * implements capsheet_hal_t read_axes / read_imu on top of the ICM-42688-P driver (icm42688p.h)
 * and, for a 9-axis chip, a magnetometer driver reached through capsheet_mag_driver_t.
 *
 * Wiring (a port, or the SIL build):
 *     static capsheet_link_sensors_t ls;
 *     capsheet_link_sensors_init(&ls, &bus, IMU_CS, &mag_or_NULL, &chip);
 *     hal.user = &ls; hal.read_axes = capsheet_link_read_axes; hal.read_imu = capsheet_link_read_imu;
 *     ... in the main loop: capsheet_link_sensors_poll(&ls, now_us)  (bring-up, no blocking)
 *     ... in the INT1 (data ready) interrupt, or its timestamped capture: capsheet_link_data_ready(&ls, edge_us)
 *
 * The glue reads the chip's CONFIG (range, rate, filter) and CONFIG_IMU (gyroscope range) from the
 * chip's readable fields and reconfigures the part when they change; a conversion made before the
 * change is not reported fresh (docs/protocol.md §5.3).
 */
#ifndef CAPSHEET_LINK_SENSORS_H
#define CAPSHEET_LINK_SENSORS_H

#include <stdbool.h>
#include <stdint.h>

#include "capsheet_fw.h"
#include "capsheet_bus.h"
#include "icm42688p.h"

#ifdef __cplusplus
extern "C" {
#endif

/* A magnetometer as the glue sees it: its own driver (firmware_ref/drivers/) fills this in.
 *   poll: optional (NULL: none). Advance the part's bring-up / conversions without blocking; called
 *         from capsheet_link_sensors_poll. 0: ready; > 0: call again in that many µs; negative: the
 *         part failed (the chip then reports a sensor fault).
 *   read: the part's latest output, in 16-bit counts at the protocol's mag_range code (docs/protocol.md
 *         §16.1: full scale 4 (r + 1) gauss, 32768 / full scale counts per gauss), sensor frame (§1.1),
 *         and SampleStatus bits in *status (SELF_TEST while its self-test runs; INVALID: no reading).
 *         A magnetometer slower than the SYNC rate repeats its last output without STALE (§16.1).
 *         Negative: a bus error or a failed part (a sensor fault: the record is INVALID, the chip FAULT). */
typedef struct {
    void *ctx;
    CAPSHEET_WARN_UNUSED int32_t (*poll)(void *ctx, uint64_t now_us);
    CAPSHEET_WARN_UNUSED int32_t (*read)(void *ctx, uint64_t now_us, uint8_t mag_range, int16_t mag[3], uint8_t *status);
} capsheet_mag_driver_t;

typedef struct {
    icm42688p_t imu;
    const capsheet_mag_driver_t *mag;   /* NULL: no magnetometer (a 6-axis or accelerometer-only chip) */
    const capsheet_chip_t *chip;        /* read only: CONFIG and CONFIG_IMU as the chip accepted them */
    bool have_accel;                    /* a conversion was read since bring-up (else the counts are 0) */
    bool gyro_fresh;                    /* read_axes found a fresh conversion: read_imu's gyroscope is it */
    int16_t accel[3];                   /* the last reading, reported again with STALE */
    int16_t gyro[3];
    uint64_t latch_us;
    uint8_t status;                     /* SampleStatus bits of the last reading (STALE, SELF_TEST) */
    int32_t fault;                      /* the first error that made the link's sensors fail (0: none) */
} capsheet_link_sensors_t;

/* Initialise the glue for the IMU on chip select `imu_cs` of `bus`, the magnetometer `mag` (NULL:
 * none) and the chip `chip` (read for its configuration; may be NULL: CONFIG's power-on values).
 * `self_test`: run the part's self-test during bring-up (its failure is a sensor fault).
 * CAPSHEET_ERR_ARGUMENT for a NULL ls/bus or a bus without spi_transfer. */
CAPSHEET_WARN_UNUSED int32_t capsheet_link_sensors_init(capsheet_link_sensors_t *ls, const capsheet_bus_t *bus,
                                                        uint8_t imu_cs, const capsheet_mag_driver_t *mag,
                                                        const capsheet_chip_t *chip, bool self_test);

/* Advance the bring-up (probe, reset, self-test, configuration, start-up) and the magnetometer's
 * poll without blocking. 0: running; > 0: call again within that many µs; negative: the sensors
 * failed (the error stays: read_axes reports INVALID from then on, never a frozen value). */
CAPSHEET_WARN_UNUSED int32_t capsheet_link_sensors_poll(capsheet_link_sensors_t *ls, uint64_t now_us);

/* The instant of an INT1 data-ready edge on the `now_us` time base (a timestamped interrupt or capture). */
void capsheet_link_data_ready(capsheet_link_sensors_t *ls, uint64_t edge_us);

/* capsheet_hal_t callbacks; `user` is the capsheet_link_sensors_t. */
CAPSHEET_WARN_UNUSED int32_t capsheet_link_read_axes(void *user, uint64_t now_us, int16_t xyz[3], uint8_t *status);
CAPSHEET_WARN_UNUSED int32_t capsheet_link_read_imu(void *user, uint64_t now_us, uint8_t gyro_range, uint8_t mag_range,
                                                    bool want_mag, capsheet_imu_reading_t *out);

#ifdef __cplusplus
}
#endif

#endif /* CAPSHEET_LINK_SENSORS_H */

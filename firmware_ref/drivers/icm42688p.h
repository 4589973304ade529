/*
 * icm42688p.h — driver for the TDK InvenSense ICM-42688-P 6-axis IMU over SPI (datasheet DS-000347;
 * register and bit names in icm42688p_reg.h, each cited there).
 *
 * C99, no dynamic memory, time passed in (`now_us`), every failure a negative return code. The
 * driver never blocks unless the bus has a delay_us callback: a step that must wait answers how long
 * (a positive number of µs) and is called again then.
 *
 * Life of a part:
 *   icm42688p_init     -> the state, nothing on the bus
 *   icm42688p_step     -> probe (WHO_AM_I 0x47), soft reset and its wait, optional self-test,
 *                         configuration, sensors on in low-noise mode and their start-up times;
 *                         0 once running. icm42688p_run does the same, blocking, with delay_us.
 *   icm42688p_configure-> a new full scale / ODR / filter / gyroscope on-off: applied by the next step
 *                         (until the new configuration's first conversion, reads are not fresh)
 *   icm42688p_read     -> INT_STATUS (DATA_RDY), one burst of TEMP + ACCEL + GYRO data registers, and
 *                         WHO_AM_I (a part that answers garbage is a fault, never a reading)
 */
#ifndef ICM42688P_H
#define ICM42688P_H

#include <stdbool.h>
#include <stdint.h>

#include "capsheet_fw.h"
#include "capsheet_bus.h"

#ifdef __cplusplus
extern "C" {
#endif

/* Error codes: negative, beside capsheet_fw.h's (which end at -12). */
#define ICM42688P_ERR_BUS (-20)        /* the bus callback failed (no answer, stuck line) */
#define ICM42688P_ERR_WHO_AM_I (-21)   /* WHO_AM_I is not 0x47: not this part, or a bus that reads garbage */
#define ICM42688P_ERR_RESET (-22)      /* the soft reset did not complete (no RESET_DONE) */
#define ICM42688P_ERR_SELF_TEST (-23)  /* the self-test response is outside the datasheet's limits */
#define ICM42688P_ERR_GONE (-24)       /* the part lost its configuration (reset, brown-out) or its id */
#define ICM42688P_ERR_NOT_READY (-25)  /* read before the bring-up finished */
#define ICM42688P_ERR_ARGUMENT (-26)   /* an argument out of its documented domain */

/* Self-test result bits (icm42688p_t.self_test) */
#define ICM42688P_ST_RAN 0x01u
#define ICM42688P_ST_GYRO_PASS 0x02u
#define ICM42688P_ST_ACCEL_PASS 0x04u

/* What the part is asked to do. Codes are the register fields' own (icm42688p_reg.h). */
typedef struct {
    uint8_t accel_fs_sel;   /* ACCEL_CONFIG0 ACCEL_FS_SEL: 0 ±16 g, 1 ±8 g, 2 ±4 g, 3 ±2 g */
    uint8_t gyro_fs_sel;    /* GYRO_CONFIG0 GYRO_FS_SEL: 0 ±2000 °/s ... 4 ±125 °/s ... 7 ±15.625 °/s */
    uint8_t odr;            /* ACCEL_ODR and GYRO_ODR: 6 = 1 kHz ... (same code for both) */
    uint8_t ui_filt_bw;     /* GYRO_ACCEL_CONFIG0 bandwidth code for both sensors: 0 ODR/2 ... 7 ODR/40 */
    bool gyro_on;           /* gyroscope in low-noise mode (false: off, an accelerometer-only chip) */
} icm42688p_config_t;

/* One burst read. */
typedef struct {
    int16_t temp;           /* TEMP_DATA: °C = temp / 132.48 + 25 */
    int16_t accel[3];       /* counts at the configured ACCEL_FS_SEL, sensor frame of the part */
    int16_t gyro[3];        /* counts at the configured GYRO_FS_SEL (0 when the gyroscope is off) */
    bool fresh;             /* DATA_RDY was set: a conversion finished since the previous read */
    bool saturated;         /* an accelerometer or gyroscope count is at its rail (-32767 .. +32767 ends) */
    bool latch_known;       /* latch_us is the data-ready edge of this conversion */
    uint64_t latch_us;      /* when the conversion was latched (now_us's time base) */
} icm42688p_sample_t;

typedef struct {
    const capsheet_bus_t *bus;
    uint8_t cs;
    uint8_t phase;           /* bring-up phase (icm42688p.c) */
    uint8_t self_test;       /* ICM42688P_ST_* */
    bool want_self_test;
    bool config_dirty;       /* icm42688p_configure changed `want` */
    icm42688p_config_t want; /* asked for */
    icm42688p_config_t cfg;  /* written to the part */
    uint64_t wait_until_us;  /* the phase's wait ends */
    uint64_t fresh_after_us; /* conversions before this instant belong to an older configuration */
    uint64_t last_fresh_us;  /* the last fresh read (or the configuration's start-up end) */
    bool settled;            /* a read after fresh_after_us cleared DATA_RDY: the next one is new */
    int32_t error;           /* sticky: the first failure (0: none) */
    bool drdy_known;         /* a data-ready edge was reported since the last read */
    uint64_t drdy_us;
    /* self-test accumulation */
    uint8_t st_sensor;       /* 0 gyro, 1 accel */
    uint16_t st_count;
    uint16_t st_polls;
    int32_t st_sum[3];
    int32_t st_off[3];
} icm42688p_t;

/* The part's power-on configuration for a capsheet chip: ±2 g, ±1000 °/s, 1 kHz, ODR/4, gyroscope on. */
void icm42688p_default_config(icm42688p_config_t *cfg);

/* Initialise `d` for the part on chip select `cs`; nothing goes on the bus. ICM42688P_ERR_ARGUMENT for
 * a NULL pointer or a bus without spi_transfer. */
CAPSHEET_WARN_UNUSED int32_t icm42688p_init(icm42688p_t *d, const capsheet_bus_t *bus, uint8_t cs, bool self_test);

/* Ask for a configuration (applied at the next step; ARGUMENT for a field out of its range). */
CAPSHEET_WARN_UNUSED int32_t icm42688p_configure(icm42688p_t *d, const icm42688p_config_t *cfg);

/* Advance the bring-up. 0: running (sensors on, started up, configuration applied); > 0: call again
 * in that many µs; negative: failed (sticky until icm42688p_init). */
CAPSHEET_WARN_UNUSED int32_t icm42688p_step(icm42688p_t *d, uint64_t now_us);

/* icm42688p_step until running, waiting with the bus's delay_us (ARGUMENT without one); *now_us
 * advances by the time waited. */
CAPSHEET_WARN_UNUSED int32_t icm42688p_run(icm42688p_t *d, uint64_t *now_us);

/* A data-ready (INT1) edge at `edge_us`: the instant of the conversion the next read returns. */
void icm42688p_data_ready(icm42688p_t *d, uint64_t edge_us);

/* Read INT_STATUS and the data registers. NOT_READY before the bring-up finished; BUS / GONE (sticky:
 * the part is failed from then on, never a frozen value). */
CAPSHEET_WARN_UNUSED int32_t icm42688p_read(icm42688p_t *d, uint64_t now_us, icm42688p_sample_t *out);

/* The self-test is running (its phases of the bring-up). */
bool icm42688p_in_self_test(const icm42688p_t *d);

/* Register access (bank 0 unless REG_BANK_SEL was changed; the driver restores bank 0). */
CAPSHEET_WARN_UNUSED int32_t icm42688p_read_regs(icm42688p_t *d, uint8_t reg, uint8_t *buf, size_t len);
CAPSHEET_WARN_UNUSED int32_t icm42688p_write_reg(icm42688p_t *d, uint8_t reg, uint8_t value);

#ifdef __cplusplus
}
#endif

#endif /* ICM42688P_H */

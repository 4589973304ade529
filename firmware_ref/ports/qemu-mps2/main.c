/*
 * main.c — the reference firmware (firmware_ref/src, unmodified) as a serial chip on QEMU
 * mps2-an385: HAL callbacks over the port's UART, clock and a stub ADC, and the main loop.
 *
 * The stub ADC is a chip lying flat, top face up: (0, 0, +1 g) = (0, 0, 1024) counts at ±2 g,
 * plus ±2 counts of deterministic noise per axis (xorshift32), status 0.
 *
 * Sensors (docs §16; `make -C firmware_ref qemu SENSORS=accel+gyro|accel+gyro+mag`, which sets
 * CAPSHEET_QEMU_SENSORS 1 or 2; default 0, the accelerometer chip): a stub gyroscope at rest (0 °/s,
 * ±2 counts of noise per axis) and a stub magnetometer in a field of (0.2, 0, −0.4) gauss, both
 * latched at the read with the port's clock, so time_us is the true delay from the SYNC's end to
 * the read. The chip then reports GYRO (and MAG) and SAMPLE_TIME.
 *
 * Mutant builds (conformance must fail them; `make -C firmware_ref qemu MUTANT=...`):
 *   -DCAPSHEET_MUTANTS -DCAPSHEET_QEMU_MUTANT=CAPSHEET_MUT_...  the library breaks that rule
 *                          (capsheet_mutant_t in capsheet_fw.h: a dead sensor, a wrong CRC, ...)
 *   -DCLOCK_DIVIDER=2      the clock runs at half speed: heartbeat and re-announce at twice their period
 */
#include <string.h>

#include "board.h"
#include "capsheet_fw.h"

#ifndef CAPSHEET_QEMU_UID
#define CAPSHEET_QEMU_UID 0x0123456789ABCDEFull
#endif

static uint32_t noise_state = 0x12345678u;

static int16_t noise(void)
{
    uint32_t x = noise_state;
    x ^= x << 13;
    x ^= x >> 17;
    x ^= x << 5;
    noise_state = x;
    return (int16_t)((int32_t)(x % 5u) - 2);
}

static int32_t read_axes(void *user, uint64_t now_us, int16_t xyz[3], uint8_t *status)
{
    (void)user;
    (void)now_us;
    xyz[0] = noise();
    xyz[1] = noise();
    xyz[2] = (int16_t)(1024 + noise());
    *status = 0u;
    return 0;
}

#ifndef CAPSHEET_QEMU_SENSORS
#define CAPSHEET_QEMU_SENSORS 0
#endif
#if CAPSHEET_QEMU_SENSORS == 0
#define SENSOR_CAPS 0u
#define READ_IMU 0
#else
#if CAPSHEET_QEMU_SENSORS == 2
#define SENSOR_CAPS (CAPSHEET_CAP_GYRO | CAPSHEET_CAP_MAG | CAPSHEET_CAP_SAMPLE_TIME)
#else
#define SENSOR_CAPS (CAPSHEET_CAP_GYRO | CAPSHEET_CAP_SAMPLE_TIME)
#endif
#define READ_IMU read_imu

/* gyroscope at rest (noise only, whatever the range); magnetometer at 8192 / (r + 1) counts per gauss */
static int32_t read_imu(void *user, uint64_t now_us, uint8_t gyro_range, uint8_t mag_range, bool want_mag,
                        capsheet_imu_reading_t *out)
{
    static const int16_t field_mgauss[3] = {200, 0, -400};
    unsigned i;
    (void)user;
    (void)now_us;
    (void)gyro_range;
    for (i = 0; i < 3u; i++) {
        out->gyro[i] = noise();
        if (want_mag) {
            out->mag[i] = (int16_t)((int32_t)field_mgauss[i] * 8192 / 1000 / (int32_t)(mag_range + 1u) + noise());
        }
    }
    out->latch_us = clock_us();  /* the read's instant: time_us = this - the SYNC's end */
    return 0;
}
#endif

/* `data` is the chip's TX buffer, reused by the next send: uart_write returns once every byte
 * is in the UART, so nothing needs copying (a DMA HAL would copy, see README.md). */
static int32_t send_bytes(void *user, const uint8_t *data, size_t len)
{
    (void)user;
    uart_write(data, len);
    return 0;
}

static uint64_t read_uid(void *user)
{
    (void)user;
    return CAPSHEET_QEMU_UID;
}

/* "Non-volatile" calibration: RAM that survives a protocol RESET (not a power cycle). */
static capsheet_cal_t nv_cal[3];
static uint8_t nv_valid[3];

static int32_t cal_load(void *user, uint8_t axis, capsheet_cal_t *cal)
{
    (void)user;
    if (axis > 2u || !nv_valid[axis]) {
        return -1;
    }
    *cal = nv_cal[axis];
    return 0;
}

static int32_t cal_store(void *user, uint8_t axis, const capsheet_cal_t *cal)
{
    (void)user;
    if (axis > 2u) {
        return -1;
    }
    nv_cal[axis] = *cal;
    nv_valid[axis] = 1u;
    return 0;
}

/* The gyro/mag calibration elements (§17), the same way (a chip would keep them in flash). */
static uint32_t nv_imu[CAPSHEET_IMU_CAL_COUNT];
static uint8_t nv_imu_valid[CAPSHEET_IMU_CAL_COUNT];

static int32_t cal_imu_load(void *user, uint8_t element, uint32_t *bits)
{
    (void)user;
    if (element >= CAPSHEET_IMU_CAL_COUNT || !nv_imu_valid[element]) {
        return -1;
    }
    *bits = nv_imu[element];
    return 0;
}

static int32_t cal_imu_store(void *user, uint8_t element, uint32_t bits)
{
    (void)user;
    if (element >= CAPSHEET_IMU_CAL_COUNT) {
        return -1;
    }
    nv_imu[element] = bits;
    nv_imu_valid[element] = 1u;
    return 0;
}

static const capsheet_hal_t hal = {0, read_axes, send_bytes, 0, read_uid, cal_load, cal_store, READ_IMU,
                                   cal_imu_load, cal_imu_store};
static const capsheet_chip_config_t config = {CAPSHEET_TRANSPORT_SERIAL, false,
                                              CAPSHEET_CAP_CAL_STORAGE | CAPSHEET_CAP_MULTI_RANGE | SENSOR_CAPS};
static capsheet_chip_t chip;
static uint8_t rx_buf[CAPSHEET_RX_BUFFER_SIZE];

/* The chip's calls return the frames sent, or CAPSHEET_ERR_HAL when a send failed. This port's
 * send_bytes cannot fail, so a failure is only counted (readable in a debugger); a port whose
 * HAL can fail would retry or reset here. */
static volatile uint32_t hal_errors;

static void check(int32_t rc)
{
    if (rc < 0) {
        hal_errors++;
    }
}

int main(void)
{
    uint8_t buf[32];
    clock_init();
    uart_init();
    if (capsheet_chip_init(&chip, &config, &hal, rx_buf, sizeof rx_buf) != 0) {
        for (;;) {
        }
    }
#ifdef CAPSHEET_QEMU_MUTANT
    chip.mutant = CAPSHEET_QEMU_MUTANT;  /* a broken build: the rule capsheet_fw.h names */
#endif
    check(capsheet_chip_power_on(&chip, clock_us()));
    for (;;) {
        const size_t n = uart_read(buf, sizeof buf);
        const uint64_t now = clock_us();
        if (n > 0u) {
            check(capsheet_chip_rx_bytes(&chip, buf, n, now));
        }
        check(capsheet_chip_poll(&chip, now));
        if (n == 0u) {
            __asm volatile("wfi"); /* woken by the UART RX interrupt or the 1 kHz SysTick */
        }
    }
}

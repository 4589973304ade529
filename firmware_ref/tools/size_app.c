/*
 * size_app.c — the smallest application around the protocol core, for `make size`: one chip with
 * its RX buffer of CAPSHEET_RX_BUFFER_SIZE bytes (a build-time option), stub HAL callbacks, and a
 * main loop calling every entry point. Linked with --gc-sections, so the image holds exactly what
 * a chip uses (the SNAPSHOT encoder and the decoders a chip never calls drop out).
 * -DSIZE_CAN: a CAN chip; -DSIZE_IMU=1 / 2: a 6-axis / 9-axis chip (capability GYRO (+ MAG) and
 * SAMPLE_TIME, a stub read_imu); -DCAPSHEET_IMU=0: the accelerometer-only build.
 */
#include "capsheet_fw.h"

static int32_t read_axes(void *user, uint64_t now_us, int16_t xyz[3], uint8_t *status)
{
    (void)user;
    xyz[0] = (int16_t)(now_us & 0x7FFu);
    xyz[1] = 0;
    xyz[2] = 1024;
    *status = 0;
    return 0;
}

#ifdef SIZE_IMU
static int32_t read_imu(void *user, uint64_t now_us, uint8_t gyro_range, uint8_t mag_range, bool want_mag,
                        capsheet_imu_reading_t *out)
{
    (void)user;
    out->gyro[0] = (int16_t)(now_us & 0x7FFu);
    out->gyro[2] = (int16_t)(gyro_range * 100);
    if (want_mag) {
        out->mag[0] = (int16_t)(8192 >> mag_range);
    }
    out->latch_us = now_us;
    return 0;
}
#define READ_IMU read_imu
#if SIZE_IMU == 2
#define IMU_CAPS (CAPSHEET_CAP_GYRO | CAPSHEET_CAP_MAG | CAPSHEET_CAP_SAMPLE_TIME)
#else
#define IMU_CAPS (CAPSHEET_CAP_GYRO | CAPSHEET_CAP_SAMPLE_TIME)
#endif
#else
#define READ_IMU 0
#define IMU_CAPS 0
#endif

static volatile uint8_t sink;

static int32_t send_bytes(void *user, const uint8_t *data, size_t len)
{
    (void)user;
    sink = data[len - 1u];
    return 0;
}

static int32_t send_can(void *user, uint32_t id, const uint8_t *data, uint8_t len, bool is_fd)
{
    (void)user;
    (void)is_fd;
    sink = (uint8_t)(id ^ (len ? data[0] : 0u));
    return 0;
}

static uint64_t read_uid(void *user)
{
    (void)user;
    return 0x0123456789ABCDEFull;
}

static const capsheet_hal_t hal = {0, read_axes, send_bytes, send_can, read_uid, 0, 0, READ_IMU, 0, 0};
/* every call's result is kept (CAPSHEET_WARN_UNUSED: a result may not be dropped; a real chip
 * would act on a negative one) */
static volatile int32_t last_rc;
static capsheet_chip_t chip;
static uint8_t rx_buf[CAPSHEET_RX_BUFFER_SIZE];

extern volatile uint8_t rx_byte;
extern volatile uint64_t clock_us;
volatile uint8_t rx_byte;
volatile uint64_t clock_us;

void app_main(void);
void app_main(void)
{
    static const capsheet_chip_config_t cfg = {
#ifdef SIZE_CAN
        CAPSHEET_TRANSPORT_CAN,
#else
        CAPSHEET_TRANSPORT_SERIAL,
#endif
        false, IMU_CAPS};
    last_rc = capsheet_chip_init(&chip, &cfg, &hal, rx_buf, sizeof rx_buf);
    last_rc = capsheet_chip_power_on(&chip, clock_us);
    for (;;) {
        const uint8_t b = rx_byte;
#ifdef SIZE_CAN
        last_rc = capsheet_chip_rx_can(&chip, clock_us & 0x1FFFFFFFu, true, false, &b, 1, clock_us);
#else
        last_rc = capsheet_chip_rx_bytes(&chip, &b, 1, clock_us);
#endif
        last_rc = capsheet_chip_poll(&chip, clock_us);
    }
}

/*
 * main.c — the reference firmware (firmware_ref/src, unmodified) on a NUCLEO-G0B1RE: one link's chip,
 * reading its ICM-42688-P (and MMC5983MA) through the drivers (firmware_ref/drivers/) over SPI1,
 * speaking the serial transport (USART2 or USART1) or CAN (FDCAN1), keeping its calibration in flash.
 *
 * Build options (firmware_ref/Makefile `board`):
 *   BOARD_TRANSPORT_CAN 0 serial (default), 1 CAN
 *   BOARD_UART          2 the ST-LINK virtual COM port (default), 1 USART1 on the RS-485 bus
 *   BOARD_BAUD          serial baud rate, default 3000000 (capsheet host's default; up to 8000000)
 *   BOARD_CAN_FD        0 classic CAN at 1 Mbit/s (default), 1 also FD frames, data phase at
 *                       BOARD_CAN_FD_DATA_BPS (default 8000000; 4000000, 2000000)
 *   BOARD_HSE_HZ        0 HSI16 (default; fine for a UART), or the external clock a CAN chip needs:
 *                       a crystal (BOARD_HSE_BYPASS=0) or a clock signal on OSC_IN (BOARD_HSE_BYPASS=1,
 *                       such as the ST-LINK's 8 MHz MCO where the board routes it)
 *   BOARD_SENSORS       0 accelerometer chip, 1 6-axis (default: the ICM-42688-P's gyroscope too),
 *                       2 9-axis (and the MMC5983MA magnetometer on chip select 1)
 *
 * The HAL (capsheet_hal_t): read_axes / read_imu are the link glue's (link_sensors.h), fed with the
 * INT1 data-ready instants TIM2 captured; cal_load / cal_store / cal_imu_load / cal_imu_store are the
 * flash record log (calstore.h) on bank 2's last two pages; read_uid folds the part's 96-bit unique
 * id into 64 bits; send_bytes / send_can are the port's UART / FDCAN.
 *
 * A calibration store is quick (one double word) except when the log's page is full: the copy to
 * the other page erases it first (22 ms typical, 40 ms max: flash.c), and the main loop waits. The
 * receive rings keep filling meanwhile (1 KiB of UART, 16 CAN frames); the host writes calibration
 * while the sheet is idle (capsheet calibrate --write-chips), when little else is on the bus.
 */
#include "board.h"
#include "calstore.h"
#include "capsheet_bus.h"
#include "capsheet_fw.h"
#include "link_sensors.h"

#ifndef BOARD_BAUD
#define BOARD_BAUD 3000000u
#endif
#ifndef BOARD_SENSORS
#define BOARD_SENSORS 1
#endif

#if BOARD_SENSORS == 2
#include "mmc5983ma.h"
#define SENSOR_CAPS (CAPSHEET_CAP_GYRO | CAPSHEET_CAP_MAG | CAPSHEET_CAP_SAMPLE_TIME)
#define READ_IMU read_imu
#elif BOARD_SENSORS == 1
#define SENSOR_CAPS (CAPSHEET_CAP_GYRO | CAPSHEET_CAP_SAMPLE_TIME)
#define READ_IMU read_imu
#elif BOARD_SENSORS == 0
#define SENSOR_CAPS 0u
#define READ_IMU 0
#else
#error "BOARD_SENSORS: 0 (accelerometer), 1 (6-axis) or 2 (9-axis)"
#endif

static capsheet_chip_t chip;
static capsheet_link_sensors_t sensors;
static calstore_t cal;
#if BOARD_SENSORS == 2
/* MMC5983MA bandwidth code 1: a 4 ms measurement (the driver's mmc5983ma.h), so one finishes between
 * two SYNCs up to ~200 Hz */
#define MAG_BW 1u
static mmc5983ma_t mag;
static capsheet_mag_driver_t mag_driver;
#define MAG_DRIVER (&mag_driver)
#else
#define MAG_DRIVER NULL
#endif

/* ---- the sensor bus: SPI1 (capsheet_bus.h) ----------------------------------------------------- */

static int32_t bus_spi(void *user, uint8_t cs, const uint8_t *tx, uint8_t *rx, size_t len)
{
    (void)user;
    return spi_transfer(cs, tx, rx, len);
}

/* no delay_us: the drivers never block, they answer when to call again */
static const capsheet_bus_t bus = {NULL, bus_spi, NULL, NULL};

/* INT1 edges TIM2 captured, handed to the glue: the conversion's instant, on the chip's time base */
static uint32_t drdy_missed;

static void feed_data_ready(void)
{
    uint64_t edge;
    if (clock_capture(&edge, &drdy_missed)) {
        capsheet_link_data_ready(&sensors, edge);
    }
}

static int32_t read_axes(void *user, uint64_t now_us, int16_t xyz[3], uint8_t *status)
{
    (void)user;
    feed_data_ready(); /* an edge since the main loop last looked belongs to the conversion read now */
    return capsheet_link_read_axes(&sensors, now_us, xyz, status);
}

#if BOARD_SENSORS >= 1
static int32_t read_imu(void *user, uint64_t now_us, uint8_t gyro_range, uint8_t mag_range, bool want_mag,
                        capsheet_imu_reading_t *out)
{
    (void)user;
    return capsheet_link_read_imu(&sensors, now_us, gyro_range, mag_range, want_mag, out);
}
#endif

/* ---- calibration in flash (calstore.h over flash.c) ------------------------------------------- */

static int32_t page_erase(void *ctx, uint8_t page)
{
    (void)ctx;
    return flash_erase_page(page == 0u ? CAL_PAGE0_PNB : CAL_PAGE1_PNB);
}

static int32_t page_program(void *ctx, uint8_t page, uint32_t offset, uint32_t lo, uint32_t hi)
{
    (void)ctx;
    return flash_program_dword(CAL_PAGE0_ADDR + (uint32_t)page * FLASH_PAGE_SIZE + offset, lo, hi);
}

static const calstore_flash_t cal_flash = {
    NULL,
    {(const uint8_t *)(uintptr_t)CAL_PAGE0_ADDR, (const uint8_t *)(uintptr_t)(CAL_PAGE0_ADDR + FLASH_PAGE_SIZE)},
    FLASH_PAGE_SIZE,
    page_erase,
    page_program,
};

static int32_t cal_load(void *user, uint8_t axis, capsheet_cal_t *c)
{
    (void)user;
    return calstore_cal_load(&cal, axis, c);
}

static int32_t cal_store(void *user, uint8_t axis, const capsheet_cal_t *c)
{
    (void)user;
    return calstore_cal_store(&cal, axis, c);
}

static int32_t cal_imu_load(void *user, uint8_t element, uint32_t *bits)
{
    (void)user;
    return calstore_imu_load(&cal, element, bits);
}

static int32_t cal_imu_store(void *user, uint8_t element, uint32_t bits)
{
    (void)user;
    return calstore_imu_store(&cal, element, bits);
}

/* ---- identity and transport ------------------------------------------------------------------- */

/* The 96-bit unique id (RM0444 "Unique device ID register (96 bits)": word 0 the die's X/Y position
 * on the wafer, word 1 the wafer number and the lot number's first bytes, word 2 the rest of the lot
 * number) folded into the protocol's 64 bits: the position kept whole, the lot and wafer XOR-ed. */
static uint64_t read_uid(void *user)
{
    const uint32_t w0 = REG32(UID_BASE);
    const uint32_t w1 = REG32(UID_BASE + 4u);
    const uint32_t w2 = REG32(UID_BASE + 8u);
    (void)user;
    return ((uint64_t)(w1 ^ w2) << 32) | w0;
}

#if BOARD_TRANSPORT_CAN
static int32_t send_can(void *user, uint32_t id, const uint8_t *data, uint8_t len, bool is_fd)
{
    (void)user;
    return can_write(id, data, len, is_fd);
}
#define SEND_BYTES 0
#define SEND_CAN send_can
#define TRANSPORT CAPSHEET_TRANSPORT_CAN
#define RX_PENDING can_pending
#else
/* `data` is the chip's TX buffer, reused by the next send: uart_write returns once every byte is on
 * the wire, so nothing needs copying (a DMA HAL would copy, see firmware_ref/README.md). */
static int32_t send_bytes(void *user, const uint8_t *data, size_t len)
{
    (void)user;
    uart_write(data, len);
    return 0;
}
#define SEND_BYTES send_bytes
#define SEND_CAN 0
#define TRANSPORT CAPSHEET_TRANSPORT_SERIAL
#define RX_PENDING uart_pending
#endif

static const capsheet_hal_t hal = {NULL,     read_axes,     SEND_BYTES, SEND_CAN,    read_uid,
                                   cal_load, cal_store,     READ_IMU,   cal_imu_load, cal_imu_store};
static const capsheet_chip_config_t config = {
    TRANSPORT, BOARD_CAN_FD != 0, CAPSHEET_CAP_CAL_STORAGE | CAPSHEET_CAP_MULTI_RANGE | SENSOR_CAPS};

#if !BOARD_TRANSPORT_CAN
static uint8_t rx_buf[CAPSHEET_RX_BUFFER_SIZE];
#endif

/* Failures the main loop cannot hand to anyone: counted, readable with a debugger. A send that failed
 * (CAN: no acknowledgement within 1 ms) is a frame the host misses and counts as such. */
static volatile uint32_t hal_errors;
static volatile int32_t sensor_error;
static volatile bool clock_external_failed; /* BOARD_HSE_HZ set, yet no external clock: running on HSI16 */

static void check(int32_t rc)
{
    if (rc < 0) {
        hal_errors++;
    }
}

static void halt(void)
{
    for (;;) {
    }
}

int main(void)
{
    uint64_t sensors_at = 0u;
    clock_external_failed = !clock_init();
    spi_init();
    calstore_init(&cal, &cal_flash);
#if BOARD_TRANSPORT_CAN
    can_init();
    if (capsheet_chip_init(&chip, &config, &hal, NULL, 0u) != 0) {
        halt();
    }
#else
    uart_init(BOARD_BAUD);
    if (capsheet_chip_init(&chip, &config, &hal, rx_buf, sizeof rx_buf) != 0) {
        halt();
    }
#endif
#if BOARD_SENSORS == 2
    if (mmc5983ma_init(&mag, &bus, SPI_CS_MAG, MAG_BW) != 0) {
        halt();
    }
    mmc5983ma_mag_driver(&mag, &mag_driver);
#endif
    if (capsheet_link_sensors_init(&sensors, &bus, SPI_CS_IMU, MAG_DRIVER, &chip, true) != 0) {
        halt();
    }
    check(capsheet_chip_power_on(&chip, clock_us()));
    for (;;) {
        uint64_t now = clock_us();
        bool busy = false;
        feed_data_ready();
        if (sensor_error == 0 && now >= sensors_at) {
            const int32_t rc = capsheet_link_sensors_poll(&sensors, now);
            if (rc < 0) {
                sensor_error = rc; /* the glue reports INVALID from now on; the chip says FAULT at once */
                capsheet_chip_sensor_fault(&chip);
            } else {
                sensors_at = now + (rc > 0 ? (uint64_t)rc : 1000u);
            }
        }
#if BOARD_TRANSPORT_CAN
        {
            can_frame_t f;
            while (can_read(&f)) {
                check(capsheet_chip_rx_can(&chip, f.id, f.is_extended, f.is_fd, f.data, f.len, now));
                busy = true;
            }
        }
#else
        {
            uint8_t buf[64];
            const size_t n = uart_read(buf, sizeof buf);
            if (n > 0u) {
                check(capsheet_chip_rx_bytes(&chip, buf, n, now));
                busy = true;
            }
        }
#endif
        now = clock_us();
        check(capsheet_chip_poll(&chip, now));
        if (!busy && now + 1000u < sensors_at) {
            /* Sleep until an interrupt: the UART / FDCAN reception or the 1 kHz SysTick. Interrupts are
             * masked around the check, so a frame that arrived after the ring was read is not left
             * waiting for the next tick: WFI wakes on a pending interrupt even while masked, and it
             * runs at cpsie (Armv6-M ARM, "Wait For Interrupt"). */
            __asm volatile("cpsid i" ::: "memory");
            if (!RX_PENDING()) {
                __asm volatile("wfi");
            }
            __asm volatile("cpsie i" ::: "memory");
        }
    }
}

/*
 * icm42688p_reg.h — TDK InvenSense ICM-42688-P registers and bits, named as the datasheet prints them.
 *
 * Source: datasheet DS-000347 (rev. 1.7): §13 register map (user banks 0..4), §14 bank 0 register
 * descriptions (one subsection per register, by the name given here), §15 bank 1, §16 bank 2; the SPI interface in §9 (read bit, auto-increment); the
 * figures of §3.1 Table 1 (gyroscope) and §3.2 Table 2 (accelerometer). Datasheets are not reachable
 * from this project's build machines: every fact below was cross-checked against public drivers
 * written from the datasheet (Zephyr's drivers/sensor/tdk/icm42688 and its emulator, TDK's own
 * Ixm42xxx driver). Facts only; no code was taken from them.
 *
 * Registers are 8-bit addresses within the bank REG_BANK_SEL selects (REG_BANK_SEL itself is at 0x76
 * in every bank). Multi-byte data registers are big-endian (INTF_CONFIG0 SENSOR_DATA_ENDIAN = 1, the
 * reset value).
 */
#ifndef ICM42688P_REG_H
#define ICM42688P_REG_H

/* §9 (SPI): the first byte of a transaction is the address, bit 7 set for a read; the address then
 * auto-increments for every further byte of the same chip-select assertion. */
#define ICM42688P_SPI_READ 0x80u

/* ---- user bank 0 (§13.1 map, §14 descriptions) ---------------------------------------------- */
#define ICM42688P_DEVICE_CONFIG 0x11u      /* §14, reset 0x00 */
#define   ICM42688P_SOFT_RESET_CONFIG 0x01u    /* bit 0: 1 = software reset; wait 1 ms before any access */
#define ICM42688P_DRIVE_CONFIG 0x13u       /* §14, reset 0x05 */
#define ICM42688P_INT_CONFIG 0x14u         /* §14, reset 0x00 */
#define ICM42688P_FIFO_CONFIG 0x16u        /* §14, reset 0x00 */
#define ICM42688P_TEMP_DATA1 0x1Du         /* §14, upper byte of the temperature */
#define ICM42688P_TEMP_DATA0 0x1Eu         /* §14 */
#define ICM42688P_ACCEL_DATA_X1 0x1Fu      /* §14 .. §14: ACCEL_DATA_X1 .. ACCEL_DATA_Z0 (0x24) */
#define ICM42688P_ACCEL_DATA_Z0 0x24u
#define ICM42688P_GYRO_DATA_X1 0x25u       /* §14 .. §14: GYRO_DATA_X1 .. GYRO_DATA_Z0 (0x2A) */
#define ICM42688P_GYRO_DATA_Z0 0x2Au
#define ICM42688P_TMST_FSYNCH 0x2Bu        /* §14 */
#define ICM42688P_TMST_FSYNCL 0x2Cu        /* §14 */
#define ICM42688P_INT_STATUS 0x2Du         /* §14, reset 0x10; bits clear when read (INT_CONFIG0 default) */
#define   ICM42688P_AGC_RDY_INT 0x01u
#define   ICM42688P_FIFO_FULL_INT 0x02u
#define   ICM42688P_FIFO_THS_INT 0x04u
#define   ICM42688P_DATA_RDY_INT 0x08u         /* a new sample is in the data registers */
#define   ICM42688P_RESET_DONE_INT 0x10u       /* set after a reset (power-on or soft) completes */
#define   ICM42688P_PLL_RDY_INT 0x20u
#define   ICM42688P_UI_FSYNC_INT 0x40u
#define ICM42688P_FIFO_COUNTH 0x2Eu        /* §14 */
#define ICM42688P_FIFO_COUNTL 0x2Fu        /* §14 */
#define ICM42688P_FIFO_DATA 0x30u          /* §14 */
#define ICM42688P_INT_STATUS2 0x37u        /* §14 */
#define ICM42688P_INT_STATUS3 0x38u        /* §14 */
#define ICM42688P_SIGNAL_PATH_RESET 0x4Bu  /* §14, reset 0x00 */
#define   ICM42688P_TMST_STROBE 0x04u
#define   ICM42688P_FIFO_FLUSH 0x02u
#define ICM42688P_INTF_CONFIG0 0x4Cu       /* §14, reset 0x30 */
#define   ICM42688P_SENSOR_DATA_ENDIAN 0x10u   /* 1 (reset): big-endian data registers */
#define   ICM42688P_FIFO_COUNT_ENDIAN 0x20u
#define ICM42688P_INTF_CONFIG1 0x4Du       /* §14, reset 0x91 */
#define ICM42688P_PWR_MGMT0 0x4Eu          /* §14, reset 0x00: both sensors off */
#define   ICM42688P_TEMP_DIS 0x20u             /* bit 5: 1 = temperature sensor off */
#define   ICM42688P_IDLE 0x10u                 /* bit 4: RC oscillator kept on with the sensors off */
#define   ICM42688P_GYRO_MODE_SHIFT 2u         /* bits 3:2: 0 off, 1 standby, 3 low noise */
#define   ICM42688P_ACCEL_MODE_SHIFT 0u        /* bits 1:0: 0 off, 1 off, 2 low power, 3 low noise */
#define   ICM42688P_MODE_MASK 0x03u
#define   ICM42688P_MODE_OFF 0x00u
#define   ICM42688P_GYRO_MODE_STANDBY 0x01u
#define   ICM42688P_ACCEL_MODE_LP 0x02u
#define   ICM42688P_MODE_LN 0x03u
#define ICM42688P_GYRO_CONFIG0 0x4Fu       /* §14, reset 0x06 (±2000 °/s, 1 kHz) */
#define ICM42688P_ACCEL_CONFIG0 0x50u      /* §14, reset 0x06 (±16 g, 1 kHz) */
#define   ICM42688P_FS_SEL_SHIFT 5u            /* bits 7:5 GYRO_FS_SEL / ACCEL_FS_SEL */
#define   ICM42688P_FS_SEL_MASK 0xE0u
#define   ICM42688P_ODR_MASK 0x0Fu             /* bits 3:0 GYRO_ODR / ACCEL_ODR */
#define ICM42688P_GYRO_CONFIG1 0x51u       /* §14, reset 0x16 */
#define ICM42688P_GYRO_ACCEL_CONFIG0 0x52u /* §14, reset 0x11: ACCEL_UI_FILT_BW 7:4, GYRO_UI_FILT_BW 3:0 */
#define ICM42688P_ACCEL_CONFIG1 0x53u      /* §14, reset 0x0D */
#define ICM42688P_TMST_CONFIG 0x54u        /* §14, reset 0x23 */
#define ICM42688P_FIFO_CONFIG1 0x5Fu       /* §14, reset 0x00 */
#define ICM42688P_INT_CONFIG0 0x63u        /* §14, reset 0x00: DATA_RDY cleared on status read */
#define ICM42688P_INT_CONFIG1 0x64u        /* §14, reset 0x10 */
#define ICM42688P_INT_SOURCE0 0x65u        /* §14, reset 0x10 (RESET_DONE to INT1) */
#define   ICM42688P_UI_DRDY_INT1_EN 0x08u
#define ICM42688P_SELF_TEST_CONFIG 0x70u   /* §14, reset 0x00 */
#define   ICM42688P_EN_GX_ST 0x01u
#define   ICM42688P_EN_GY_ST 0x02u
#define   ICM42688P_EN_GZ_ST 0x04u
#define   ICM42688P_EN_AX_ST 0x08u
#define   ICM42688P_EN_AY_ST 0x10u
#define   ICM42688P_EN_AZ_ST 0x20u
#define   ICM42688P_ACCEL_ST_POWER 0x40u
#define ICM42688P_WHO_AM_I 0x75u           /* §14, reads 0x47 */
#define   ICM42688P_WHO_AM_I_VALUE 0x47u
#define ICM42688P_REG_BANK_SEL 0x76u       /* §14, reset 0x00; bits 2:0 the bank, in every bank */

/* ---- user bank 1 (§15) ---------------------------------------------------------------------- */
#define ICM42688P_XG_ST_DATA 0x5Fu         /* §15: factory gyroscope self-test codes X, Y (0x60), Z (0x61) */
#define ICM42688P_TMSTVAL0 0x62u           /* §15: the timestamp latched by TMST_STROBE, 20 bits (0x62..0x64) */

/* ---- user bank 2 (§16) ---------------------------------------------------------------------- */
#define ICM42688P_XA_ST_DATA 0x3Bu         /* §16: factory accelerometer self-test codes X, Y (0x3C), Z (0x3D) */

/* ---- codes ---------------------------------------------------------------------------------- */
/* GYRO_FS_SEL (§14): 0 ±2000, 1 ±1000, 2 ±500, 3 ±250, 4 ±125, 5 ±62.5, 6 ±31.25, 7 ±15.625 °/s;
 * sensitivity (§3.1 Table 1) 16.4, 32.8, 65.5, 131, 262, 524.3, 1048.6, 2097.2 LSB/(°/s) = 32768 / full scale. */
#define ICM42688P_GYRO_FS_2000 0u
#define ICM42688P_GYRO_FS_250 3u
#define ICM42688P_GYRO_FS_125 4u
/* ACCEL_FS_SEL (§14): 0 ±16 g, 1 ±8 g, 2 ±4 g, 3 ±2 g; sensitivity (§3.2 Table 2) 2048, 4096, 8192,
 * 16384 LSB/g. */
#define ICM42688P_ACCEL_FS_16G 0u
#define ICM42688P_ACCEL_FS_2G 3u
/* ODR (§14): 1 32 kHz, 2 16 kHz, 3 8 kHz, 4 4 kHz, 5 2 kHz, 6 1 kHz, 7 200 Hz, 8 100 Hz,
 * 9 50 Hz, 10 25 Hz, 11 12.5 Hz, 15 500 Hz (accelerometer also 12..14: 6.25, 3.125, 1.5625 Hz, LP). */
#define ICM42688P_ODR_1KHZ 6u
#define ICM42688P_ODR_200HZ 7u
#define ICM42688P_ODR_500HZ 15u

/* ---- timing (µs) ---------------------------------------------------------------------------- */
#define ICM42688P_SOFT_RESET_WAIT_US 1000u    /* §14: 1 ms after SOFT_RESET_CONFIG before any access */
#define ICM42688P_PWR_MODE_WAIT_US 200u       /* §14: no register write for 200 µs after turning a sensor on */
#define ICM42688P_GYRO_STARTUP_US 30000u      /* §3.1 Table 1: gyroscope start-up time, 30 ms (from off) */
#define ICM42688P_ACCEL_STARTUP_US 10000u     /* §3.2 Table 2: accelerometer start-up time, 10 ms (from off) */
/* Self-test (§3.1/§3.2 "self-test response" and TDK's procedure): full scale ±250 °/s and ±2 g at
 * 1 kHz; the response |on - off| over ST_OTP = 2620 / 2^(3 - FS_SEL) · 1.01^(code - 1) LSB must lie in
 * (0.5, 1.5); a factory code of 0 falls back to the absolute limits (gyroscope >= 60 °/s; accelerometer
 * 50..1200 mg). Settling: 60 ms (gyroscope), 25 ms (accelerometer) after turning on, 200 ms / 25 ms
 * after enabling the self-test. */
#define ICM42688P_ST_OTP_BASE 2620u
#define ICM42688P_ST_GYRO_SETTLE_US 60000u
#define ICM42688P_ST_ACCEL_SETTLE_US 25000u
#define ICM42688P_ST_GYRO_ON_SETTLE_US 200000u
#define ICM42688P_ST_ACCEL_ON_SETTLE_US 25000u

#endif /* ICM42688P_REG_H */

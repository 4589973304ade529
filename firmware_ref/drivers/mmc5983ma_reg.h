/*
 * mmc5983ma_reg.h — MEMSIC MMC5983MA 3-axis AMR magnetometer: registers and bits, named as the
 * datasheet prints them.
 *
 * Source: MEMSIC "MMC5983MA ±8 Gauss, High Performance 3-axis Magnetic Sensor", Rev A, formal release
 * 4/3/2019 (the datasheet has no document number; cited below as "DS Rev A" with its page and section).
 * Cross-checked against public drivers written from it (SparkFun's MMC5983MA Arduino library, Kris
 * Winer's MMC5983MA sketches): the same addresses, bits, product id and SPI read bit.
 */
#ifndef MMC5983MA_REG_H
#define MMC5983MA_REG_H

/* --- SPI command byte (DS Rev A p.5 "SPI Read and Write protocol", p.6 "SPI Read", p.7 "SPI Write") ---
 * The first byte clocked out, MSB first: bit 7 RW (1 read, 0 write), bit 6 don't care, bits 5..0 the
 * register address AD(5:0). Further bytes of one chip-select transaction read/write the following
 * registers (p.6/p.7 "Multiple byte read/write"; p.17 "the internal memory address pointer
 * automatically moves to the next byte"). The chip drives SDO from bit 8 on (p.5). Mode: SCK idles
 * high while CS is high (p.5), i.e. CPOL 1; data driven on the falling edge, captured on the rising
 * edge. SPI clock up to 10 MHz, tc(SCK) >= 100 ns (p.4 "SPI interface I/O characteristics"). */
#define MMC5983MA_SPI_READ 0x80u
#define MMC5983MA_SPI_ADDR_MASK 0x3Fu
#define MMC5983MA_SPI_MAX_HZ 10000000u

/* --- I2C (DS Rev A p.9 "Ordering guide": 7-bit address 0110000; p.17 "Data transfer") --- */
#define MMC5983MA_I2C_ADDR 0x30u

/* --- Register map (DS Rev A p.13 "Register map") --- */
#define MMC5983MA_XOUT0 0x00u        /* Xout[17:10], R */
#define MMC5983MA_XOUT1 0x01u        /* Xout[9:2], R */
#define MMC5983MA_YOUT0 0x02u        /* Yout[17:10], R */
#define MMC5983MA_YOUT1 0x03u        /* Yout[9:2], R */
#define MMC5983MA_ZOUT0 0x04u        /* Zout[17:10], R */
#define MMC5983MA_ZOUT1 0x05u        /* Zout[9:2], R */
#define MMC5983MA_XYZOUT2 0x06u      /* Xout[1:0] Yout[1:0] Zout[1:0] 0 0, R */
#define MMC5983MA_TOUT 0x07u         /* temperature, R */
#define MMC5983MA_STATUS 0x08u       /* device status, R/W (write 1 clears a done bit) */
#define MMC5983MA_INTERNAL_CONTROL_0 0x09u   /* W */
#define MMC5983MA_INTERNAL_CONTROL_1 0x0Au   /* W */
#define MMC5983MA_INTERNAL_CONTROL_2 0x0Bu   /* W */
#define MMC5983MA_INTERNAL_CONTROL_3 0x0Cu   /* W */
#define MMC5983MA_PRODUCT_ID_1 0x2Fu         /* R, reset value 0011 0000 (DS Rev A p.16 "Product ID1") */
#define MMC5983MA_PRODUCT_ID_1_VALUE 0x30u

/* XYZout2 (DS Rev A p.13): bits 7:6 Xout[1:0], 5:4 Yout[1:0], 3:2 Zout[1:0], 1:0 read 0 */
#define MMC5983MA_XYZOUT2_X_SHIFT 6u
#define MMC5983MA_XYZOUT2_Y_SHIFT 4u
#define MMC5983MA_XYZOUT2_Z_SHIFT 2u
#define MMC5983MA_XYZOUT2_ZERO_MASK 0x03u

/* Status 08H (DS Rev A p.14 "Status"): reset value 0; bits 7:5 and 3:2 reserved */
#define MMC5983MA_STATUS_MEAS_M_DONE 0x01u   /* a field measurement finished; write 1 to clear */
#define MMC5983MA_STATUS_MEAS_T_DONE 0x02u   /* a temperature measurement finished; write 1 to clear */
#define MMC5983MA_STATUS_OTP_READ_DONE 0x10u /* the chip read its memory (OTP) successfully */
#define MMC5983MA_STATUS_RESERVED_MASK 0xECu

/* Internal control 0, 09H (DS Rev A p.14-15 "Internal Control 0"): write only, reset value 0 */
#define MMC5983MA_CTRL0_TM_M 0x01u               /* take a field measurement; self-clears at its end */
#define MMC5983MA_CTRL0_TM_T 0x02u               /* take a temperature measurement; never with TM_M */
#define MMC5983MA_CTRL0_INT_MEAS_DONE_EN 0x04u   /* INT pin on measurement done */
#define MMC5983MA_CTRL0_SET 0x08u                /* SET current through the coil for 500 ns; self-clears */
#define MMC5983MA_CTRL0_RESET 0x10u              /* RESET current for 500 ns; self-clears */
#define MMC5983MA_CTRL0_AUTO_SR_EN 0x20u         /* automatic set/reset */
#define MMC5983MA_CTRL0_OTP_READ 0x40u           /* read the OTP again */

/* Internal control 1, 0AH (DS Rev A p.15 "Internal Control 1"): write only, reset value 0 */
/* BW1 BW0: 00 8 ms/100 Hz, 01 4 ms/200 Hz, 10 2 ms/400 Hz, 11 0.5 ms/800 Hz */
#define MMC5983MA_CTRL1_BW_MASK 0x03u
#define MMC5983MA_CTRL1_X_INHIBIT 0x04u
#define MMC5983MA_CTRL1_YZ_INHIBIT 0x18u         /* both bits: Y and Z off */
#define MMC5983MA_CTRL1_SW_RST 0x80u             /* reset like power-up, re-read the OTP; power-on time 10 ms */

/* Internal control 2, 0BH (DS Rev A p.15-16 "Internal Control 2"): write only, reset value 0 */
/* CM_Freq[2:0]: 000 off, 001 1 Hz, 010 10, 011 20, 100 50, 101 100, 110 200 (BW=01), 111 1000 Hz (BW=11) */
#define MMC5983MA_CTRL2_CM_FREQ_MASK 0x07u
#define MMC5983MA_CTRL2_CMM_EN 0x08u             /* continuous measurement mode (CM_Freq not 000) */
/* Prd_set[2:0]: a SET every 1, 25, 75, 100, 250, 500, 1000, 2000 measurements */
#define MMC5983MA_CTRL2_PRD_SET_SHIFT 4u
#define MMC5983MA_CTRL2_PRD_SET_MASK 0x70u
#define MMC5983MA_CTRL2_EN_PRD_SET 0x80u         /* periodic SET (needs Auto_SR_en and Cmm_en) */

/* Internal control 3, 0CH (DS Rev A p.16 "Internal Control 3"): write only, reset value 0 */
#define MMC5983MA_CTRL3_ST_ENP 0x02u             /* extra coil current, positive to negative end */
#define MMC5983MA_CTRL3_ST_ENM 0x04u             /* extra coil current, negative to positive end */
#define MMC5983MA_CTRL3_SPI_3W 0x40u             /* 3-wire SPI */

/* --- Timing and transfer function (DS Rev A) --- */
#define MMC5983MA_POWER_ON_US 10000u             /* p.15 SW_RST: "The power on time is 10mS" */
#define MMC5983MA_SET_RESET_NS 500u              /* p.15 Set / Reset: current flows for 500 ns */
/* p.15 Internal Control 1: measurement time per BW code, µs */
#define MMC5983MA_MEAS_US_BW0 8000u
#define MMC5983MA_MEAS_US_BW1 4000u
#define MMC5983MA_MEAS_US_BW2 2000u
#define MMC5983MA_MEAS_US_BW3 500u
/* p.2 Specifications: 18-bit output, 16384 counts/G; null field output 131072 counts (unsigned
 * format, p.13); field range ±8 G; null field output 0.5 G (the self-test's offset limit). */
#define MMC5983MA_COUNTS_PER_GAUSS 16384
#define MMC5983MA_NULL_FIELD 131072
#define MMC5983MA_RAW_MAX 262143
#define MMC5983MA_NULL_FIELD_LIMIT_COUNTS 8192   /* 0.5 G at 16384 counts/G */
/* p.14 Tout: unsigned, 00000000 is −75 °C, about 0.8 °C/LSB (p.2: 0.8 °C/count) */
#define MMC5983MA_TOUT_ZERO_DC (-750)            /* deci-°C at code 0 */
#define MMC5983MA_TOUT_DC_PER_LSB 8              /* deci-°C per code */

#endif /* MMC5983MA_REG_H */

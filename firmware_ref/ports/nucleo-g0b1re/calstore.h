/*
 * calstore.h — calibration in flash that survives power loss: a record log on two flash pages.
 * Portable C99 (no registers): the port gives it the pages (mapped for reading) and two operations,
 * erase a page and program one 64-bit double word; tests run it on the host over a simulated flash.
 *
 * Layout: every record is one double word (the unit a STM32G0 programs, with its ECC):
 *   byte 0      key: 0x00..0x02 accelerometer axis x/y/z (capsheet_cal_t), 0x10 + k the gyro/mag
 *               element k (0..32, docs/protocol.md §17.1), 0xA5 the page header; 0xFF: erased
 *   bytes 1..2  accelerometer offset_q4 (little-endian; 0 for the others)
 *   bytes 3..6  value: sensitivity or element as float32 bits; the header's generation (little-endian)
 *   byte 7      check: CRC-8 (poly 0x07, init 0) of bytes 0..6, 0x00 in place of 0xFF; it is in the
 *               word programmed second, so a record cut off after its first word (0xFF there) fails
 * A page is valid when its first double word is a header; the valid page with the highest generation
 * is the live one. A store appends one record; a key's last record with a good check is its value
 * (a record whose programming was cut off fails its check and is skipped). When the live page is
 * full, every current value is copied to the other page (erased first), the new header written LAST:
 * a power cut during the copy leaves the old page live. So a load after any power cut returns each
 * key's old or new value, never a mixture and never garbage.
 *
 * Not handled: a double word cut off mid-programming may also fail the flash's ECC, which on a
 * STM32G0 raises an NMI on read (RM0444 "Error code correction (ECC)"); the port's NMI handler then
 * stops, and a full chip erase recovers. No store happens unless the host asks for one.
 */
#ifndef CALSTORE_H
#define CALSTORE_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#include "capsheet_fw.h"

#define CALSTORE_KEY_ACCEL 0x00u
#define CALSTORE_KEY_IMU 0x10u
#define CALSTORE_KEY_HEADER 0xA5u
#define CALSTORE_KEY_ERASED 0xFFu
#define CALSTORE_KEYS (3u + CAPSHEET_IMU_CAL_COUNT)

#define CALSTORE_ERR_ARGUMENT (-1) /* an axis or element out of range, a NULL pointer */
#define CALSTORE_ERR_MISSING (-2)  /* never stored (the chip then uses the nominal value) */
#define CALSTORE_ERR_FLASH (-3)    /* erase or program failed */

typedef struct {
    void *ctx;
    const uint8_t *page[2];       /* the two pages, readable */
    uint32_t page_size;           /* bytes, a multiple of 8, at least 8 * (CALSTORE_KEYS + 2) */
    int32_t (*erase)(void *ctx, uint8_t page);                              /* 0 or negative */
    int32_t (*program)(void *ctx, uint8_t page, uint32_t offset, uint32_t lo, uint32_t hi); /* 0 or negative */
} calstore_flash_t;

typedef struct {
    const calstore_flash_t *flash;
    int8_t live;                  /* the live page, -1: none yet */
    uint32_t generation;          /* the live page's */
    uint32_t next;                /* offset of the first erased double word of the live page */
} calstore_t;

/* Find the live page and its end. Reads only: nothing is written until the first store. */
void calstore_init(calstore_t *cs, const calstore_flash_t *flash);

/* capsheet_hal_t callbacks (`user` is the calstore_t): one accelerometer axis, one gyro/mag element.
 * Loads: 0, CALSTORE_ERR_MISSING, CALSTORE_ERR_ARGUMENT. Stores: 0, CALSTORE_ERR_FLASH (the value
 * is not stored; the chip NACKs STORAGE_FAILED), CALSTORE_ERR_ARGUMENT. */
int32_t calstore_cal_load(void *user, uint8_t axis, capsheet_cal_t *cal);
int32_t calstore_cal_store(void *user, uint8_t axis, const capsheet_cal_t *cal);
int32_t calstore_imu_load(void *user, uint8_t element, uint32_t *bits);
int32_t calstore_imu_store(void *user, uint8_t element, uint32_t bits);

#endif

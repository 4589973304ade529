/*
 * chip_internal.h — what chip.c and chip_imu.c share. Not the firmware's interface (that is
 * include/capsheet_fw.h): a port or a host never calls these.
 */
#ifndef CAPSHEET_CHIP_INTERNAL_H
#define CAPSHEET_CHIP_INTERNAL_H

#include "capsheet_fw.h"

/* out of line: an IMU record's messages and its reading stay off the stack of a chip in format 0,
 * §17.3's int64 frame off the stack under capsheet_chip_send_msg */
#if defined(__GNUC__) || defined(__clang__)
#define NOINLINE __attribute__((noinline))
#else
#define NOINLINE
#endif

/* chip.c: one message sent on the chip's transport (1, one frame, or a negative error); a message
 * zeroed with its type and node; the capabilities ANNOUNCE_INFO states (§8.3) */
CAPSHEET_WARN_UNUSED int32_t capsheet_chip_send_msg(capsheet_chip_t *c, const capsheet_msg_t *m);
void capsheet_chip_msg_init(capsheet_msg_t *m, uint8_t type, uint16_t node);
uint16_t capsheet_chip_capabilities(const capsheet_chip_t *c);

#if CAPSHEET_IMU
/* The gyroscope's and magnetometer's calibration (§17.1): inline, as they were when one file held the
 * chip (out of line in both files they cost the chip image ~60 B of flash) */

/* element k of (block, index) */
static inline uint8_t capsheet_chip_cal_imu_slot(uint8_t block, uint8_t index)
{
    static const uint8_t first[5] = {0u, 9u, 12u, 21u, 30u};
    return (uint8_t)(first[block] + index);
}

/* the nominal value's bits: 1.0f on the two matrices' diagonals (elements 0, 4, 8 and 21, 25, 29),
 * +0 elsewhere */
static inline uint32_t capsheet_chip_cal_imu_nominal_bits(uint8_t k)
{
    if (k >= 21u) {
        k = (uint8_t)(k - 21u);
    }
    return (k < 9u && (k & 3u) == 0u) ? 0x3F800000u : 0u;
}

/* chip_imu.c: element k's stored flag (one bit per element: RAM 5 bytes, not 33); the 33 elements loaded
 * at boot (the stored ones, nominal values for the others); the SYNC's answer in format 1 or 2 around
 * the SAMPLE `s` */
void capsheet_chip_set_imu_stored(capsheet_chip_t *c, uint8_t k, bool stored);
void capsheet_chip_load_imu_calibration(capsheet_chip_t *c);
CAPSHEET_WARN_UNUSED int32_t capsheet_chip_send_record(capsheet_chip_t *c, const capsheet_msg_t *s, uint64_t now_us);
#endif

#endif

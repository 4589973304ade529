/*
 * codec_internal.h — what codec.c (CRC, COBS, serial and CAN frames, the stream decoder) and
 * payload.c (the types and their payloads) share. Not the firmware's interface (include/capsheet_fw.h).
 */
#ifndef CAPSHEET_CODEC_INTERNAL_H
#define CAPSHEET_CODEC_INTERNAL_H

#include "capsheet_fw.h"

#include <string.h>

/* ------------------------------------------------------------------------------------------ */
/* little-endian helpers (no unaligned access, no host-endianness assumption)                  */
/* ------------------------------------------------------------------------------------------ */

/* Portable promotion: a uint16_t operand is promoted to int (32-bit int) or unsigned int (16-bit int),
 * so the shift never overflows a signed int, whatever the target's int width. */
static inline uint16_t get_u16(const uint8_t *p) { return (uint16_t)((uint16_t)p[0] | ((uint16_t)p[1] << 8)); }

static inline uint32_t get_u32(const uint8_t *p)
{
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) | ((uint32_t)p[3] << 24);
}

static inline void put_u16(uint8_t *p, uint16_t v)
{
    p[0] = (uint8_t)(v & 0xFFu);
    p[1] = (uint8_t)(v >> 8);
}

static inline void put_u32(uint8_t *p, uint32_t v)
{
    p[0] = (uint8_t)(v & 0xFFu);
    p[1] = (uint8_t)((v >> 8) & 0xFFu);
    p[2] = (uint8_t)((v >> 16) & 0xFFu);
    p[3] = (uint8_t)(v >> 24);
}

static inline uint32_t float_bits(float f)
{
    uint32_t u;
    memcpy(&u, &f, sizeof u);
    return u;
}

static inline float bits_float(uint32_t u)
{
    float f;
    memcpy(&f, &u, sizeof f);
    return f;
}

typedef char capsheet_float_is_32_bits[(sizeof(float) == 4) ? 1 : -1];

#if !CAPSHEET_CHIP_ONLY  /* decoding node -> host payloads only */
/* sign-extend a 12-bit field */
static inline int16_t sext12(uint32_t v)
{
    v &= 0xFFFu;
    return (int16_t)((int32_t)v - (int32_t)((v & 0x800u) << 1));
}
#endif

/* a run of bytes: a frame is encoded from the spans of its parts without assembling it first */
typedef struct {
    const uint8_t *p;
    size_t n;
} span_t;

/* The fixed part of a payload: everything but SNAPSHOT's words and SNAPSHOT_IMU's records; at most
 * a 9-axis IMU_SAMPLE's 21 bytes. */
#define CAPSHEET_CODEC_FIXED_MAX 21u

/* payload.c: the payload of `m` as (fixed part in `tmp`, SNAPSHOT words / SNAPSHOT_IMU records)
 * spans, returning its length or a negative error */
CAPSHEET_WARN_UNUSED int32_t capsheet_codec_payload_spans(const capsheet_msg_t *m, uint8_t tmp[CAPSHEET_CODEC_FIXED_MAX],
                                                          span_t sp[2]);

/* one §16.1 record's bytes in `format` (0: none) */
static inline size_t capsheet_codec_imu_record_size(uint8_t format)
{
    return (format == CAPSHEET_IMU_FORMAT_6AXIS) ? CAPSHEET_IMU6_RECORD_SIZE
           : (format == CAPSHEET_IMU_FORMAT_9AXIS) ? CAPSHEET_IMU9_RECORD_SIZE : 0u;
}

#endif

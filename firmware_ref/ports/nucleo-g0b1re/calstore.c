/* calstore.c — calibration records in two flash pages. See calstore.h. */
#include <string.h>

#include "calstore.h"

/* CRC-8 (poly 0x07, init 0) of bytes 0..6, never 0xFF: a record whose second word never made it
 * reads 0xFF there, so it can never pass */
static uint8_t check_of(const uint8_t rec[8])
{
    uint8_t crc = 0u;
    unsigned i, b;
    for (i = 0; i < 7u; i++) {
        crc ^= rec[i];
        for (b = 0; b < 8u; b++) {
            crc = (uint8_t)((crc & 0x80u) != 0u ? (uint8_t)(crc << 1) ^ 0x07u : (uint8_t)(crc << 1));
        }
    }
    return crc == 0xFFu ? 0x00u : crc;
}

static bool erased(const uint8_t *rec)
{
    unsigned i;
    for (i = 0; i < 8u; i++) {
        if (rec[i] != 0xFFu) {
            return false;
        }
    }
    return true;
}

static bool valid(const uint8_t *rec)
{
    return rec[0] != CALSTORE_KEY_ERASED && check_of(rec) == rec[7];
}

static uint32_t get32(const uint8_t *p)
{
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) | ((uint32_t)p[3] << 24);
}

static void make(uint8_t rec[8], uint8_t key, uint16_t aux, uint32_t value)
{
    rec[0] = key;
    rec[1] = (uint8_t)(aux & 0xFFu);
    rec[2] = (uint8_t)(aux >> 8);
    rec[3] = (uint8_t)(value & 0xFFu);
    rec[4] = (uint8_t)((value >> 8) & 0xFFu);
    rec[5] = (uint8_t)((value >> 16) & 0xFFu);
    rec[6] = (uint8_t)(value >> 24);
    rec[7] = check_of(rec);
}

void calstore_init(calstore_t *cs, const calstore_flash_t *flash)
{
    uint8_t p;
    cs->flash = flash;
    cs->live = -1;
    cs->generation = 0u;
    cs->next = 0u;
    for (p = 0; p < 2u; p++) {
        const uint8_t *h = flash->page[p];
        if (valid(h) && h[0] == CALSTORE_KEY_HEADER && (cs->live < 0 || get32(h + 3) > cs->generation)) {
            cs->live = (int8_t)p;
            cs->generation = get32(h + 3);
        }
    }
    if (cs->live >= 0) {
        const uint8_t *page = flash->page[cs->live];
        uint32_t off = 8u;
        while (off < flash->page_size && !erased(page + off)) {
            off += 8u;
        }
        cs->next = off;
    }
}

/* The last good record of `key` in the live page, or NULL. */
static const uint8_t *find(const calstore_t *cs, uint8_t key)
{
    const uint8_t *found = NULL;
    const uint8_t *page;
    uint32_t off;
    if (cs->live < 0) {
        return NULL;
    }
    page = cs->flash->page[cs->live];
    for (off = 8u; off < cs->next; off += 8u) {
        if (page[off] == key && valid(page + off)) {
            found = page + off;
        }
    }
    return found;
}

static int32_t program(const calstore_t *cs, uint8_t page, uint32_t off, const uint8_t rec[8])
{
    return cs->flash->program(cs->flash->ctx, page, off, get32(rec), get32(rec + 4)) < 0 ? CALSTORE_ERR_FLASH : 0;
}

/* Copy every current value and `rec` to the other page; its header last. */
static int32_t compact(calstore_t *cs, const uint8_t rec[8])
{
    const uint8_t target = (uint8_t)(cs->live < 0 ? 0 : 1 - cs->live);
    uint8_t copy[CALSTORE_KEYS][8];
    uint8_t header[8];
    unsigned n = 0, k;
    uint32_t off = 8u;
    for (k = 0; k < CALSTORE_KEYS; k++) {
        const uint8_t key = (uint8_t)(k < 3u ? CALSTORE_KEY_ACCEL + k : CALSTORE_KEY_IMU + (k - 3u));
        const uint8_t *cur = find(cs, key);
        if (cur != NULL && key != rec[0]) {
            memcpy(copy[n++], cur, 8u);
        }
    }
    if (cs->flash->erase(cs->flash->ctx, target) < 0) {
        return CALSTORE_ERR_FLASH;
    }
    for (k = 0; k < n; k++, off += 8u) {
        if (program(cs, target, off, copy[k]) < 0) {
            return CALSTORE_ERR_FLASH;
        }
    }
    if (program(cs, target, off, rec) < 0) {
        return CALSTORE_ERR_FLASH;
    }
    off += 8u;
    make(header, CALSTORE_KEY_HEADER, 0u, cs->generation + 1u);
    if (program(cs, target, 0u, header) < 0) {
        return CALSTORE_ERR_FLASH;
    }
    cs->live = (int8_t)target;
    cs->generation += 1u;
    cs->next = off;
    return 0;
}

static int32_t store(calstore_t *cs, uint8_t key, uint16_t aux, uint32_t value)
{
    uint8_t rec[8];
    make(rec, key, aux, value);
    if (cs->live >= 0 && cs->next < cs->flash->page_size) {
        const uint32_t off = cs->next;
        cs->next += 8u; /* the slot is used even if programming fails: it is no longer erased */
        return program(cs, (uint8_t)cs->live, off, rec);
    }
    return compact(cs, rec);
}

int32_t calstore_cal_load(void *user, uint8_t axis, capsheet_cal_t *cal)
{
    const uint8_t *rec;
    uint32_t bits;
    if (user == NULL || cal == NULL || axis > 2u) {
        return CALSTORE_ERR_ARGUMENT;
    }
    rec = find((const calstore_t *)user, (uint8_t)(CALSTORE_KEY_ACCEL + axis));
    if (rec == NULL) {
        return CALSTORE_ERR_MISSING;
    }
    bits = get32(rec + 3);
    cal->axis = axis;
    cal->flags = 1u;
    cal->offset_q4 = (int16_t)(uint16_t)((uint16_t)rec[1] | (uint16_t)((uint16_t)rec[2] << 8));
    memcpy(&cal->sensitivity, &bits, sizeof bits);
    return 0;
}

int32_t calstore_cal_store(void *user, uint8_t axis, const capsheet_cal_t *cal)
{
    uint32_t bits;
    if (user == NULL || cal == NULL || axis > 2u) {
        return CALSTORE_ERR_ARGUMENT;
    }
    memcpy(&bits, &cal->sensitivity, sizeof bits);
    return store((calstore_t *)user, (uint8_t)(CALSTORE_KEY_ACCEL + axis), (uint16_t)cal->offset_q4, bits);
}

int32_t calstore_imu_load(void *user, uint8_t element, uint32_t *bits)
{
    const uint8_t *rec;
    if (user == NULL || bits == NULL || element >= CAPSHEET_IMU_CAL_COUNT) {
        return CALSTORE_ERR_ARGUMENT;
    }
    rec = find((const calstore_t *)user, (uint8_t)(CALSTORE_KEY_IMU + element));
    if (rec == NULL) {
        return CALSTORE_ERR_MISSING;
    }
    *bits = get32(rec + 3);
    return 0;
}

int32_t calstore_imu_store(void *user, uint8_t element, uint32_t bits)
{
    if (user == NULL || element >= CAPSHEET_IMU_CAL_COUNT) {
        return CALSTORE_ERR_ARGUMENT;
    }
    return store((calstore_t *)user, (uint8_t)(CALSTORE_KEY_IMU + element), 0u, bits);
}

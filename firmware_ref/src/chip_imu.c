/*
 * chip_imu.c — what a 6/9-axis chip adds to chip.c (docs/protocol.md §16, §17): the IMU record it
 * answers each SYNC with in format 1 or 2 (the accelerometer word as a SAMPLE's, the HAL's gyroscope
 * and magnetometer, time_us; one IMU_SAMPLE, or IMU_GYRO (+ IMU_MAG) + IMU_ACCEL on classic CAN), and
 * the gyroscope's and magnetometer's calibration: its 33 stored elements and §17.3's correction in
 * integer arithmetic. An accelerometer-only build (CAPSHEET_IMU 0) has neither sensor: it answers
 * every CAL_IMU_* with NACK 5 and keeps nothing, and this file compiles to nothing of its own.
 */
#include "capsheet_fw.h"
#include "chip_internal.h"

#include <string.h>

#if CAPSHEET_IMU

/* ------------------------------------------------------------------------------------------ */
/* The calibration (§17)                                                                       */
/* ------------------------------------------------------------------------------------------ */

void capsheet_chip_set_imu_stored(capsheet_chip_t *c, uint8_t k, bool stored)
{
    const uint8_t bit = (uint8_t)(1u << (k & 7u));
    c->imu_cal_stored[k >> 3] = (uint8_t)(stored ? (c->imu_cal_stored[k >> 3] | bit) : (c->imu_cal_stored[k >> 3] & ~bit));
}

/* At boot (power-on, RESET): the stored elements (the HAL's non-volatile memory), nominal values
 * for the others. */
void capsheet_chip_load_imu_calibration(capsheet_chip_t *c)
{
    uint8_t k;
    for (k = 0; k < CAPSHEET_IMU_CAL_COUNT; k++) {
        uint32_t bits = 0;
        const bool stored = c->hal->cal_imu_load != NULL && c->hal->cal_imu_load(c->hal->user, k, &bits) == 0;
        c->imu_cal[k] = stored ? bits : capsheet_chip_cal_imu_nominal_bits(k);
        capsheet_chip_set_imu_stored(c, k, stored);
    }
}

/* §17.3 in 32-bit integers (a Cortex-M0+ has no FPU; soft float cost ~4 KB of flash, int64 all
 * through ~1 KB): every float32 element is turned into a fixed-point int32 as it is used (`f32_q`;
 * the elements in RAM stay the float32 bits CAL_IMU_READ answers), the one product that needs 64
 * bits is `mulq`. Every intermediate is rounded to nearest (halves away from zero) at 2^-8 count
 * or finer and saturated at ±2^28 of its unit: the result is within a few hundredths of a count of
 * the exact one for elements within the ranges below, and bit-exact with the counts read when
 * every element is nominal (A = I is 2^24 in Q24 times u = c · 2^8: c · 2^8 exactly).
 * The gyroscope's counts per rad/s at range r, x 2^16, are K_GYRO / 2^r: K_GYRO = round(32768 /
 * 125 · 180/π · 65536); the magnetometer's counts per tesla at range r: round(32768 / (4 (r + 1)) · 10^4).
 * Units: A, S Q24 (|element| < 16), b Q22 rad/s (< 64), Γ Q30 rad/s per g (< 0.25), h Q36 T (< 39 gauss). */
#define K_GYRO 984333997
static const int32_t k_mag_cpt[4] = {81920000, 40960000, 27306667, 20480000};
#define Q_LIM (((int32_t)1) << 28)

/* round(|x| / 2^n) with the sign of x, halves away from zero, saturated at ±Q_LIM; n >= 1 */
static NOINLINE int32_t round_sat(bool neg, uint64_t x, uint8_t n)
{
    uint64_t r = ((x >> (n - 1u)) + 1u) >> 1;
    r = (r > (uint64_t)Q_LIM) ? (uint64_t)Q_LIM : r;
    return neg ? -(int32_t)r : (int32_t)r;
}

/* round(v · 2^q) of the float32 v with these bits, saturated at ±Q_LIM */
static int32_t f32_q(uint32_t bits, int32_t q)
{
    const int32_t e = (int32_t)((bits >> 23) & 0xFFu);
    const int32_t t = (e ? e : 1) - 150 + q + 1;  /* v · 2^(q+1) = m · 2^t (subnormal: e = 1) */
    const uint32_t m = (bits & 0x7FFFFFu) | (e ? 0x800000u : 0u);
    /* a normal m >= 2^23: from t = 7 on, m · 2^t > 2 Q_LIM (saturated); below, it fits 32 bits */
    return round_sat((bits >> 31) != 0u, (t > 6) ? (uint32_t)Q_LIM << 1 : ((t > 0) ? m << t : ((t < -30) ? 0u : m >> (-t))), 1u);
}

/* round(a · b / 2^n), saturated at ±Q_LIM; |a| <= 2^28, |b| < 2^30, n >= 1 */
static NOINLINE int32_t mulq(int32_t a, int32_t b, uint8_t n)
{
    const bool neg = (a < 0) != (b < 0);
    return round_sat(neg, (uint64_t)(uint32_t)(a < 0 ? -a : a) * (uint32_t)(b < 0 ? -b : b), n);
}

/* Σ_j round(round(M_j · 2^q) · v_j / 2^n): one row of a matrix times v */
static int32_t row3(const uint32_t *M, int32_t q, const int32_t v[3], uint8_t n)
{
    uint8_t j;
    int32_t acc = 0;
    for (j = 0; j < 3u; j++) {
        acc += mulq(f32_q(M[j], q), v[j], n);
    }
    return acc;
}

/* x' = M (x − o), the gyroscope's (M = A, o = s (b + Γ f)) and the magnetometer's (S, s_m h) alike:
 * o = (round(o_i · 2^q) + t_i) · k / 2^sh in Q8 counts, u in Q8 counts, M in Q24; clamped to 16 bits */
static void correct(const uint32_t *M, const uint32_t *o, int32_t q, const int32_t t[3], int32_t k, uint8_t sh,
                    int16_t x[3])
{
    uint8_t i;
    int32_t u[3];
    for (i = 0; i < 3u; i++) {
        u[i] = (int32_t)x[i] * 256 - mulq(f32_q(o[i], q) + t[i], k, sh);
    }
    for (i = 0; i < 3u; i++) {
        const int32_t acc = row3(&M[3u * i], 24, u, 24u);  /* Q8, |acc| < 3 · 2^28 */
        const int32_t r = round_sat(acc < 0, (uint32_t)(acc < 0 ? -acc : acc), 8u);
        x[i] = (int16_t)((r > 32767) ? 32767 : ((r < -32768) ? -32768 : r));
    }
}

/* §17.3, in counts: g' = A (g − s (b + Γ f)), f = a · 2^r_a / 1024; m' = S (m − s_m h). `s` the
 * SAMPLE: its accelerometer counts a as sent, at CONFIG's range. In place. b + Γ f in Q22 rad/s:
 * Γ (Q30) a over 2^(18 − r_a); h in Q36 T. */
static NOINLINE void apply_imu_calibration(const capsheet_chip_t *c, const capsheet_msg_t *s, int16_t g[3],
                                           int16_t m[3], bool nine)
{
    uint8_t i;
    int32_t t[3];
    const int32_t v[3] = {s->u.sample.x, s->u.sample.y, s->u.sample.z};
    for (i = 0; i < 3u; i++) {
        t[i] = row3(&c->imu_cal[12u + 3u * i], 30, v, (uint8_t)(18u - c->range_code));
    }
    correct(&c->imu_cal[0], &c->imu_cal[9], 22, t, K_GYRO, (uint8_t)(30u + c->gyro_range), g);
    if (nine) {
        t[0] = t[1] = t[2] = 0;
        correct(&c->imu_cal[21], &c->imu_cal[30], 36, t, k_mag_cpt[c->mag_range], 28u, m);
    }
}


/* ------------------------------------------------------------------------------------------ */
/* The record (§16.1) and how it is sent (§16.3, §16.4)                                         */
/* ------------------------------------------------------------------------------------------ */

static bool i16_rail(const int16_t *v, unsigned n)
{
    unsigned i;
    for (i = 0; i < n; i++) {
        if (v[i] == INT16_MIN || v[i] == INT16_MAX) {
            return true;
        }
    }
    return false;
}

/* §16.1 time_us: latch - now in µs, clamped to ±32767; −32768 (unknown) without SAMPLE_TIME */
static int16_t sample_time_us(const capsheet_chip_t *c, uint64_t latch_us, uint64_t now_us)
{
    uint64_t d;
    if (!(capsheet_chip_capabilities(c) & CAPSHEET_CAP_SAMPLE_TIME)) {
        return (int16_t)CAPSHEET_TIME_UNKNOWN;
    }
    if (latch_us >= now_us) {
        d = latch_us - now_us;
        return (int16_t)(d > 32767u ? 32767u : d);
    }
    d = now_us - latch_us;
    return (int16_t)-(int32_t)(d > 32767u ? 32767u : d);
}

/* Format 1 or 2 (§16): the IMU record `r` around the SAMPLE `s` the chip would send (its
 * accelerometer word, range, SATURATED and FAULT rules applied), with the HAL's gyroscope (and
 * magnetometer), §17.3's correction and time_us. Out of line: the reading is not on the stack
 * under send_msg. */
static NOINLINE void read_record(capsheet_chip_t *c, const capsheet_msg_t *s, capsheet_msg_t *r, uint64_t now_us)
{
    const bool nine = c->imu_format == CAPSHEET_IMU_FORMAT_9AXIS;
    uint8_t status = s->u.sample.status;
    capsheet_chip_msg_init(r, CAPSHEET_IMU_SAMPLE, c->node);
    r->u.imu_sample.format = c->imu_format;
    r->u.imu_sample.counter = s->u.sample.counter;
    r->u.imu_sample.time_us = (int16_t)CAPSHEET_TIME_UNKNOWN;
    if (!(status & CAPSHEET_SAMPLE_INVALID)) {
        capsheet_imu_reading_t rd;
        memset(&rd, 0, sizeof rd);
        if (c->hal->read_imu(c->hal->user, now_us, c->gyro_range, c->mag_range, nine, &rd) < 0
            || (rd.status & CAPSHEET_SAMPLE_INVALID)) {
            c->state = CAPSHEET_FAULT;  /* the gyroscope failed: an INVALID record, FAULT (§16.1, §8.6) */
            status = CAPSHEET_SAMPLE_INVALID;
        } else {
            apply_imu_calibration(c, s, rd.gyro, rd.mag, nine);  /* §17.3 (nominal: unchanged) */
            r->u.imu_sample.x = s->u.sample.x;
            r->u.imu_sample.y = s->u.sample.y;
            r->u.imu_sample.z = s->u.sample.z;
            r->u.imu_sample.gx = rd.gyro[0];
            r->u.imu_sample.gy = rd.gyro[1];
            r->u.imu_sample.gz = rd.gyro[2];
            if (nine) {
                r->u.imu_sample.mx = rd.mag[0];
                r->u.imu_sample.my = rd.mag[1];
                r->u.imu_sample.mz = rd.mag[2];
            }
            status = (uint8_t)(status | (rd.status & (CAPSHEET_SAMPLE_STALE | CAPSHEET_SAMPLE_SELF_TEST)));
            if (i16_rail(rd.gyro, 3u) || (nine && i16_rail(rd.mag, 3u))) {
                status = (uint8_t)(status | CAPSHEET_SAMPLE_SATURATED);  /* a count sent at its rail (§16.1) */
            }
            r->u.imu_sample.time_us = sample_time_us(c, rd.latch_us, now_us);
        }
    }
    r->u.imu_sample.status = status;
}

/* classic CAN (§16.4): the record `r` as IMU_GYRO, IMU_MAG (format 2), IMU_ACCEL, back to back.
 * Out of line: its two messages are not on a serial chip's stack. */
static NOINLINE CAPSHEET_WARN_UNUSED int32_t send_record_classic(capsheet_chip_t *c, const capsheet_msg_t *rp)
{
    const bool nine = rp->u.imu_sample.format == CAPSHEET_IMU_FORMAT_9AXIS;
    int32_t rc, sent;
    {   /* classic CAN (§16.4): IMU_GYRO, IMU_MAG (format 2), IMU_ACCEL, back to back */
        capsheet_msg_t f, a;
        const bool accel_first = CAPSHEET_MUTANT(c, CAPSHEET_MUT_IMU_ACCEL_FIRST);
        capsheet_chip_msg_init(&a, CAPSHEET_IMU_ACCEL, c->node);
        a.u.imu_accel.counter_lo = (uint8_t)(rp->u.imu_sample.counter & 0xFFu);
        a.u.imu_accel.x = rp->u.imu_sample.x;
        a.u.imu_accel.y = rp->u.imu_sample.y;
        a.u.imu_accel.z = rp->u.imu_sample.z;
        a.u.imu_accel.status = rp->u.imu_sample.status;
        a.u.imu_accel.time_us = rp->u.imu_sample.time_us;
        sent = 0;
        if (accel_first) {
            sent = capsheet_chip_send_msg(c, &a);
            if (sent < 0) {
                return sent;
            }
        }
        capsheet_chip_msg_init(&f, CAPSHEET_IMU_GYRO, c->node);
        f.u.imu_gyro.counter = rp->u.imu_sample.counter;
        f.u.imu_gyro.gx = rp->u.imu_sample.gx;
        f.u.imu_gyro.gy = rp->u.imu_sample.gy;
        f.u.imu_gyro.gz = rp->u.imu_sample.gz;
        rc = capsheet_chip_send_msg(c, &f);
        if (rc < 0) {
            return rc;
        }
        sent += rc;
        if (nine) {
            capsheet_chip_msg_init(&f, CAPSHEET_IMU_MAG, c->node);
            f.u.imu_mag.counter = rp->u.imu_sample.counter;
            f.u.imu_mag.mx = rp->u.imu_sample.mx;
            f.u.imu_mag.my = rp->u.imu_sample.my;
            f.u.imu_mag.mz = rp->u.imu_sample.mz;
            rc = capsheet_chip_send_msg(c, &f);
            if (rc < 0) {
                return rc;
            }
            sent += rc;
        }
        if (accel_first) {
            return sent;
        }
        rc = capsheet_chip_send_msg(c, &a);
        return (rc < 0) ? rc : sent + rc;
    }
}

NOINLINE CAPSHEET_WARN_UNUSED int32_t capsheet_chip_send_record(capsheet_chip_t *c, const capsheet_msg_t *s,
                                                         uint64_t now_us)
{
    capsheet_msg_t r;
    read_record(c, s, &r, now_us);
    if (c->config.transport == CAPSHEET_TRANSPORT_SERIAL || (c->imu_flags & CAPSHEET_IMU_FLAG_FD)) {
        return capsheet_chip_send_msg(c, &r);
    }
    return send_record_classic(c, &r);
}

#else
/* ISO C wants a declaration in every translation unit */
typedef int capsheet_chip_imu_absent_t;
#endif

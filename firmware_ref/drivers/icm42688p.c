/*
 * icm42688p.c — the ICM-42688-P driver (icm42688p.h). Register facts: icm42688p_reg.h (DS-000347).
 *
 * The bring-up is a sequence of phases, each a few register accesses and at most one wait, so that a
 * port without delay_us (a main loop, the SIL build) drives it with icm42688p_step and the time it is
 * told to wait:
 *
 *   POWER_UP     wait 1 ms (the part may have powered up with the MCU; its registers answer after it)
 *   PROBE        REG_BANK_SEL <- 0 (a part left in another bank by an MCU reset), WHO_AM_I == 0x47,
 *                DEVICE_CONFIG <- SOFT_RESET_CONFIG; wait 1 ms (§14)
 *   RESET_DONE   INT_STATUS has RESET_DONE_INT (cleared by this read), WHO_AM_I again
 *   ST_*         optional self-test, gyroscope then accelerometer (icm42688p_reg.h: TDK's procedure)
 *   CONFIG       full scales, ODRs, UI filter bandwidth, DATA_RDY to INT1, then PWR_MGMT0 (low noise);
 *                wait the start-up time (§3.1, §3.2: 30 ms gyroscope, 10 ms accelerometer)
 *   RUN          reads; a changed configuration is written here too
 */
#include "icm42688p.h"

#include <string.h>

#include "icm42688p_reg.h"

enum {
    PHASE_POWER_UP = 0,
    PHASE_PROBE,
    PHASE_RESET_DONE,
    PHASE_ST_START,
    PHASE_ST_OFF,
    PHASE_ST_ON,
    PHASE_CONFIG,
    PHASE_RUN,
    PHASE_FAILED
};

/* Samples averaged with the self-test off and on (TDK's procedure: 200 at 1 kHz). */
#ifndef ICM42688P_ST_SAMPLES
#define ICM42688P_ST_SAMPLES 200u
#endif
/* A running part whose DATA_RDY has not been seen for this long has stopped converting: a sensor
 * fault (docs/protocol.md §8.6: "a conversion that does not complete"), not a stream of STALE. */
#ifndef ICM42688P_DRDY_TIMEOUT_US
#define ICM42688P_DRDY_TIMEOUT_US 100000u
#endif

static int32_t fail(icm42688p_t *d, int32_t err)
{
    if (d->error == 0) {
        d->error = err;
    }
    d->phase = PHASE_FAILED;
    return d->error;
}

int32_t icm42688p_read_regs(icm42688p_t *d, uint8_t reg, uint8_t *buf, size_t len)
{
    uint8_t tx[24];
    uint8_t rx[24];
    if (d == NULL || buf == NULL || len == 0u || len + 1u > sizeof tx) {
        return ICM42688P_ERR_ARGUMENT;
    }
    memset(tx, 0, sizeof tx);
    tx[0] = (uint8_t)(reg | ICM42688P_SPI_READ);
    if (d->bus->spi_transfer(d->bus->user, d->cs, tx, rx, len + 1u) < 0) {
        return ICM42688P_ERR_BUS;
    }
    memcpy(buf, &rx[1], len);
    return 0;
}

int32_t icm42688p_write_reg(icm42688p_t *d, uint8_t reg, uint8_t value)
{
    uint8_t tx[2];
    uint8_t rx[2];
    if (d == NULL) {
        return ICM42688P_ERR_ARGUMENT;
    }
    tx[0] = (uint8_t)(reg & 0x7Fu);
    tx[1] = value;
    if (d->bus->spi_transfer(d->bus->user, d->cs, tx, rx, sizeof tx) < 0) {
        return ICM42688P_ERR_BUS;
    }
    return 0;
}

static int16_t be16(const uint8_t *p)
{
    const uint16_t u = (uint16_t)(((uint16_t)p[0] << 8) | p[1]);
    return (int16_t)(u >= 0x8000u ? (int32_t)u - 65536 : (int32_t)u);
}

void icm42688p_default_config(icm42688p_config_t *cfg)
{
    if (cfg == NULL) {
        return;
    }
    cfg->accel_fs_sel = ICM42688P_ACCEL_FS_2G;
    cfg->gyro_fs_sel = 1u;  /* ±1000 °/s: the protocol's default gyro_range 3 */
    cfg->odr = ICM42688P_ODR_1KHZ;
    cfg->ui_filt_bw = 1u;   /* ODR/4: GYRO_ACCEL_CONFIG0's reset value for both sensors */
    cfg->gyro_on = true;
}

static bool odr_valid(uint8_t odr)
{
    return (odr >= 1u && odr <= 11u) || odr == 15u;
}

int32_t icm42688p_init(icm42688p_t *d, const capsheet_bus_t *bus, uint8_t cs, bool self_test)
{
    if (d == NULL || bus == NULL || bus->spi_transfer == NULL) {
        return ICM42688P_ERR_ARGUMENT;
    }
    memset(d, 0, sizeof *d);
    d->bus = bus;
    d->cs = cs;
    d->want_self_test = self_test;
    icm42688p_default_config(&d->want);
    d->phase = PHASE_POWER_UP;
    return 0;
}

int32_t icm42688p_configure(icm42688p_t *d, const icm42688p_config_t *cfg)
{
    if (d == NULL || cfg == NULL || cfg->accel_fs_sel > 3u || cfg->gyro_fs_sel > 7u || !odr_valid(cfg->odr)
        || cfg->ui_filt_bw > 7u) {
        return ICM42688P_ERR_ARGUMENT;
    }
    if (memcmp(&d->want, cfg, sizeof *cfg) != 0) {
        d->want = *cfg;
        d->config_dirty = true;
    }
    return 0;
}

void icm42688p_data_ready(icm42688p_t *d, uint64_t edge_us)
{
    if (d != NULL) {
        d->drdy_known = true;
        d->drdy_us = edge_us;
    }
}

/* The ODR period in µs for an ODR code (§14). */
static uint32_t odr_period_us(uint8_t odr)
{
    static const uint32_t period[16] = {1000u, 31u, 63u, 125u, 250u, 500u, 1000u, 5000u, 10000u, 20000u,
                                        40000u, 80000u, 160000u, 320000u, 640000u, 2000u};
    return period[odr & 0x0Fu];
}

static int32_t write_config(icm42688p_t *d, uint64_t now_us)
{
    const icm42688p_config_t *c = &d->want;
    const uint8_t pwr = (uint8_t)((ICM42688P_MODE_LN << ICM42688P_ACCEL_MODE_SHIFT)
                                  | ((c->gyro_on ? ICM42688P_MODE_LN : ICM42688P_MODE_OFF) << ICM42688P_GYRO_MODE_SHIFT));
    const bool gyro_starts = c->gyro_on && !(d->phase == PHASE_RUN && d->cfg.gyro_on);
    const bool accel_starts = d->phase != PHASE_RUN;
    uint8_t status;
    uint32_t wait = 0;
    if (icm42688p_write_reg(d, ICM42688P_GYRO_CONFIG0, (uint8_t)((c->gyro_fs_sel << ICM42688P_FS_SEL_SHIFT) | c->odr)) < 0
        || icm42688p_write_reg(d, ICM42688P_ACCEL_CONFIG0, (uint8_t)((c->accel_fs_sel << ICM42688P_FS_SEL_SHIFT) | c->odr)) < 0
        || icm42688p_write_reg(d, ICM42688P_GYRO_ACCEL_CONFIG0, (uint8_t)((c->ui_filt_bw << 4) | c->ui_filt_bw)) < 0
        || icm42688p_write_reg(d, ICM42688P_INT_SOURCE0, ICM42688P_UI_DRDY_INT1_EN) < 0
        || icm42688p_write_reg(d, ICM42688P_PWR_MGMT0, pwr) < 0
        /* clear a DATA_RDY of the old configuration: the next one is a conversion of this one (§5.3) */
        || icm42688p_read_regs(d, ICM42688P_INT_STATUS, &status, 1u) < 0) {
        return ICM42688P_ERR_BUS;
    }
    d->cfg = *c;
    d->config_dirty = false;
    d->settled = false;
    d->drdy_known = false;
    if (accel_starts) {
        wait = ICM42688P_ACCEL_STARTUP_US;
    }
    if (gyro_starts) {
        wait = ICM42688P_GYRO_STARTUP_US;
    }
    if (wait < ICM42688P_PWR_MODE_WAIT_US) {
        wait = ICM42688P_PWR_MODE_WAIT_US;
    }
    d->fresh_after_us = now_us + wait;
    d->last_fresh_us = now_us + wait;
    d->wait_until_us = now_us + wait;
    return (int32_t)wait;
}

/* ---- self-test ------------------------------------------------------------------------------ */

static int32_t st_begin(icm42688p_t *d, uint64_t now_us)
{
    const bool gyro = d->st_sensor == 0u;
    const uint8_t pwr = gyro ? (uint8_t)(ICM42688P_MODE_LN << ICM42688P_GYRO_MODE_SHIFT)
                             : (uint8_t)(ICM42688P_MODE_LN << ICM42688P_ACCEL_MODE_SHIFT);
    if (icm42688p_write_reg(d, ICM42688P_GYRO_CONFIG0, (uint8_t)((ICM42688P_GYRO_FS_250 << ICM42688P_FS_SEL_SHIFT) | ICM42688P_ODR_1KHZ)) < 0
        || icm42688p_write_reg(d, ICM42688P_ACCEL_CONFIG0, (uint8_t)((ICM42688P_ACCEL_FS_2G << ICM42688P_FS_SEL_SHIFT) | ICM42688P_ODR_1KHZ)) < 0
        || icm42688p_write_reg(d, ICM42688P_GYRO_ACCEL_CONFIG0, 0x44u) < 0  /* ODR/10 for both */
        || icm42688p_write_reg(d, ICM42688P_PWR_MGMT0, pwr) < 0) {
        return ICM42688P_ERR_BUS;
    }
    d->st_count = 0;
    d->st_polls = 0;
    memset(d->st_sum, 0, sizeof d->st_sum);
    d->wait_until_us = now_us + (gyro ? ICM42688P_ST_GYRO_SETTLE_US : ICM42688P_ST_ACCEL_SETTLE_US);
    d->phase = PHASE_ST_OFF;
    return (int32_t)(d->wait_until_us - now_us);
}

static uint32_t iabs32(int32_t v)
{
    return v < 0 ? (uint32_t)(-(int64_t)v) : (uint32_t)v;
}

/* ST_OTP (LSB) for a factory code at FS_SEL 3 (±250 °/s, ±2 g): 2620 · 1.01^(code - 1), rounded. */
static uint32_t st_otp(uint8_t code)
{
    float v = (float)ICM42688P_ST_OTP_BASE;
    uint8_t i;
    for (i = 1u; i < code; i++) {
        v *= 1.01f;
    }
    return (uint32_t)(v + 0.5f);
}

static int32_t st_judge(icm42688p_t *d, const int32_t on[3])
{
    const bool gyro = d->st_sensor == 0u;
    uint8_t codes[3];
    bool pass = true;
    unsigned i;
    if (icm42688p_write_reg(d, ICM42688P_REG_BANK_SEL, gyro ? 1u : 2u) < 0
        || icm42688p_read_regs(d, gyro ? ICM42688P_XG_ST_DATA : ICM42688P_XA_ST_DATA, codes, 3u) < 0
        || icm42688p_write_reg(d, ICM42688P_REG_BANK_SEL, 0u) < 0) {
        return ICM42688P_ERR_BUS;
    }
    for (i = 0; i < 3u; i++) {
        const uint32_t response = iabs32(on[i] - d->st_off[i]);
        if (codes[0] == 0u || codes[1] == 0u || codes[2] == 0u) {
            /* no factory code: absolute limits; 131 LSB per °/s at ±250 °/s, 16384 LSB per g at ±2 g */
            if (gyro ? response < 60u * 131u : (response < 16384u * 50u / 1000u || response > 16384u * 1200u / 1000u)) {
                pass = false;
            }
        } else {
            const uint32_t otp = st_otp(codes[i]);
            /* 0.5 < response / otp < 1.5, in integers */
            if (2u * response <= otp || 2u * response >= 3u * otp) {
                pass = false;
            }
        }
    }
    if (gyro) {
        for (i = 0; i < 3u; i++) {  /* gyroscope offset at rest below 20 °/s */
            if (iabs32(d->st_off[i]) > 20u * 131u) {
                pass = false;
            }
        }
    }
    if (pass) {
        d->self_test = (uint8_t)(d->self_test | (gyro ? ICM42688P_ST_GYRO_PASS : ICM42688P_ST_ACCEL_PASS));
    }
    return pass ? 0 : ICM42688P_ERR_SELF_TEST;
}

/* One poll of a self-test average: a DATA_RDY conversion of the sensor under test is summed. */
static int32_t st_collect(icm42688p_t *d, uint64_t now_us)
{
    const bool gyro = d->st_sensor == 0u;
    uint8_t status, raw[6];
    int32_t avg[3];
    unsigned i;
    if (icm42688p_read_regs(d, ICM42688P_INT_STATUS, &status, 1u) < 0) {
        return ICM42688P_ERR_BUS;
    }
    if (status & ICM42688P_DATA_RDY_INT) {
        if (icm42688p_read_regs(d, gyro ? ICM42688P_GYRO_DATA_X1 : ICM42688P_ACCEL_DATA_X1, raw, 6u) < 0) {
            return ICM42688P_ERR_BUS;
        }
        if (!(be16(&raw[0]) == -32768 && be16(&raw[2]) == -32768 && be16(&raw[4]) == -32768)) {
            for (i = 0; i < 3u; i++) {
                d->st_sum[i] += be16(&raw[2u * i]);
            }
            d->st_count++;
        }
    }
    if (++d->st_polls > 3u * ICM42688P_ST_SAMPLES) {
        return ICM42688P_ERR_SELF_TEST;  /* the sensor does not convert */
    }
    if (d->st_count < ICM42688P_ST_SAMPLES) {
        d->wait_until_us = now_us + 1000u;  /* one period at 1 kHz */
        return 1000;
    }
    for (i = 0; i < 3u; i++) {
        avg[i] = d->st_sum[i] / (int32_t)ICM42688P_ST_SAMPLES;
    }
    d->st_count = 0;
    d->st_polls = 0;
    memset(d->st_sum, 0, sizeof d->st_sum);
    if (d->phase == PHASE_ST_OFF) {
        memcpy(d->st_off, avg, sizeof avg);
        if (icm42688p_write_reg(d, ICM42688P_SELF_TEST_CONFIG,
                                gyro ? (uint8_t)(ICM42688P_EN_GX_ST | ICM42688P_EN_GY_ST | ICM42688P_EN_GZ_ST)
                                     : (uint8_t)(ICM42688P_EN_AX_ST | ICM42688P_EN_AY_ST | ICM42688P_EN_AZ_ST
                                                 | ICM42688P_ACCEL_ST_POWER)) < 0) {
            return ICM42688P_ERR_BUS;
        }
        d->phase = PHASE_ST_ON;
        d->wait_until_us = now_us + (gyro ? ICM42688P_ST_GYRO_ON_SETTLE_US : ICM42688P_ST_ACCEL_ON_SETTLE_US);
        return (int32_t)(d->wait_until_us - now_us);
    }
    /* PHASE_ST_ON: self-test off, sensors off, judge */
    if (icm42688p_write_reg(d, ICM42688P_SELF_TEST_CONFIG, 0u) < 0
        || icm42688p_write_reg(d, ICM42688P_PWR_MGMT0, 0u) < 0) {
        return ICM42688P_ERR_BUS;
    }
    {
        const int32_t rc = st_judge(d, avg);
        if (rc < 0) {
            return rc;
        }
    }
    if (gyro) {
        d->st_sensor = 1u;
        d->phase = PHASE_ST_START;
    } else {
        d->phase = PHASE_CONFIG;
    }
    d->wait_until_us = now_us + ICM42688P_PWR_MODE_WAIT_US;
    return (int32_t)ICM42688P_PWR_MODE_WAIT_US;
}

/* ---- bring-up ------------------------------------------------------------------------------- */

int32_t icm42688p_step(icm42688p_t *d, uint64_t now_us)
{
    uint8_t v;
    int32_t rc;
    if (d == NULL || d->bus == NULL) {
        return ICM42688P_ERR_ARGUMENT;
    }
    if (d->phase == PHASE_FAILED) {
        return d->error;
    }
    if (now_us < d->wait_until_us) {
        const uint64_t left = d->wait_until_us - now_us;
        return (int32_t)(left > 0x7FFFFFFFu ? 0x7FFFFFFFu : left);
    }
    switch (d->phase) {
    case PHASE_POWER_UP:
        /* the part may have powered up with the MCU: its registers answer 1 ms later */
        d->phase = PHASE_PROBE;
        d->wait_until_us = now_us + ICM42688P_SOFT_RESET_WAIT_US;
        return (int32_t)ICM42688P_SOFT_RESET_WAIT_US;
    case PHASE_PROBE:
        if (icm42688p_write_reg(d, ICM42688P_REG_BANK_SEL, 0u) < 0
            || icm42688p_read_regs(d, ICM42688P_WHO_AM_I, &v, 1u) < 0) {
            return fail(d, ICM42688P_ERR_BUS);
        }
        if (v != ICM42688P_WHO_AM_I_VALUE) {
            return fail(d, ICM42688P_ERR_WHO_AM_I);
        }
        if (icm42688p_write_reg(d, ICM42688P_DEVICE_CONFIG, ICM42688P_SOFT_RESET_CONFIG) < 0) {
            return fail(d, ICM42688P_ERR_BUS);
        }
        d->phase = PHASE_RESET_DONE;
        d->wait_until_us = now_us + ICM42688P_SOFT_RESET_WAIT_US;
        return (int32_t)ICM42688P_SOFT_RESET_WAIT_US;
    case PHASE_RESET_DONE:
        if (icm42688p_read_regs(d, ICM42688P_INT_STATUS, &v, 1u) < 0) {
            return fail(d, ICM42688P_ERR_BUS);
        }
        if (!(v & ICM42688P_RESET_DONE_INT)) {
            return fail(d, ICM42688P_ERR_RESET);
        }
        if (icm42688p_read_regs(d, ICM42688P_WHO_AM_I, &v, 1u) < 0) {
            return fail(d, ICM42688P_ERR_BUS);
        }
        if (v != ICM42688P_WHO_AM_I_VALUE) {
            return fail(d, ICM42688P_ERR_WHO_AM_I);
        }
        d->st_sensor = (uint8_t)(d->want.gyro_on ? 0u : 1u);
        d->phase = d->want_self_test ? PHASE_ST_START : PHASE_CONFIG;
        return icm42688p_step(d, now_us);
    case PHASE_ST_START:
        if (d->st_sensor == 0u) {
            d->self_test = ICM42688P_ST_RAN;
        } else {
            d->self_test = (uint8_t)(d->self_test | ICM42688P_ST_RAN);
        }
        rc = st_begin(d, now_us);
        return rc < 0 ? fail(d, rc) : rc;
    case PHASE_ST_OFF:
    case PHASE_ST_ON:
        rc = st_collect(d, now_us);
        return rc < 0 ? fail(d, rc) : rc;
    case PHASE_CONFIG:
        rc = write_config(d, now_us);
        if (rc < 0) {
            return fail(d, rc);
        }
        d->phase = PHASE_RUN;
        return rc;
    case PHASE_RUN:
        if (d->config_dirty) {
            rc = write_config(d, now_us);
            return rc < 0 ? fail(d, rc) : rc;
        }
        return 0;
    default:
        return fail(d, ICM42688P_ERR_ARGUMENT);
    }
}

bool icm42688p_in_self_test(const icm42688p_t *d)
{
    return d != NULL && d->phase >= PHASE_ST_START && d->phase <= PHASE_ST_ON;
}

int32_t icm42688p_run(icm42688p_t *d, uint64_t *now_us)
{
    int32_t rc;
    if (d == NULL || now_us == NULL || d->bus == NULL || d->bus->delay_us == NULL) {
        return ICM42688P_ERR_ARGUMENT;
    }
    for (;;) {
        rc = icm42688p_step(d, *now_us);
        if (rc <= 0) {
            return rc;
        }
        d->bus->delay_us(d->bus->user, (uint32_t)rc);
        *now_us += (uint32_t)rc;
    }
}

/* ---- reading -------------------------------------------------------------------------------- */

static bool at_rail(int16_t v)
{
    return v == 32767 || v <= -32767;
}

int32_t icm42688p_read(icm42688p_t *d, uint64_t now_us, icm42688p_sample_t *out)
{
    uint8_t status, who;
    uint8_t raw[14];
    unsigned i;
    if (d == NULL || out == NULL) {
        return ICM42688P_ERR_ARGUMENT;
    }
    memset(out, 0, sizeof *out);
    if (d->phase == PHASE_FAILED) {
        return d->error;
    }
    if (d->phase != PHASE_RUN) {
        return ICM42688P_ERR_NOT_READY;
    }
    if (icm42688p_read_regs(d, ICM42688P_INT_STATUS, &status, 1u) < 0
        || icm42688p_read_regs(d, ICM42688P_TEMP_DATA1, raw, sizeof raw) < 0) {
        return fail(d, ICM42688P_ERR_BUS);
    }
    if (status & ICM42688P_RESET_DONE_INT) {
        return fail(d, ICM42688P_ERR_GONE);  /* the part reset itself: its configuration is gone */
    }
    /* still this part? INT_STATUS bit 7 is reserved (0), WHO_AM_I reads 0x47: a part that answers
     * garbage (a broken line, another device answering) is a fault, never a reading */
    if ((status & 0x80u) || icm42688p_read_regs(d, ICM42688P_WHO_AM_I, &who, 1u) < 0) {
        return fail(d, (status & 0x80u) ? ICM42688P_ERR_GONE : ICM42688P_ERR_BUS);
    }
    if (who != ICM42688P_WHO_AM_I_VALUE) {
        return fail(d, ICM42688P_ERR_GONE);
    }
    out->temp = be16(&raw[0]);
    for (i = 0; i < 3u; i++) {
        out->accel[i] = be16(&raw[2u + 2u * i]);
        out->gyro[i] = d->cfg.gyro_on ? be16(&raw[8u + 2u * i]) : 0;
    }
    /* fresh: a DATA_RDY of a conversion made after the configuration's start-up. Without the edge's
     * time, the first read past the start-up only clears DATA_RDY (its conversion may be older). */
    out->fresh = (status & ICM42688P_DATA_RDY_INT) && now_us >= d->fresh_after_us
                 && (d->settled || (d->drdy_known && d->drdy_us >= d->fresh_after_us));
    if (now_us >= d->fresh_after_us) {
        d->settled = true;
    }
    if (out->fresh) {
        const bool accel_off = out->accel[0] == -32768 && out->accel[1] == -32768 && out->accel[2] == -32768;
        const bool gyro_off = d->cfg.gyro_on && out->gyro[0] == -32768 && out->gyro[1] == -32768
                              && out->gyro[2] == -32768;
        if (accel_off || gyro_off) {
            return fail(d, ICM42688P_ERR_GONE);  /* a sensor that was on reads "off" */
        }
        for (i = 0; i < 3u; i++) {
            if (at_rail(out->accel[i]) || (d->cfg.gyro_on && at_rail(out->gyro[i]))) {
                out->saturated = true;
            }
        }
        out->latch_known = d->drdy_known;
        out->latch_us = d->drdy_known ? d->drdy_us : now_us - odr_period_us(d->cfg.odr) / 2u;
        d->drdy_known = false;
        d->fresh_after_us = now_us;
        d->last_fresh_us = now_us;
    } else if (now_us >= d->last_fresh_us && now_us - d->last_fresh_us > ICM42688P_DRDY_TIMEOUT_US) {
        return fail(d, ICM42688P_ERR_GONE);  /* no conversion for 100 ms: the part stopped */
    }
    return 0;
}

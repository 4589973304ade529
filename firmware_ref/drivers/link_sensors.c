/*
 * link_sensors.c — capsheet_hal_t read_axes / read_imu on top of the ICM-42688-P driver (and a
 * magnetometer driver): link_sensors.h.
 *
 * From the protocol to the part:
 *   CONFIG range r (±2 g · 2^r)       -> ACCEL_FS_SEL 3 - r (±2 g is FS_SEL 3, ±16 g FS_SEL 0: §14)
 *   CONFIG_IMU gyro_range r (±125·2^r) -> GYRO_FS_SEL 4 - r (±125 °/s is FS_SEL 4, ±2000 FS_SEL 0: §14);
 *                                         the part's counts are then the protocol's (32768 / full scale)
 *   CONFIG rate_hz                     -> the lowest ODR of at least twice the SYNC rate (a conversion
 *                                         within every SYNC period despite the two clocks' drift)
 *   CONFIG filter 0 / 50 / 100 / 200 Hz-> the UI filter bandwidth: ODR/4 (the part's default), or the
 *                                         widest ODR/n not above the cut-off asked for
 * From the part to the protocol: read_axes hands the chip ±2 g counts (1024 per g, what the reference
 * chip scales by its range: capsheet_fw.h), i.e. the part's counts · 2^r / 16; read_imu the gyroscope
 * counts as read, and latch_us from the data-ready edge.
 */
#include "link_sensors.h"

#include <string.h>

#include "icm42688p_reg.h"

int32_t capsheet_link_sensors_init(capsheet_link_sensors_t *ls, const capsheet_bus_t *bus, uint8_t imu_cs,
                                   const capsheet_mag_driver_t *mag, const capsheet_chip_t *chip, bool self_test)
{
    if (ls == NULL || bus == NULL || bus->spi_transfer == NULL || (mag != NULL && mag->read == NULL)) {
        return CAPSHEET_ERR_ARGUMENT;
    }
    memset(ls, 0, sizeof *ls);
    ls->mag = mag;
    ls->chip = chip;
    ls->status = CAPSHEET_SAMPLE_STALE;
    if (icm42688p_init(&ls->imu, bus, imu_cs, self_test) < 0) {
        return CAPSHEET_ERR_ARGUMENT;
    }
    return 0;
}

/* ODR codes by period, shortest last: the lowest ODR at least twice rate_hz. */
static uint8_t odr_for(uint16_t rate_hz)
{
    static const struct { uint16_t hz; uint8_t code; } odrs[] = {
        {25u, 10u}, {50u, 9u}, {100u, 8u}, {200u, 7u}, {500u, 15u}, {1000u, 6u}, {2000u, 5u},
        {4000u, 4u}, {8000u, 3u}};
    const uint32_t want = 2u * (uint32_t)rate_hz;
    size_t i;
    for (i = 0; i < sizeof odrs / sizeof odrs[0]; i++) {
        if (odrs[i].hz >= want) {
            return odrs[i].code;
        }
    }
    return 3u;
}

static uint8_t bw_for(uint8_t filter, uint8_t odr_code)
{
    static const uint16_t cutoff[4] = {0u, 50u, 100u, 200u};
    static const uint8_t div[8] = {2u, 4u, 5u, 8u, 10u, 16u, 20u, 40u};
    static const uint32_t odr_hz[16] = {0u, 32000u, 16000u, 8000u, 4000u, 2000u, 1000u, 200u, 100u, 50u,
                                        25u, 12u, 6u, 3u, 1u, 500u};
    uint8_t i;
    if (filter == 0u || filter > 3u) {
        return 1u;
    }
    for (i = 0; i < 8u; i++) {
        if (odr_hz[odr_code & 0x0Fu] / div[i] <= cutoff[filter]) {
            return i;
        }
    }
    return 7u;
}

/* The configuration the chip's CONFIG / CONFIG_IMU ask for. */
static void wanted(const capsheet_link_sensors_t *ls, uint8_t gyro_range, icm42688p_config_t *cfg)
{
    icm42688p_default_config(cfg);
    cfg->odr = odr_for(145u);   /* CONFIG's power-on rate_hz (docs/protocol.md §4.11) */
    if (ls->chip != NULL && !ls->chip->powered) {
        /* the sensors come up before the chip's protocol starts: CONFIG's and CONFIG_IMU's power-on
         * values (§4.11, §16.2), the gyroscope as the chip's capabilities say */
        cfg->gyro_on = (ls->chip->config.capabilities & CAPSHEET_CAP_GYRO) != 0u;
        gyro_range = CAPSHEET_IMU_DEFAULT_GYRO_RANGE;
    } else if (ls->chip != NULL) {
        const uint8_t range = ls->chip->range_code > 3u ? 3u : ls->chip->range_code;
        cfg->accel_fs_sel = (uint8_t)(3u - range);
        cfg->odr = odr_for(ls->chip->rate_hz);
        cfg->ui_filt_bw = bw_for(ls->chip->filter, cfg->odr);
        cfg->gyro_on = (ls->chip->config.capabilities & CAPSHEET_CAP_GYRO) != 0u;
    }
    cfg->gyro_fs_sel = (uint8_t)(4u - (gyro_range > 4u ? 4u : gyro_range));
}

static int32_t sensors_failed(capsheet_link_sensors_t *ls, int32_t err)
{
    if (ls->fault == 0) {
        ls->fault = err;
    }
    return ls->fault;
}

int32_t capsheet_link_sensors_poll(capsheet_link_sensors_t *ls, uint64_t now_us)
{
    icm42688p_config_t cfg;
    int32_t rc, mrc = 0;
    if (ls == NULL) {
        return CAPSHEET_ERR_ARGUMENT;
    }
    if (ls->fault != 0) {
        return ls->fault;
    }
    wanted(ls, ls->chip != NULL ? ls->chip->gyro_range : CAPSHEET_IMU_DEFAULT_GYRO_RANGE, &cfg);
    if (icm42688p_configure(&ls->imu, &cfg) < 0) {
        return sensors_failed(ls, CAPSHEET_ERR_ARGUMENT);
    }
    rc = icm42688p_step(&ls->imu, now_us);
    if (rc < 0) {
        return sensors_failed(ls, rc);
    }
    if (ls->mag != NULL && ls->mag->poll != NULL) {
        mrc = ls->mag->poll(ls->mag->ctx, now_us);
        if (mrc < 0) {
            return sensors_failed(ls, mrc);
        }
    }
    return (rc > 0 && (mrc == 0 || rc < mrc)) ? rc : mrc > 0 ? mrc : rc;
}

void capsheet_link_data_ready(capsheet_link_sensors_t *ls, uint64_t edge_us)
{
    if (ls != NULL) {
        icm42688p_data_ready(&ls->imu, edge_us);
    }
}

/* counts at ACCEL_FS_SEL 3 - r, to ±2 g counts of 1024 per g: · 2^r / 16, floored. */
static int16_t to_2g_counts(int16_t raw, uint8_t range)
{
    const int32_t v = (int32_t)raw * (int32_t)(1u << range);
    const int32_t q = (v >= 0) ? v / 16 : -((-v + 15) / 16);
    return (int16_t)q;
}

int32_t capsheet_link_read_axes(void *user, uint64_t now_us, int16_t xyz[3], uint8_t *status)
{
    capsheet_link_sensors_t *ls = (capsheet_link_sensors_t *)user;
    icm42688p_sample_t s;
    int32_t rc;
    unsigned i;
    if (ls == NULL || xyz == NULL || status == NULL) {
        return CAPSHEET_ERR_ARGUMENT;
    }
    rc = capsheet_link_sensors_poll(ls, now_us);
    if (rc < 0) {
        return rc;   /* a sensor fault: INVALID, never the last value again */
    }
    ls->gyro_fresh = false;
    rc = icm42688p_read(&ls->imu, now_us, &s);
    if (rc == ICM42688P_ERR_NOT_READY) {
        /* still in its bring-up: no conversion yet (SELF_TEST while the self-test runs) */
        memcpy(xyz, ls->accel, sizeof ls->accel);
        *status = (uint8_t)(CAPSHEET_SAMPLE_STALE
                            | (icm42688p_in_self_test(&ls->imu) ? CAPSHEET_SAMPLE_SELF_TEST : 0u));
        ls->status = *status;
        return 0;
    }
    if (rc < 0) {
        return sensors_failed(ls, rc);
    }
    if (s.fresh) {
        const uint8_t range = (uint8_t)(3u - ls->imu.cfg.accel_fs_sel);
        for (i = 0; i < 3u; i++) {
            ls->accel[i] = to_2g_counts(s.accel[i], range);
            ls->gyro[i] = s.gyro[i];
        }
        ls->latch_us = s.latch_us;
        ls->have_accel = true;
        ls->gyro_fresh = true;
        ls->status = s.saturated ? CAPSHEET_SAMPLE_SATURATED : 0u;
    } else {
        ls->status = CAPSHEET_SAMPLE_STALE;  /* §5.3: the last value again, flagged */
    }
    memcpy(xyz, ls->accel, sizeof ls->accel);
    *status = ls->status;
    return 0;
}

int32_t capsheet_link_read_imu(void *user, uint64_t now_us, uint8_t gyro_range, uint8_t mag_range,
                               bool want_mag, capsheet_imu_reading_t *out)
{
    capsheet_link_sensors_t *ls = (capsheet_link_sensors_t *)user;
    if (ls == NULL || out == NULL) {
        return CAPSHEET_ERR_ARGUMENT;
    }
    if (ls->fault != 0) {
        return ls->fault;
    }
    memcpy(out->gyro, ls->gyro, sizeof ls->gyro);
    out->latch_us = ls->latch_us;
    out->status = (uint8_t)(ls->status & (CAPSHEET_SAMPLE_STALE | CAPSHEET_SAMPLE_SELF_TEST));
    if (ls->imu.cfg.gyro_fs_sel != (uint8_t)(4u - (gyro_range > 4u ? 4u : gyro_range))) {
        out->status = (uint8_t)(out->status | CAPSHEET_SAMPLE_STALE);  /* not yet converted at this range */
    }
    if (want_mag) {
        uint8_t ms = 0;
        int32_t rc;
        if (ls->mag == NULL) {
            return sensors_failed(ls, CAPSHEET_ERR_HAL);
        }
        rc = ls->mag->read(ls->mag->ctx, now_us, mag_range, out->mag, &ms);
        if (rc < 0 || (ms & CAPSHEET_SAMPLE_INVALID)) {
            return sensors_failed(ls, rc < 0 ? rc : CAPSHEET_ERR_HAL);
        }
        out->status = (uint8_t)(out->status | (ms & CAPSHEET_SAMPLE_SELF_TEST));
    }
    return 0;
}

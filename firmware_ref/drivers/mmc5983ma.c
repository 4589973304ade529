/*
 * mmc5983ma.c — the MEMSIC MMC5983MA driver (mmc5983ma.h); the datasheet facts it uses are in
 * mmc5983ma_reg.h, each cited to "MMC5983MA Rev A" and its page.
 */
#include "mmc5983ma.h"

#include <string.h>

#include "mmc5983ma_reg.h"

enum {
    PH_START = 0,       /* first step: the part's power-on time runs from here */
    PH_PROBE,           /* Product ID1, then SW_RST */
    PH_AFTER_RESET,     /* OTP_Rd_Done, bandwidth, SET */
    PH_MEAS_SET,        /* TM_M after the SET pulse */
    PH_READ_SET,        /* the SET measurement's outputs; then RESET */
    PH_MEAS_RESET,      /* TM_M after the RESET pulse */
    PH_READ_RESET,      /* the RESET measurement's outputs; the offset; then TM_T */
    PH_READ_TEMP,       /* Tout; then SET */
    PH_FIRST,           /* the first streaming TM_M after the SET pulse */
    PH_RUNNING
};

/* DS Rev A p.15, Internal Control 1: the measurement time of each BW code */
static const uint32_t k_meas_us[4] = { MMC5983MA_MEAS_US_BW0, MMC5983MA_MEAS_US_BW1, MMC5983MA_MEAS_US_BW2,
                                       MMC5983MA_MEAS_US_BW3 };

/* SET / RESET run 500 ns (DS Rev A p.15); the driver waits a whole µs. */
/* The power-on time is 10 ms (p.15), a typical figure on the part's own clock, for which the
 * datasheet gives no tolerance: the driver waits 20 % more before it speaks to the part. */
#define POWER_ON_WAIT_US (MMC5983MA_POWER_ON_US + MMC5983MA_POWER_ON_US / 5u)
#define SET_RESET_WAIT_US 1u
/* a measurement not finished after 4 times its time + 1 ms has failed (the timeout SparkFun's
 * driver uses; the datasheet gives the times as typical, with no tolerance) */
static uint32_t timeout_us(const mmc5983ma_t *d)
{
    return 4u * k_meas_us[d->bw] + 1000u;
}

static int32_t fail(mmc5983ma_t *d, int32_t err)
{
    if (d->error == 0) {
        d->error = err;
    }
    return d->error;
}

int32_t mmc5983ma_read_regs(mmc5983ma_t *d, uint8_t reg, uint8_t *buf, size_t len)
{
    uint8_t tx[16], rx[16];
    if (d == NULL || buf == NULL || len == 0u || len > sizeof tx - 1u) {
        return MMC5983MA_ERR_ARGUMENT;
    }
    if (d->on_i2c) {  /* the register address, a repeated start, the bytes (DS Rev A p.17) */
        tx[0] = (uint8_t)(reg & MMC5983MA_SPI_ADDR_MASK);
        return d->bus->i2c_write_read(d->bus->user, d->i2c_addr, tx, 1u, buf, len) < 0 ? MMC5983MA_ERR_BUS : 0;
    }
    memset(tx, 0, sizeof tx);
    tx[0] = (uint8_t)(MMC5983MA_SPI_READ | (reg & MMC5983MA_SPI_ADDR_MASK));
    if (d->bus->spi_transfer(d->bus->user, d->cs, tx, rx, len + 1u) < 0) {
        return MMC5983MA_ERR_BUS;
    }
    memcpy(buf, rx + 1, len);
    return 0;
}

int32_t mmc5983ma_write_reg(mmc5983ma_t *d, uint8_t reg, uint8_t value)
{
    uint8_t tx[2], rx[2];
    if (d == NULL) {
        return MMC5983MA_ERR_ARGUMENT;
    }
    tx[0] = (uint8_t)(reg & MMC5983MA_SPI_ADDR_MASK);  /* SPI: RW bit 0, a write (DS Rev A p.7) */
    tx[1] = value;
    if (d->on_i2c) {
        return d->bus->i2c_write_read(d->bus->user, d->i2c_addr, tx, 2u, NULL, 0u) < 0 ? MMC5983MA_ERR_BUS : 0;
    }
    if (d->bus->spi_transfer(d->bus->user, d->cs, tx, rx, 2u) < 0) {
        return MMC5983MA_ERR_BUS;
    }
    return 0;
}

static void setup(mmc5983ma_t *d, const capsheet_bus_t *bus, uint8_t bw)
{
    memset(d, 0, sizeof *d);
    d->bus = bus;
    d->bw = bw;
    d->axes[0] = 1;
    d->axes[1] = 2;
    d->axes[2] = 3;
    d->phase = PH_START;
}

int32_t mmc5983ma_init(mmc5983ma_t *d, const capsheet_bus_t *bus, uint8_t cs, uint8_t bw)
{
    if (d == NULL || bus == NULL || bus->spi_transfer == NULL || bw > 3u) {
        return MMC5983MA_ERR_ARGUMENT;
    }
    setup(d, bus, bw);
    d->cs = cs;
    return 0;
}

int32_t mmc5983ma_init_i2c(mmc5983ma_t *d, const capsheet_bus_t *bus, uint8_t addr7, uint8_t bw)
{
    if (d == NULL || bus == NULL || bus->i2c_write_read == NULL || bw > 3u || addr7 > 0x7Fu) {
        return MMC5983MA_ERR_ARGUMENT;
    }
    setup(d, bus, bw);
    d->i2c_addr = addr7;
    d->on_i2c = true;
    return 0;
}

int32_t mmc5983ma_set_axes(mmc5983ma_t *d, const int8_t axes[3])
{
    unsigned seen = 0u, i;
    if (d == NULL || axes == NULL) {
        return MMC5983MA_ERR_ARGUMENT;
    }
    for (i = 0; i < 3u; i++) {
        const int a = axes[i] < 0 ? -axes[i] : axes[i];
        if (a < 1 || a > 3 || (seen & (1u << a))) {
            return MMC5983MA_ERR_ARGUMENT;
        }
        seen |= 1u << a;
    }
    memcpy(d->axes, axes, sizeof d->axes);
    return 0;
}

/* Xout0 .. Status in one burst (DS Rev A p.13; p.17: the address pointer moves to the next byte).
 * A part that answers like no MMC5983MA — a reserved Status bit set, OTP_Rd_Done clear (it is set
 * from power-up on), XYZout2's two low bits set — is gone: SDO floating high (0xFF), stuck low
 * (0x00: OTP_Rd_Done clear), or a part rebooting. */
static int32_t read_block(mmc5983ma_t *d, uint8_t regs[9])
{
    if (mmc5983ma_read_regs(d, MMC5983MA_XOUT0, regs, 9u) < 0) {
        return fail(d, MMC5983MA_ERR_BUS);
    }
    if ((regs[MMC5983MA_STATUS] & MMC5983MA_STATUS_RESERVED_MASK) != 0u
        || (regs[MMC5983MA_STATUS] & MMC5983MA_STATUS_OTP_READ_DONE) == 0u
        || (regs[MMC5983MA_XYZOUT2] & MMC5983MA_XYZOUT2_ZERO_MASK) != 0u) {
        return fail(d, MMC5983MA_ERR_GONE);
    }
    return 0;
}

/* the 18-bit outputs, MSB first: Xout0 = [17:10], Xout1 = [9:2], XYZout2 = the two low bits (p.13) */
static void outputs(const uint8_t regs[9], uint32_t raw[3])
{
    static const uint8_t shift[3] = { MMC5983MA_XYZOUT2_X_SHIFT, MMC5983MA_XYZOUT2_Y_SHIFT, MMC5983MA_XYZOUT2_Z_SHIFT };
    unsigned i;
    for (i = 0; i < 3u; i++) {
        raw[i] = ((uint32_t)regs[2u * i] << 10) | ((uint32_t)regs[2u * i + 1u] << 2)
                 | (((uint32_t)regs[MMC5983MA_XYZOUT2] >> shift[i]) & 3u);
    }
}

static bool at_rail(uint32_t raw)
{
    return raw == 0u || raw >= (uint32_t)MMC5983MA_RAW_MAX;
}

/* A measurement in flight: taken when Meas_M_Done says it finished (1), not yet (0), or failed. */
static int32_t take_measurement(mmc5983ma_t *d, uint64_t now_us, uint32_t raw[3])
{
    uint8_t regs[9];
    int32_t rc = read_block(d, regs);
    if (rc < 0) {
        return rc;
    }
    if (!(regs[MMC5983MA_STATUS] & MMC5983MA_STATUS_MEAS_M_DONE)) {
        if (now_us > d->start_us && now_us - d->start_us > timeout_us(d)) {  /* an older now: not late */
            return fail(d, MMC5983MA_ERR_TIMEOUT);
        }
        return 0;
    }
    outputs(regs, raw);
    return 1;
}

/* TM_M at now_us (after a SET or RESET pulse has ended) */
static int32_t start_measurement(mmc5983ma_t *d, uint64_t now_us)
{
    if (mmc5983ma_write_reg(d, MMC5983MA_INTERNAL_CONTROL_0, MMC5983MA_CTRL0_TM_M) < 0) {
        return fail(d, MMC5983MA_ERR_BUS);
    }
    d->start_us = now_us;
    d->pending = true;
    return 0;
}

static int32_t wait(mmc5983ma_t *d, uint64_t now_us, uint32_t us)
{
    d->wait_until_us = now_us + us;
    return (int32_t)us;
}

/* the poll interval while a measurement is expected */
static uint32_t poll_us(const mmc5983ma_t *d)
{
    const uint32_t q = k_meas_us[d->bw] / 4u;
    return q > 0u ? q : 1u;
}

/* Running: take a finished measurement (offset removed) and start the next after a SET. */
static int32_t service(mmc5983ma_t *d, uint64_t now_us)
{
    uint32_t raw[3];
    unsigned i;
    int32_t rc = take_measurement(d, now_us, raw);
    if (rc < 0) {
        return rc;
    }
    if (rc == 0) {  /* still converting */
        const uint64_t due = d->start_us + k_meas_us[d->bw];
        return due > now_us ? (int32_t)(due - now_us) : (int32_t)poll_us(d);
    }
    if (d->pending) {
        d->railed = 0u;
        for (i = 0; i < 3u; i++) {
            d->field2[i] = 2 * ((int32_t)raw[i] - MMC5983MA_NULL_FIELD) - d->offset2[i];
            if (at_rail(raw[i])) {
                d->railed = (uint8_t)(d->railed | (1u << i));
            }
        }
        d->latch_us = d->start_us + k_meas_us[d->bw] / 2u;
        d->have_field = true;
        d->measurements++;
        d->pending = false;
    }
    /* SET before every measurement (Prd_set's "every 1 measurement", DS Rev A p.16, done by hand):
     * the offset was measured after a SET, and a SET restores a film a field over 10 G flipped. The
     * pulse (500 ns) is over before the next transaction's 16 clocks end at 10 MHz (1.6 µs); the
     * bus's delay_us, when there is one, waits for it anyway. */
    if (mmc5983ma_write_reg(d, MMC5983MA_INTERNAL_CONTROL_0, MMC5983MA_CTRL0_SET) < 0) {
        return fail(d, MMC5983MA_ERR_BUS);
    }
    if (d->bus->delay_us != NULL) {
        d->bus->delay_us(d->bus->user, SET_RESET_WAIT_US);
        now_us += SET_RESET_WAIT_US;
    }
    rc = start_measurement(d, now_us);
    return rc < 0 ? rc : (int32_t)k_meas_us[d->bw];
}

/* The self-test's verdict on the SET and RESET outputs (DS Rev A p.18 "Using SET and RESET to
 * remove bridge offset": Output1 = +H + Offset, Output2 = -H + Offset): no output at a rail, and
 * the offset (Output1 + Output2) / 2 within the null-field output's 0.5 G (p.2). */
static int32_t judge_self_test(mmc5983ma_t *d)
{
    unsigned i;
    for (i = 0; i < 3u; i++) {
        const int32_t off2 = (int32_t)d->raw_set[i] + (int32_t)d->raw_reset[i] - 2 * MMC5983MA_NULL_FIELD;
        if (at_rail(d->raw_set[i]) || at_rail(d->raw_reset[i])
            || off2 > 2 * MMC5983MA_NULL_FIELD_LIMIT_COUNTS || off2 < -2 * MMC5983MA_NULL_FIELD_LIMIT_COUNTS) {
            return fail(d, MMC5983MA_ERR_SELF_TEST);
        }
        d->offset2[i] = off2;
    }
    return 0;
}

static int32_t bring_up(mmc5983ma_t *d, uint64_t now_us)
{
    uint8_t v;
    uint32_t raw[3];
    int32_t rc;
    switch (d->phase) {
    case PH_START:  /* the part may have powered up with the MCU: its power-on time first (p.15) */
        d->phase = PH_PROBE;
        return wait(d, now_us, POWER_ON_WAIT_US);
    case PH_PROBE:
        if (mmc5983ma_read_regs(d, MMC5983MA_PRODUCT_ID_1, &v, 1u) < 0) {
            return fail(d, MMC5983MA_ERR_BUS);
        }
        if (v != MMC5983MA_PRODUCT_ID_1_VALUE) {
            return fail(d, MMC5983MA_ERR_PRODUCT_ID);
        }
        if (mmc5983ma_write_reg(d, MMC5983MA_INTERNAL_CONTROL_1, MMC5983MA_CTRL1_SW_RST) < 0) {
            return fail(d, MMC5983MA_ERR_BUS);
        }
        d->phase = PH_AFTER_RESET;
        return wait(d, now_us, POWER_ON_WAIT_US);  /* "The power on time is 10mS" (p.15) */
    case PH_AFTER_RESET:
        if (mmc5983ma_read_regs(d, MMC5983MA_PRODUCT_ID_1, &v, 1u) < 0) {
            return fail(d, MMC5983MA_ERR_BUS);
        }
        if (v != MMC5983MA_PRODUCT_ID_1_VALUE) {
            return fail(d, MMC5983MA_ERR_PRODUCT_ID);
        }
        if (mmc5983ma_read_regs(d, MMC5983MA_STATUS, &v, 1u) < 0) {
            return fail(d, MMC5983MA_ERR_BUS);
        }
        if ((v & MMC5983MA_STATUS_RESERVED_MASK) != 0u) {
            return fail(d, MMC5983MA_ERR_GONE);
        }
        if (!(v & MMC5983MA_STATUS_OTP_READ_DONE)) {
            return fail(d, MMC5983MA_ERR_OTP);
        }
        if (mmc5983ma_write_reg(d, MMC5983MA_INTERNAL_CONTROL_1, d->bw) < 0
            || mmc5983ma_write_reg(d, MMC5983MA_INTERNAL_CONTROL_0, MMC5983MA_CTRL0_SET) < 0) {
            return fail(d, MMC5983MA_ERR_BUS);
        }
        d->phase = PH_MEAS_SET;
        return wait(d, now_us, SET_RESET_WAIT_US);
    case PH_MEAS_SET:
    case PH_MEAS_RESET:
    case PH_FIRST:
        rc = start_measurement(d, now_us);
        if (rc < 0) {
            return rc;
        }
        d->phase = (uint8_t)(d->phase + 1u);
        if (d->phase == PH_RUNNING) {
            return 0;
        }
        return wait(d, now_us, k_meas_us[d->bw]);
    case PH_READ_SET:
    case PH_READ_RESET:
        rc = take_measurement(d, now_us, raw);
        if (rc <= 0) {
            return rc < 0 ? rc : wait(d, now_us, poll_us(d));
        }
        d->pending = false;
        if (d->phase == PH_READ_SET) {
            memcpy(d->raw_set, raw, sizeof raw);
            if (mmc5983ma_write_reg(d, MMC5983MA_INTERNAL_CONTROL_0, MMC5983MA_CTRL0_RESET) < 0) {
                return fail(d, MMC5983MA_ERR_BUS);
            }
            d->phase = PH_MEAS_RESET;
            return wait(d, now_us, SET_RESET_WAIT_US);
        }
        memcpy(d->raw_reset, raw, sizeof raw);
        rc = judge_self_test(d);
        if (rc < 0) {
            return rc;
        }
        if (mmc5983ma_write_reg(d, MMC5983MA_INTERNAL_CONTROL_0, MMC5983MA_CTRL0_TM_T) < 0) {
            return fail(d, MMC5983MA_ERR_BUS);
        }
        d->start_us = now_us;
        d->phase = PH_READ_TEMP;
        return wait(d, now_us, k_meas_us[d->bw]);  /* TM_T's time is not given: a measurement's */
    case PH_READ_TEMP: {
        uint8_t regs[9];
        rc = read_block(d, regs);
        if (rc < 0) {
            return rc;
        }
        if (!(regs[MMC5983MA_STATUS] & MMC5983MA_STATUS_MEAS_T_DONE)) {
            if (now_us > d->start_us && now_us - d->start_us > timeout_us(d)) {
                return fail(d, MMC5983MA_ERR_TIMEOUT);
            }
            return wait(d, now_us, poll_us(d));
        }
        d->tout = regs[MMC5983MA_TOUT];
        if (mmc5983ma_write_reg(d, MMC5983MA_INTERNAL_CONTROL_0, MMC5983MA_CTRL0_SET) < 0) {
            return fail(d, MMC5983MA_ERR_BUS);
        }
        d->phase = PH_FIRST;
        return wait(d, now_us, SET_RESET_WAIT_US);
    }
    default:
        return fail(d, MMC5983MA_ERR_ARGUMENT);
    }
}

int32_t mmc5983ma_step(mmc5983ma_t *d, uint64_t now_us)
{
    if (d == NULL || d->bus == NULL) {
        return MMC5983MA_ERR_ARGUMENT;
    }
    if (d->error != 0) {
        return d->error;
    }
    if (d->phase != PH_START && now_us < d->wait_until_us) {
        return (int32_t)(d->wait_until_us - now_us);
    }
    if (d->phase != PH_RUNNING) {
        return bring_up(d, now_us);
    }
    if (!d->pending || now_us >= d->start_us + k_meas_us[d->bw]) {
        const int32_t rc = service(d, now_us);
        if (rc < 0) {
            return rc;
        }
        d->wait_until_us = now_us + (uint32_t)rc;
        return rc;
    }
    return (int32_t)(d->start_us + k_meas_us[d->bw] - now_us);
}

int32_t mmc5983ma_run(mmc5983ma_t *d, uint64_t *now_us)
{
    unsigned guard;
    if (d == NULL || now_us == NULL || d->bus == NULL || d->bus->delay_us == NULL) {
        return MMC5983MA_ERR_ARGUMENT;
    }
    for (guard = 0; guard < 1000u; guard++) {
        const int32_t rc = mmc5983ma_step(d, *now_us);
        if (rc < 0) {
            return rc;
        }
        if (d->phase == PH_RUNNING) {
            return 0;
        }
        d->bus->delay_us(d->bus->user, (uint32_t)rc);
        *now_us += (uint32_t)rc;
    }
    return fail(d, MMC5983MA_ERR_TIMEOUT);
}

/* twice a field of 18-bit counts (16384 per gauss) to counts at range r (32768 / (4 (r + 1)) per
 * gauss): / (4 (r + 1)), rounded half away from zero, clamped to the 16-bit range */
static int16_t to_range(int32_t field2, uint8_t r, bool *sat)
{
    const int32_t den = 4 * ((int32_t)r + 1);
    const int32_t q = field2 >= 0 ? (field2 + den / 2) / den : -((-field2 + den / 2) / den);
    if (q >= INT16_MAX) {
        *sat = true;
        return INT16_MAX;
    }
    if (q <= INT16_MIN) {
        *sat = true;
        return INT16_MIN;
    }
    return (int16_t)q;
}

int32_t mmc5983ma_read(mmc5983ma_t *d, uint64_t now_us, uint8_t mag_range, int16_t mag[3], uint8_t *status,
                       uint64_t *latch_us)
{
    unsigned i;
    int32_t rc;
    if (d == NULL || mag == NULL || status == NULL || mag_range > 3u) {
        return MMC5983MA_ERR_ARGUMENT;
    }
    if (d->error != 0) {
        return d->error;
    }
    if (d->phase != PH_RUNNING) {
        return MMC5983MA_ERR_NOT_READY;
    }
    /* every read goes to the part: a finished measurement is taken, and a part gone is found now */
    rc = service(d, now_us);
    if (rc < 0) {
        return rc;
    }
    *status = 0u;
    for (i = 0; i < 3u; i++) {
        const int a = d->axes[i] < 0 ? -d->axes[i] : d->axes[i];
        const unsigned p = (unsigned)(a - 1);
        bool sat = false;
        int32_t f2 = d->field2[p];
        if (d->axes[i] < 0) {
            f2 = -f2;
        }
        if (d->railed & (1u << p)) {  /* the part's own rail: the protocol's rail, of its sign */
            mag[i] = f2 >= 0 ? INT16_MAX : INT16_MIN;
            sat = true;
        } else {
            mag[i] = to_range(f2, mag_range, &sat);
        }
        if (sat) {
            *status = (uint8_t)(*status | CAPSHEET_SAMPLE_SATURATED);
        }
    }
    if (latch_us != NULL) {
        *latch_us = d->latch_us;
    }
    return 0;
}

int32_t mmc5983ma_temperature_dc(const mmc5983ma_t *d)
{
    return MMC5983MA_TOUT_ZERO_DC + MMC5983MA_TOUT_DC_PER_LSB * (int32_t)d->tout;
}

static int32_t glue_poll(void *ctx, uint64_t now_us)
{
    const int32_t rc = mmc5983ma_step((mmc5983ma_t *)ctx, now_us);
    /* running: the glue need not call again for the magnetometer's sake (reads drive it) */
    return (rc > 0 && ((mmc5983ma_t *)ctx)->phase == PH_RUNNING) ? 0 : rc;
}

static int32_t glue_read(void *ctx, uint64_t now_us, uint8_t mag_range, int16_t mag[3], uint8_t *status)
{
    return mmc5983ma_read((mmc5983ma_t *)ctx, now_us, mag_range, mag, status, NULL);
}

void mmc5983ma_mag_driver(mmc5983ma_t *d, capsheet_mag_driver_t *out)
{
    if (out != NULL) {
        out->ctx = d;
        out->poll = glue_poll;
        out->read = glue_read;
    }
}

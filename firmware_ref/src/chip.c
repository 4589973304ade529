/*
 * chip.c — the chip side of the capsheet protocol (docs/protocol.md §3–§8) on top of codec.c.
 *
 * Everything that decides what the chip does with a command is the table `k_rules` below, a
 * transcription of protocol/state.py RULES (the tests compare the two pair by pair). The rest follows
 * docs/protocol.md §8.1 exactly as the Python chip model (virtual_sheet/chip.py) does, so the
 * two are interchangeable (the tests drive both with the same frames, and with tests/vectors/chip.json):
 *   1. a frame whose integrity failed (COBS, short, CRC, oversize) is counted in rx_errors
 *      (saturating at 255) and dropped;
 *   2. a frame for another node (not its node id, not 0: also every CAN frame that is not a capsheet
 *      frame) is ignored, not counted — except, in BOOT, an ASSIGN to its previous provisional id;
 *   3. a node -> host type (0x01..0x0F, defined or not) is ignored, not counted;
 *   4. another version / an undefined type / a wrong length / a field out of range: counted; NACK
 *      BAD_VERSION / UNKNOWN_COMMAND / BAD_LENGTH / BAD_VALUE when addressed, silence when broadcast;
 *   5. ASSIGN whose uid_low is not this chip's: silent;
 *   6. (state, type) not in the table: NACK BAD_STATE when addressed, silent when broadcast;
 *   7. the rule's field checks (CONFIG, CAL_WRITE, CONFIG_IMU): NACK BAD_VALUE or UNSUPPORTED when
 *      addressed, silent (and nothing applied) when broadcast;
 *   8. the rule's reply and transition.
 * A broadcast is never answered with a NACK.
 *
 * new in 1.2 (§16): a chip built with capability GYRO (and MAG) takes CONFIG_IMU and, in format 1 or 2,
 * answers each SYNC with one IMU record — the accelerometer word exactly as a SAMPLE's (range,
 * SATURATED, STALE, FAULT rules), the HAL's gyroscope (and magnetometer) counts, time_us — as an
 * IMU_SAMPLE on serial and, with CONFIG_IMU flag FD, in a CAN FD frame; else as IMU_GYRO (+ IMU_MAG)
 * + IMU_ACCEL classic CAN frames, in that order. Format 0 is the 1.1 chip, byte for byte.
 */
#include "capsheet_fw.h"
#include "chip_internal.h"

#include <string.h>

/* ------------------------------------------------------------------------------------------ */
/* The state table (protocol/state.py RULES)                                                   */
/* ------------------------------------------------------------------------------------------ */

#define R_(reply, next, validate) {(uint8_t)(reply), (uint8_t)(next), (uint8_t)(validate)}
#define NO_RULE R_(0xFF, CAPSHEET_STAY, 0)
#define ST CAPSHEET_STAY

/* [state][type - 0x10]: SYNC ASSIGN CONFIG START STOP GET_INFO RESET CAL_WRITE CAL_READ CONFIG_IMU
 * CAL_IMU_WRITE CAL_IMU_READ */
static const capsheet_rule_t k_rules[CAPSHEET_STATE_COUNT][CAPSHEET_HOST_TYPE_LAST - CAPSHEET_HOST_TYPE_FIRST + 1u] = {
    /* BOOT */
    {R_(CAPSHEET_REPLY_NONE, ST, 0), R_(CAPSHEET_REPLY_ACK, CAPSHEET_IDLE, 0), NO_RULE, NO_RULE, NO_RULE,
     R_(CAPSHEET_REPLY_ANNOUNCE_INFO, ST, 0), R_(CAPSHEET_REPLY_ACK_THEN_BOOT, CAPSHEET_BOOT, 0), NO_RULE,
     NO_RULE, NO_RULE, NO_RULE, NO_RULE},
    /* IDLE */
    {R_(CAPSHEET_REPLY_NONE, ST, 0), R_(CAPSHEET_REPLY_ACK, CAPSHEET_IDLE, 0), R_(CAPSHEET_REPLY_ACK, ST, 1),
     R_(CAPSHEET_REPLY_ACK, CAPSHEET_STREAMING, 0), R_(CAPSHEET_REPLY_ACK, ST, 0),
     R_(CAPSHEET_REPLY_ANNOUNCE_INFO, ST, 0), R_(CAPSHEET_REPLY_ACK_THEN_BOOT, CAPSHEET_BOOT, 0),
     R_(CAPSHEET_REPLY_ACK, ST, 1), R_(CAPSHEET_REPLY_CAL_DATA, ST, 0), R_(CAPSHEET_REPLY_ACK, ST, 1),
     R_(CAPSHEET_REPLY_ACK, ST, 1), R_(CAPSHEET_REPLY_CAL_IMU_DATA, ST, 1)},
    /* STREAMING */
    {R_(CAPSHEET_REPLY_SAMPLE, ST, 0), NO_RULE, NO_RULE, R_(CAPSHEET_REPLY_ACK, ST, 0),
     R_(CAPSHEET_REPLY_ACK, CAPSHEET_IDLE, 0), R_(CAPSHEET_REPLY_ANNOUNCE_INFO, ST, 0),
     R_(CAPSHEET_REPLY_ACK_THEN_BOOT, CAPSHEET_BOOT, 0), NO_RULE, R_(CAPSHEET_REPLY_CAL_DATA, ST, 0), NO_RULE,
     NO_RULE, R_(CAPSHEET_REPLY_CAL_IMU_DATA, ST, 1)},
    /* FAULT */
    {R_(CAPSHEET_REPLY_SAMPLE, ST, 0), R_(CAPSHEET_REPLY_ACK, CAPSHEET_FAULT, 0), R_(CAPSHEET_REPLY_ACK, ST, 1),
     R_(CAPSHEET_REPLY_ACK, ST, 0), R_(CAPSHEET_REPLY_ACK, ST, 0), R_(CAPSHEET_REPLY_ANNOUNCE_INFO, ST, 0),
     R_(CAPSHEET_REPLY_ACK_THEN_BOOT, CAPSHEET_BOOT, 0), NO_RULE, R_(CAPSHEET_REPLY_CAL_DATA, ST, 0),
     R_(CAPSHEET_REPLY_ACK, ST, 1), NO_RULE, R_(CAPSHEET_REPLY_CAL_IMU_DATA, ST, 1)},
};

int32_t capsheet_rule_for(uint8_t state, uint8_t type, capsheet_rule_t *rule)
{
    CAPSHEET_ASSERT(rule != NULL);
    if (state >= CAPSHEET_STATE_COUNT || type < CAPSHEET_HOST_TYPE_FIRST || type > CAPSHEET_HOST_TYPE_LAST) {
        return CAPSHEET_ERR_ARGUMENT;
    }
    *rule = k_rules[state][type - CAPSHEET_HOST_TYPE_FIRST];
    return (rule->reply == 0xFFu) ? 0 : 1;
}

#ifdef CAPSHEET_MUTANTS
/* Mutant: the frame in c->tx re-encoded with CRC-16/XMODEM (init 0x0000). Returns its length. */
static int32_t mutant_wrong_crc(capsheet_chip_t *c, int32_t n)
{
    uint8_t raw[CAPSHEET_CHIP_TX_WIRE_SIZE];
    int32_t k = capsheet_cobs_decode(c->tx, (size_t)n - 1u, raw, sizeof raw);
    uint16_t crc;
    if (k < 2) {
        return n;
    }
    crc = capsheet_crc16(raw, (size_t)k - 2u, 0x0000u);
    raw[k - 2] = (uint8_t)(crc >> 8);
    raw[k - 1] = (uint8_t)(crc & 0xFFu);
    k = capsheet_cobs_encode(raw, (size_t)k, c->tx, sizeof c->tx - 1u);
    if (k < 0) {
        return n;
    }
    c->tx[k] = 0u;
    return k + 1;
}
#endif

/* ------------------------------------------------------------------------------------------ */
/* Sending                                                                                     */
/* ------------------------------------------------------------------------------------------ */

/* Send one message; returns 1 (one frame) or a negative error. */
CAPSHEET_WARN_UNUSED int32_t capsheet_chip_send_msg(capsheet_chip_t *c, const capsheet_msg_t *m)
{
    int32_t n;
    if (c->config.transport == CAPSHEET_TRANSPORT_SERIAL) {
        n = capsheet_serial_encode(m, c->tx, sizeof c->tx);
        if (n < 0) {
            return n;
        }
#ifdef CAPSHEET_MUTANTS
        if (CAPSHEET_MUTANT(c, CAPSHEET_MUT_WRONG_CRC)
            || (CAPSHEET_MUTANT(c, CAPSHEET_MUT_WRONG_CRC_SAMPLE) && m->type == CAPSHEET_SAMPLE)) {
            n = mutant_wrong_crc(c, n);
        }
#endif
        return (c->hal->send_bytes(c->hal->user, c->tx, (size_t)n) < 0) ? CAPSHEET_ERR_HAL : 1;
    } else {
        uint32_t id;
        bool fd;
        /* AUTO: classic for every payload of 8 bytes or less (§7.2), FD for an IMU_SAMPLE (§16.3) */
        n = capsheet_can_encode(m, CAPSHEET_CAN_AUTO, &id, c->tx, sizeof c->tx, &fd);
        if (n < 0) {
            return n;
        }
        if (CAPSHEET_MUTANT(c, CAPSHEET_MUT_WRONG_PRIORITY) && m->type == CAPSHEET_SAMPLE) {
            id = (id & 0x03FFFFFFu) | ((uint32_t)4u << 26);
        }
        return (c->hal->send_can(c->hal->user, id, c->tx, (uint8_t)n, fd) < 0) ? CAPSHEET_ERR_HAL : 1;
    }
}

void capsheet_chip_msg_init(capsheet_msg_t *m, uint8_t type, uint16_t node)
{
    memset(m, 0, sizeof *m);
    m->type = type;
    m->node = node;
}

static CAPSHEET_WARN_UNUSED int32_t send_ack(capsheet_chip_t *c, uint8_t command)
{
    capsheet_msg_t m;
    capsheet_chip_msg_init(&m, CAPSHEET_ACK, c->node);
    m.u.ack.command = command;
    if (CAPSHEET_MUTANT(c, CAPSHEET_MUT_ACK_DETAIL)) {
        m.u.ack.detail = 1u;
    }
    return capsheet_chip_send_msg(c, &m);
}

static CAPSHEET_WARN_UNUSED int32_t send_nack(capsheet_chip_t *c, uint8_t command, uint8_t reason)
{
    capsheet_msg_t m;
    capsheet_chip_msg_init(&m, CAPSHEET_NACK, c->node);
    m.u.nack.command = command;
    m.u.nack.reason = reason;
    if (CAPSHEET_MUTANT(c, CAPSHEET_MUT_WRONG_NACK_REASON)) {
        m.u.nack.reason = (uint8_t)(reason % 7u + 1u);
    }
    return capsheet_chip_send_msg(c, &m);
}

uint16_t capsheet_chip_capabilities(const capsheet_chip_t *c)
{
    return (uint16_t)(c->config.capabilities | (c->config.can_fd ? CAPSHEET_CAP_CAN_FD : 0u));
}

static CAPSHEET_WARN_UNUSED int32_t send_announce_info(capsheet_chip_t *c)
{
    capsheet_msg_t m;
    int32_t rc;
    capsheet_chip_msg_init(&m, CAPSHEET_ANNOUNCE, c->node);
    m.u.announce.uid = c->uid;
    rc = capsheet_chip_send_msg(c, &m);
    if (rc < 0) {
        return rc;
    }
    capsheet_chip_msg_init(&m, CAPSHEET_INFO, c->node);
    m.u.info.fw_major = CAPSHEET_FW_VERSION_MAJOR;
    m.u.info.fw_minor = CAPSHEET_FW_VERSION_MINOR;
    m.u.info.fw_patch = CAPSHEET_FW_VERSION_PATCH;
    m.u.info.protocol_version = (uint8_t)CAPSHEET_PROTOCOL_VERSION;
    m.u.info.capabilities = capsheet_chip_capabilities(c);
    if (CAPSHEET_MUTANT(c, CAPSHEET_MUT_RESERVED_CAPABILITY_BIT)) {
        m.u.info.capabilities = (uint16_t)(m.u.info.capabilities | 0x8000u);
    }
    m.u.info.adc_bits = 12;
    m.u.info.state = c->state;
    rc = capsheet_chip_send_msg(c, &m);
    return (rc < 0) ? rc : 2;
}

static uint32_t uptime_s(const capsheet_chip_t *c, uint64_t now_us)
{
    /* floor((now - boot) / 1e6) by shift-and-subtract: Cortex-M0+ has no divider, and libgcc's
     * 64-bit division alone would cost ~700 bytes of flash. Bounded: 64 steps. */
    const uint64_t d = (now_us > c->boot_us) ? now_us - c->boot_us : 0u;
    uint64_t rem = 0, q = 0;
    int bit;
    for (bit = 63; bit >= 0; bit--) {
        rem = (rem << 1) | ((d >> bit) & 1u);
        q <<= 1;
        if (rem >= 1000000u) {
            rem -= 1000000u;
            q |= 1u;
        }
    }
    return (uint32_t)q;  /* u32 on the wire (136 years) */
}

static uint8_t status_flags(const capsheet_chip_t *c)
{
    uint8_t f = c->flags & CAPSHEET_FLAG_CONFIGURED;
    if ((c->cal[0].flags | c->cal[1].flags | c->cal[2].flags) & 1u) {
        f = (uint8_t)(f | CAPSHEET_FLAG_CAL_VALID);
    }
    if (c->state == CAPSHEET_FAULT) {
        f = (uint8_t)(f | CAPSHEET_FLAG_ADC_FAULT);
    }
    return f;
}

static CAPSHEET_WARN_UNUSED int32_t send_status(capsheet_chip_t *c, uint64_t now_us)
{
    capsheet_msg_t m;
    capsheet_chip_msg_init(&m, CAPSHEET_STATUS, c->node);
    m.u.status.state = c->state;
    m.u.status.flags = status_flags(c);
    m.u.status.rx_errors = c->rx_errors;
    m.u.status.missed_syncs = c->missed_syncs;
    m.u.status.uptime_s = uptime_s(c, now_us);
    return capsheet_chip_send_msg(c, &m);
}

/* ------------------------------------------------------------------------------------------ */
/* Boot and time                                                                               */
/* ------------------------------------------------------------------------------------------ */

static void load_calibration(capsheet_chip_t *c)
{
    uint8_t axis;
    for (axis = 0; axis < 3u; axis++) {
        capsheet_cal_t *cal = &c->cal[axis];
        if (c->hal->cal_load == NULL || c->hal->cal_load(c->hal->user, axis, cal) < 0) {
            cal->flags = 0;
            cal->offset_q4 = 0;
            cal->sensitivity = 1024.0f;  /* nominal, ±2 g */
        }
        cal->axis = axis;
        cal->flags &= 1u;
    }
}


static void schedule(uint64_t *deadline, uint64_t period_us, uint64_t now_us)
{
    /* docs §14: next = previous deadline + period (no drift); if that is not after now (a whole
     * period was missed), now + period: what was missed is skipped, never sent back to back */
    *deadline += period_us;
    if (*deadline <= now_us) {
        *deadline = now_us + period_us;
    }
}

static CAPSHEET_WARN_UNUSED int32_t boot(capsheet_chip_t *c, uint64_t now_us)
{
    c->uid = c->hal->read_uid(c->hal->user);
    c->state = CAPSHEET_BOOT;
    c->salt = 0;
    c->node = capsheet_provisional_node(c->uid, 0);
    c->has_prev = false;
    c->prev_node = 0;
    c->link = 0;
    c->has_link = false;
    c->started = false;
    c->flags = 0;
    c->rx_errors = 0;
    c->missed_syncs = 0;
    c->have_sync = false;
    if (CAPSHEET_MUTANT(c, CAPSHEET_MUT_UPTIME_RESET)) {
        c->boot_us = now_us;
    }
    c->next_announce_us = now_us + CAPSHEET_ANNOUNCE_PERIOD_US;
    c->heartbeat_on = false;
    c->next_heartbeat_us = 0;
    c->rate_hz = 145;
    c->range_code = 0;
    c->filter = 0;
    c->heartbeat_ms = CAPSHEET_DEFAULT_HEARTBEAT_MS;
    c->imu_format = CAPSHEET_IMU_FORMAT_ACCEL;  /* §16.2: until the first CONFIG_IMU */
    c->gyro_range = CAPSHEET_IMU_DEFAULT_GYRO_RANGE;
    c->mag_range = 0;
    c->imu_flags = 0;
    load_calibration(c);
#if CAPSHEET_IMU
    capsheet_chip_load_imu_calibration(c);
#endif
    if (c->config.transport == CAPSHEET_TRANSPORT_SERIAL) {
        c->rx.len = 0;
        c->rx.discarding = false;
    }
    c->powered = true;
    return send_announce_info(c);
}

int32_t capsheet_chip_init(capsheet_chip_t *chip, const capsheet_chip_config_t *config,
                           const capsheet_hal_t *hal, uint8_t *rx_buf, size_t rx_cap)
{
    CAPSHEET_ASSERT(chip != NULL && config != NULL && hal != NULL);
    memset(chip, 0, sizeof *chip);
    if (hal->read_axes == NULL || hal->read_uid == NULL) {
        return CAPSHEET_ERR_ARGUMENT;
    }
    if ((config->capabilities & CAPSHEET_CAP_CAL_STORAGE) && (hal->cal_load == NULL || hal->cal_store == NULL)) {
        return CAPSHEET_ERR_ARGUMENT;
    }
    if ((config->capabilities & CAPSHEET_CAP_GYRO) && (!CAPSHEET_IMU || hal->read_imu == NULL
        || ((config->capabilities & CAPSHEET_CAP_CAL_STORAGE) && (hal->cal_imu_load == NULL || hal->cal_imu_store == NULL)))) {
        return CAPSHEET_ERR_ARGUMENT;  /* a gyroscope the HAL cannot read (or store the calibration of), or a build without IMU records */
    }
    if (config->transport == CAPSHEET_TRANSPORT_SERIAL) {
        if (hal->send_bytes == NULL || rx_cap < CAPSHEET_MIN_RX_BUFFER_SIZE) {
            return CAPSHEET_ERR_ARGUMENT;
        }
        if (capsheet_stream_init(&chip->rx, rx_buf, rx_cap) < 0) {
            return CAPSHEET_ERR_ARGUMENT;
        }
    } else if (config->transport == CAPSHEET_TRANSPORT_CAN) {
        if (hal->send_can == NULL) {
            return CAPSHEET_ERR_ARGUMENT;
        }
    } else {
        return CAPSHEET_ERR_ARGUMENT;
    }
    chip->hal = hal;
    chip->config = *config;
    chip->state = CAPSHEET_BOOT;
    return 0;
}

int32_t capsheet_chip_power_on(capsheet_chip_t *chip, uint64_t now_us)
{
    CAPSHEET_ASSERT(chip != NULL && chip->hal != NULL);
    chip->boot_us = now_us;  /* uptime_s counts from power-on; RESET does not restart it (§4.4) */
    return boot(chip, now_us);
}

void capsheet_chip_sensor_fault(capsheet_chip_t *chip)
{
    CAPSHEET_ASSERT(chip != NULL);
    if (chip->powered && chip->state != CAPSHEET_BOOT) {
        chip->state = CAPSHEET_FAULT;
    }
}

int32_t capsheet_chip_poll(capsheet_chip_t *c, uint64_t now_us)
{
    int32_t rc;
    CAPSHEET_ASSERT(c != NULL && c->hal != NULL);
    if (!c->powered) {
        return 0;
    }
    if (c->state == CAPSHEET_BOOT) {
        if (now_us < c->next_announce_us) {
            return 0;
        }
        if (CAPSHEET_MUTANT(c, CAPSHEET_MUT_NO_REANNOUNCE)) {
            return 0;
        }
        /* unanswered: a new provisional id (salt = ANNOUNCE rounds unanswered, docs §3.2); the
         * previous one still takes an ASSIGN that crossed this ANNOUNCE on the wire (§3.3) */
        c->salt++;
        c->prev_node = c->node;
        c->has_prev = true;
        c->node = capsheet_provisional_node(c->uid, c->salt);
        schedule(&c->next_announce_us, CAPSHEET_ANNOUNCE_PERIOD_US, now_us);
        return send_announce_info(c);
    }
    if (c->heartbeat_ms != 0u && c->heartbeat_on && now_us >= c->next_heartbeat_us) {
        schedule(&c->next_heartbeat_us, (uint64_t)((uint32_t)c->heartbeat_ms * 1000u)
                                            * (CAPSHEET_MUTANT(c, CAPSHEET_MUT_SLOW_HEARTBEAT) ? 2u : 1u), now_us);
        rc = send_status(c, now_us);
        return rc;
    }
    return 0;
}

/* ------------------------------------------------------------------------------------------ */
/* Commands                                                                                    */
/* ------------------------------------------------------------------------------------------ */

static void count_rx_error(capsheet_chip_t *c)
{
    if (CAPSHEET_MUTANT(c, CAPSHEET_MUT_NO_RX_ERRORS)) {
        return;
    }
    if (c->rx_errors < 0xFFu) {
        c->rx_errors++;
    }
}

/* The rule's field checks (CONFIG, CAL_WRITE, CONFIG_IMU): 0, or a NACK reason. */
static uint8_t check_fields(const capsheet_chip_t *c, const capsheet_msg_t *m)
{
    const uint16_t caps = capsheet_chip_capabilities(c);
    if (m->type == CAPSHEET_CONFIG) {
        if ((m->u.config.rate_hz < 1u || m->u.config.rate_hz > 4000u || m->u.config.range > 3u
             || m->u.config.filter > 3u) && !CAPSHEET_MUTANT(c, CAPSHEET_MUT_ACCEPTS_BAD_CONFIG)) {
            return CAPSHEET_NACK_BAD_VALUE;
        }
        if (m->u.config.range != 0u && !(caps & CAPSHEET_CAP_MULTI_RANGE)
            && !CAPSHEET_MUTANT(c, CAPSHEET_MUT_IGNORES_CAPABILITY)) {
            return CAPSHEET_NACK_UNSUPPORTED;
        }
        if (m->u.config.filter != 0u && !(caps & CAPSHEET_CAP_FILTER)) {
            return CAPSHEET_NACK_UNSUPPORTED;
        }
    } else if (m->type == CAPSHEET_CAL_WRITE) {
        if ((m->u.cal.flags & 1u) && !(caps & CAPSHEET_CAP_CAL_STORAGE)) {
            return CAPSHEET_NACK_UNSUPPORTED;
        }
    } else if (m->type == CAPSHEET_CAL_IMU_WRITE || m->type == CAPSHEET_CAL_IMU_READ) {  /* §17.2, in this order */
        const uint8_t block = m->u.cal_imu_read.block;  /* CAL_IMU_WRITE's too: the structs' common initial sequence */
        if (!CAPSHEET_IMU || !(caps & ((block <= 2u) ? CAPSHEET_CAP_GYRO : CAPSHEET_CAP_MAG))) {
            return CAPSHEET_NACK_UNSUPPORTED;
        }
        if (m->type == CAPSHEET_CAL_IMU_WRITE && (m->u.cal_imu.flags & 1u) && !(caps & CAPSHEET_CAP_CAL_STORAGE)) {
            return CAPSHEET_NACK_UNSUPPORTED;
        }
    } else if (m->type == CAPSHEET_CONFIG_IMU) {  /* §16.2, in this order; the ranges whatever the format */
        if ((m->u.config_imu.format > CAPSHEET_IMU_FORMAT_9AXIS || m->u.config_imu.gyro_range > 4u
             || m->u.config_imu.mag_range > 3u) && !CAPSHEET_MUTANT(c, CAPSHEET_MUT_IMU_ACCEPTS_BAD_CONFIG)) {
            return CAPSHEET_NACK_BAD_VALUE;
        }
        if ((m->u.config_imu.format >= CAPSHEET_IMU_FORMAT_6AXIS && !(caps & CAPSHEET_CAP_GYRO))
            || (m->u.config_imu.format == CAPSHEET_IMU_FORMAT_9AXIS && !(caps & CAPSHEET_CAP_MAG))
            || ((m->u.config_imu.flags & CAPSHEET_IMU_FLAG_FD) && !(caps & CAPSHEET_CAP_CAN_FD))) {
            return CAPSHEET_NACK_UNSUPPORTED;
        }
    }
    return 0;
}

/* arithmetic shift right (floor), as Python's >> — C leaves >> of a negative value to the compiler */
static int16_t asr(int16_t v, uint8_t r)
{
    if (v >= 0) {
        return (int16_t)(v >> r);
    }
    return (int16_t)(-1 - (int16_t)((-1 - v) >> r));
}


/* What a SYNC is answered with: the SAMPLE `s` (format 0), or the IMU record built around it. */
static CAPSHEET_WARN_UNUSED int32_t send_reading(capsheet_chip_t *c, const capsheet_msg_t *s, uint64_t now_us)
{
#if CAPSHEET_IMU
    if (c->imu_format != CAPSHEET_IMU_FORMAT_ACCEL && !CAPSHEET_MUTANT(c, CAPSHEET_MUT_IMU_ANSWERS_SAMPLE)) {
        return capsheet_chip_send_record(c, s, now_us);
    }
#endif
    (void)now_us;
    return capsheet_chip_send_msg(c, s);
}

static CAPSHEET_WARN_UNUSED int32_t on_sync(capsheet_chip_t *c, uint16_t counter, uint64_t now_us)
{
    capsheet_msg_t m;
    int16_t xyz[3] = {0, 0, 0};
    uint8_t status = 0;
    unsigned i;
    int32_t rc;
    if (!c->started || (c->state != CAPSHEET_STREAMING && c->state != CAPSHEET_FAULT)) {
        return 0;
    }
    if (c->have_sync) {
        /* §5.1: counters skipped; a repeated or older counter (gap >= 0x7FFF) adds nothing */
        const uint16_t gap = (uint16_t)(counter - c->last_sync - 1u);
        if (gap < 0x7FFFu || CAPSHEET_MUTANT(c, CAPSHEET_MUT_MISSED_SYNCS_WRAP)) {
            const uint32_t missed = (uint32_t)c->missed_syncs + gap;
            c->missed_syncs = (missed > 0xFFu) ? 0xFFu : (uint8_t)missed;
        }
    }
    c->have_sync = true;
    c->last_sync = counter;  /* whatever the counter: the chip follows its SYNC source */
    capsheet_chip_msg_init(&m, CAPSHEET_SAMPLE, c->node);
    m.u.sample.counter = CAPSHEET_MUTANT(c, CAPSHEET_MUT_COUNTER_OFF_BY_ONE) ? (uint16_t)(counter + 1u) : counter;
    if (c->state == CAPSHEET_FAULT) {
        m.u.sample.status = CAPSHEET_SAMPLE_INVALID;
        return send_reading(c, &m, now_us);
    }
    if (c->hal->read_axes(c->hal->user, now_us, xyz, &status) < 0) {
        status = CAPSHEET_SAMPLE_INVALID;
    }
    if (CAPSHEET_MUTANT(c, CAPSHEET_MUT_DEAD_SENSOR)) {
        xyz[0] = xyz[1] = xyz[2] = 0;
        status = 0;
    }
    if (status & CAPSHEET_SAMPLE_INVALID) {
        c->state = CAPSHEET_FAULT;  /* the sensor did not answer: counts 0, status INVALID alone (§8.6) */
        m.u.sample.status = CAPSHEET_SAMPLE_INVALID;
        return send_reading(c, &m, now_us);
    }
    status = (uint8_t)(status & 0xFu & ~CAPSHEET_SAMPLE_SATURATED);
    for (i = 0; i < 3u; i++) {
        int16_t v = xyz[i] < -2048 ? -2048 : (xyz[i] > 2047 ? 2047 : xyz[i]);
        xyz[i] = asr(v, c->range_code);  /* the HAL reports ±2 g counts; range r scales by 2^-r */
        if (xyz[i] == -2048 || xyz[i] == 2047) {
            status = (uint8_t)(status | CAPSHEET_SAMPLE_SATURATED);  /* exactly at a rail sent (§5.2) */
        }
    }
    m.u.sample.x = xyz[0];
    m.u.sample.y = xyz[1];
    m.u.sample.z = xyz[2];
    m.u.sample.status = status;
#ifdef CAPSHEET_MUTANTS
    if (CAPSHEET_MUTANT(c, CAPSHEET_MUT_FROZEN_SAMPLE)) {  /* one conversion, then that word again */
        if (!c->has_frozen) {
            c->has_frozen = true;
            memcpy(c->frozen_xyz, xyz, sizeof c->frozen_xyz);
            c->frozen_status = m.u.sample.status;
        }
        m.u.sample.x = c->frozen_xyz[0];
        m.u.sample.y = c->frozen_xyz[1];
        m.u.sample.z = c->frozen_xyz[2];
        m.u.sample.status = c->frozen_status;
    }
#endif
    rc = send_reading(c, &m, now_us);
    if (rc >= 0 && CAPSHEET_MUTANT(c, CAPSHEET_MUT_SYNC_TWICE)) {
        const int32_t rc2 = send_reading(c, &m, now_us);
        return (rc2 < 0) ? rc2 : rc + rc2;
    }
    return rc;
}

static bool is_integrity_error(int32_t rc)
{
    return rc == CAPSHEET_ERR_BAD_COBS || rc == CAPSHEET_ERR_SHORT || rc == CAPSHEET_ERR_BAD_CRC
           || rc == CAPSHEET_ERR_OVERSIZE;
}

/* The NACK reason for a decode error of a frame addressed to the chip (§8.1). */
static uint8_t nack_reason_for(int32_t rc)
{
    switch (rc) {
    case CAPSHEET_ERR_BAD_VERSION:
        return CAPSHEET_NACK_BAD_VERSION;
    case CAPSHEET_ERR_UNKNOWN_TYPE:
        return CAPSHEET_NACK_UNKNOWN_COMMAND;
    case CAPSHEET_ERR_BAD_LENGTH:
        return CAPSHEET_NACK_BAD_LENGTH;
    default:
        return CAPSHEET_NACK_BAD_VALUE;  /* CAPSHEET_ERR_BAD_FIELD */
    }
}

/* React to a decoded frame (rc == 0), or a decode error rc < 0 with `m->type`/`m->node` from the
 * header when there was one (node 0xFFFF when not), in the order of docs §8.1. */
static CAPSHEET_WARN_UNUSED int32_t on_frame(capsheet_chip_t *c, int32_t rc, const capsheet_msg_t *m, uint64_t now_us)
{
    capsheet_rule_t rule;
    bool addressed;
    uint8_t reason;
    int32_t out;
    if (!c->powered) {
        return 0;
    }
    if (is_integrity_error(rc)) {  /* 1. damage: counted, never answered */
        count_rx_error(c);
        return 0;
    }
    addressed = (m->node == c->node);
    if (!addressed && m->node != CAPSHEET_NODE_BROADCAST) {
        /* 2. another node's frame (also a CAN frame that is not capsheet's: node 0xFFFF) — unless,
         * in BOOT, an ASSIGN to the previous provisional id that crossed the last ANNOUNCE (§3.3) */
        if (!(rc == 0 && m->type == CAPSHEET_ASSIGN && c->state == CAPSHEET_BOOT && c->has_prev
              && m->node == c->prev_node && !CAPSHEET_MUTANT(c, CAPSHEET_MUT_NO_PREVIOUS_ID))) {
            return 0;
        }
        addressed = true;
    }
    if (m->type >= CAPSHEET_NODE_TO_HOST_FIRST && m->type <= CAPSHEET_NODE_TO_HOST_LAST) {
        /* 3. another node's type (of this revision or a later one): never answered, not counted */
        if (CAPSHEET_MUTANT(c, CAPSHEET_MUT_NACKS_NODE_TYPES) && addressed) {
            return send_nack(c, m->type, CAPSHEET_NACK_UNKNOWN_COMMAND);
        }
        return 0;
    }
    if (rc < 0) {  /* 4. version, type, length, field: counted; NACKed only when addressed */
        count_rx_error(c);
        if (!addressed && !CAPSHEET_MUTANT(c, CAPSHEET_MUT_NACKS_BROADCAST)) {
            return 0;
        }
        return send_nack(c, m->type, nack_reason_for(rc));
    }
    if (m->type == CAPSHEET_SYNC) {  /* the hot path: SAMPLE in STREAMING/FAULT, nothing elsewhere */
        return on_sync(c, m->u.sync.counter, now_us);
    }
    if (m->type == CAPSHEET_ASSIGN && m->u.assign.uid_low != (uint32_t)(c->uid & 0xFFFFFFFFu)
        && !CAPSHEET_MUTANT(c, CAPSHEET_MUT_ASSIGN_IGNORES_UID)) {
        return 0;  /* 5. §4.10: meant for another chip that shares the node id */
    }
    if (CAPSHEET_MUTANT(c, CAPSHEET_MUT_IGNORED_RESET) && m->type == CAPSHEET_RESET) {
        return send_ack(c, m->type);
    }
    if (CAPSHEET_MUTANT(c, CAPSHEET_MUT_START_NOT_IDEMPOTENT) && m->type == CAPSHEET_START
        && c->state == CAPSHEET_STREAMING && addressed) {
        return send_nack(c, m->type, CAPSHEET_NACK_BAD_STATE);
    }
    if (CAPSHEET_MUTANT(c, CAPSHEET_MUT_STREAMS_AFTER_STOP) && m->type == CAPSHEET_STOP
        && c->state == CAPSHEET_STREAMING) {
        return send_ack(c, m->type);
    }
    if (CAPSHEET_MUTANT(c, CAPSHEET_MUT_CONFIG_WHILE_STREAMING) && m->type == CAPSHEET_CONFIG
        && c->state == CAPSHEET_STREAMING) {
        return send_ack(c, m->type);
    }
    if (CAPSHEET_MUTANT(c, CAPSHEET_MUT_REFUSES_REPEATED_CONFIG) && m->type == CAPSHEET_CONFIG && addressed
        && (c->flags & CAPSHEET_FLAG_CONFIGURED) && m->u.config.rate_hz == c->rate_hz
        && m->u.config.range == c->range_code && m->u.config.filter == c->filter
        && m->u.config.heartbeat_ms == c->heartbeat_ms) {
        return send_nack(c, m->type, CAPSHEET_NACK_BAD_STATE);
    }
    if (CAPSHEET_MUTANT(c, CAPSHEET_MUT_IGNORES_BROADCAST_START) && !addressed
        && (m->type == CAPSHEET_START || m->type == CAPSHEET_STOP)) {
        return 0;
    }
    if (capsheet_rule_for(c->state, m->type, &rule) != 1) {  /* 6. the state table */
        return (addressed || CAPSHEET_MUTANT(c, CAPSHEET_MUT_NACKS_BROADCAST)
                || (CAPSHEET_MUTANT(c, CAPSHEET_MUT_ANSWERS_BROADCAST) && m->type == CAPSHEET_START))
                   ? send_nack(c, m->type, CAPSHEET_NACK_BAD_STATE) : 0;
    }
    if (rule.validate) {  /* 7. the rule's field checks */
        reason = check_fields(c, m);
        if (reason != 0u) {
            return (addressed || CAPSHEET_MUTANT(c, CAPSHEET_MUT_NACKS_BROADCAST)) ? send_nack(c, m->type, reason) : 0;
        }
    }
    if (rule.reply == CAPSHEET_REPLY_ACK_THEN_BOOT) {
        out = send_ack(c, m->type);
        if (out < 0) {
            return out;
        }
        rc = boot(c, now_us);
        return (rc < 0) ? rc : out + rc;
    }
    switch (m->type) {
    case CAPSHEET_ASSIGN:
        if (c->state == CAPSHEET_BOOT || !c->heartbeat_on) {
            c->next_heartbeat_us = now_us + (uint64_t)((uint32_t)c->heartbeat_ms * 1000u);
            c->heartbeat_on = true;
        }
        c->node = m->u.assign.new_node;
        c->has_prev = false;
        c->link = m->u.assign.link;
        c->has_link = true;
        break;
    case CAPSHEET_CONFIG:
        c->rate_hz = m->u.config.rate_hz;
        c->range_code = m->u.config.range;
        c->filter = m->u.config.filter;
        c->heartbeat_ms = m->u.config.heartbeat_ms;
        c->next_heartbeat_us = now_us + (uint64_t)((uint32_t)c->heartbeat_ms * 1000u);
        c->heartbeat_on = c->heartbeat_ms != 0u;
        c->flags = (uint8_t)(c->flags | CAPSHEET_FLAG_CONFIGURED);
        break;
    case CAPSHEET_CONFIG_IMU:  /* §16.2: at once; CONFIG's fields, CONFIGURED and the heartbeat untouched */
        if (CAPSHEET_MUTANT(c, CAPSHEET_MUT_IMU_ACCEPTS_BAD_CONFIG)
            && (m->u.config_imu.format > CAPSHEET_IMU_FORMAT_9AXIS || m->u.config_imu.gyro_range > 4u
                || m->u.config_imu.mag_range > 3u)) {
            break;  /* the mutant ACKs it and changes nothing */
        }
        c->imu_format = m->u.config_imu.format;
        c->gyro_range = m->u.config_imu.gyro_range;
        c->mag_range = m->u.config_imu.mag_range;
        c->imu_flags = m->u.config_imu.flags;
        break;
    case CAPSHEET_START:
        c->started = true;
        c->have_sync = false;
        break;
    case CAPSHEET_STOP:
        c->started = false;
        break;
    case CAPSHEET_CAL_WRITE: {
        capsheet_cal_t cal = m->u.cal;
        cal.flags &= 1u;
        if (cal.flags && c->hal->cal_store(c->hal->user, cal.axis, &cal) < 0) {
            return send_nack(c, m->type, CAPSHEET_NACK_STORAGE_FAILED);
        }
        c->cal[cal.axis] = cal;
        break;
    }
#if CAPSHEET_IMU
    case CAPSHEET_CAL_IMU_WRITE: {  /* §17.3: per element; the stored copy survives RESET */
        const uint8_t k = capsheet_chip_cal_imu_slot(m->u.cal_imu.block, m->u.cal_imu.index);
        const bool store = (m->u.cal_imu.flags & 1u) != 0u;
        uint32_t bits;
        memcpy(&bits, &m->u.cal_imu.value, sizeof bits);
        if (store && c->hal->cal_imu_store(c->hal->user, k, bits) < 0) {
            return send_nack(c, m->type, CAPSHEET_NACK_STORAGE_FAILED);
        }
        c->imu_cal[k] = bits;
        capsheet_chip_set_imu_stored(c, k, store);
        break;
    }
#endif
    default:
        break;
    }
    if (rule.next_state != CAPSHEET_STAY) {
        c->state = rule.next_state;
    }
    switch (rule.reply) {
    case CAPSHEET_REPLY_ACK:
        return send_ack(c, m->type);
    case CAPSHEET_REPLY_ANNOUNCE_INFO:
        return send_announce_info(c);
    case CAPSHEET_REPLY_CAL_DATA: {
        capsheet_msg_t d;
        capsheet_chip_msg_init(&d, CAPSHEET_CAL_DATA, c->node);
        d.u.cal = c->cal[m->u.cal_read.axis];
        if (CAPSHEET_MUTANT(c, CAPSHEET_MUT_CAL_READ_NOMINAL)) {
            d.u.cal.flags = 0;
            d.u.cal.offset_q4 = 0;
            d.u.cal.sensitivity = 1024.0f;
        }
        return capsheet_chip_send_msg(c, &d);
    }
#if CAPSHEET_IMU
    case CAPSHEET_REPLY_CAL_IMU_DATA: {
        capsheet_msg_t d;
        const uint8_t k = capsheet_chip_cal_imu_slot(m->u.cal_imu_read.block, m->u.cal_imu_read.index);
        capsheet_chip_msg_init(&d, CAPSHEET_CAL_IMU_DATA, c->node);
        d.u.cal_imu.block = m->u.cal_imu_read.block;
        d.u.cal_imu.index = m->u.cal_imu_read.index;
        uint32_t bits = c->imu_cal[k];
        d.u.cal_imu.flags = (uint8_t)(((unsigned)c->imu_cal_stored[k >> 3] >> (k & 7u)) & 1u);
        d.u.cal_imu.reserved = 0;
        if (CAPSHEET_MUTANT(c, CAPSHEET_MUT_CAL_IMU_READ_NOMINAL)) {
            bits = capsheet_chip_cal_imu_nominal_bits(k);
            d.u.cal_imu.flags = 0;
        }
        memcpy(&d.u.cal_imu.value, &bits, sizeof bits);
        return capsheet_chip_send_msg(c, &d);
    }
#endif
    default:
        return 0;
    }
}

int32_t capsheet_chip_rx_bytes(capsheet_chip_t *chip, const uint8_t *data, size_t len, uint64_t now_us)
{
    size_t i;
    int32_t sent = 0, err = 0;
    CAPSHEET_ASSERT(chip != NULL && chip->hal != NULL && (data != NULL || len == 0));
    if (chip->config.transport != CAPSHEET_TRANSPORT_SERIAL) {
        return CAPSHEET_ERR_ARGUMENT;
    }
    for (i = 0; i < len; i++) {
        capsheet_msg_t m;
        int32_t rc;
        m.type = 0xFFu;
        m.node = CAPSHEET_NODE_RESERVED;
        rc = capsheet_stream_feed(&chip->rx, data[i], &m);
        if (rc == 0) {
            continue;
        }
        rc = on_frame(chip, (rc == 1) ? 0 : rc, &m, now_us);
        if (rc < 0) {
            err = rc;
        } else {
            sent += rc;
        }
    }
    return err ? err : sent;
}

int32_t capsheet_chip_rx_can(capsheet_chip_t *chip, uint32_t id, bool is_extended, bool is_fd,
                             const uint8_t *data, size_t len, uint64_t now_us)
{
    capsheet_msg_t m;
    int32_t rc;
    CAPSHEET_ASSERT(chip != NULL && chip->hal != NULL && (data != NULL || len == 0));
    if (chip->config.transport != CAPSHEET_TRANSPORT_CAN) {
        return CAPSHEET_ERR_ARGUMENT;
    }
    m.type = 0xFFu;
    m.node = CAPSHEET_NODE_RESERVED;
    if (is_fd && !chip->config.can_fd) {
        /* an FD frame on a classic controller: never data for it (BAD_LENGTH, header from the id) */
        rc = CAPSHEET_ERR_BAD_FIELD;
        if (is_extended && id < (1ul << 29)) {
            m.type = (uint8_t)((id >> 20) & 0x3Fu);
            m.node = (uint16_t)(id & 0xFFFFu);
            rc = CAPSHEET_ERR_BAD_LENGTH;
        }
    } else {
        rc = capsheet_can_decode(id, is_extended, is_fd, data, len, &m, NULL);
    }
    return on_frame(chip, rc, &m, now_us);
}

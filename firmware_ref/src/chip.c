/*
 * chip.c — the chip side of the capsheet protocol (docs/protocol.md §3–§8) on top of codec.c.
 *
 * Everything that decides what the chip does with a command is the table `k_rules` below, a
 * transcription of protocol/state.py RULES (the tests compare the two pair by pair). What the table
 * leaves open is decided exactly as the Python chip model (virtual_sheet/chip.py) decides it, so
 * the two are interchangeable (and the tests drive both with the same frames):
 *   1. every frame the decoder drops counts in rx_errors (saturating at 255); one without a usable
 *      header (COBS, short, CRC, oversize, bad CAN identifier) gets no answer;
 *   2. BAD_VERSION: NACK BAD_VERSION when addressed to this chip or broadcast;
 *   3. chip -> host types (another chip's frames) and other nodes' frames: ignored;
 *   4. unknown type / bad length / bad field, addressed to this chip: NACK UNKNOWN_COMMAND /
 *      BAD_LENGTH / BAD_VALUE; broadcast: silent;
 *   5. ASSIGN whose uid_low is not this chip's: silent;
 *   6. (state, type) not in the table: NACK BAD_STATE when addressed, silent when broadcast;
 *   7. the rule's field checks (CONFIG, CAL_WRITE): NACK BAD_VALUE or UNSUPPORTED (also when
 *      broadcast);
 *   8. the rule's reply and transition.
 */
#include "capsheet_fw.h"

#include <string.h>

/* ------------------------------------------------------------------------------------------ */
/* The state table (protocol/state.py RULES)                                                   */
/* ------------------------------------------------------------------------------------------ */

#define R_(reply, next, validate) {(uint8_t)(reply), (uint8_t)(next), (uint8_t)(validate)}
#define NO_RULE R_(0xFF, CAPSHEET_STAY, 0)
#define ST CAPSHEET_STAY

/* [state][type - 0x10]: SYNC ASSIGN CONFIG START STOP GET_INFO RESET CAL_WRITE CAL_READ */
static const capsheet_rule_t k_rules[CAPSHEET_STATE_COUNT][9] = {
    /* BOOT */
    {R_(CAPSHEET_REPLY_NONE, ST, 0), R_(CAPSHEET_REPLY_ACK, CAPSHEET_IDLE, 1), NO_RULE, NO_RULE, NO_RULE,
     R_(CAPSHEET_REPLY_ANNOUNCE_INFO, ST, 0), R_(CAPSHEET_REPLY_ACK_THEN_BOOT, CAPSHEET_BOOT, 0), NO_RULE,
     NO_RULE},
    /* IDLE */
    {R_(CAPSHEET_REPLY_NONE, ST, 0), R_(CAPSHEET_REPLY_ACK, CAPSHEET_IDLE, 1), R_(CAPSHEET_REPLY_ACK, ST, 1),
     R_(CAPSHEET_REPLY_ACK, CAPSHEET_STREAMING, 0), R_(CAPSHEET_REPLY_ACK, ST, 0),
     R_(CAPSHEET_REPLY_ANNOUNCE_INFO, ST, 0), R_(CAPSHEET_REPLY_ACK_THEN_BOOT, CAPSHEET_BOOT, 0),
     R_(CAPSHEET_REPLY_ACK, ST, 1), R_(CAPSHEET_REPLY_CAL_DATA, ST, 0)},
    /* STREAMING */
    {R_(CAPSHEET_REPLY_SAMPLE, ST, 0), NO_RULE, NO_RULE, R_(CAPSHEET_REPLY_ACK, ST, 0),
     R_(CAPSHEET_REPLY_ACK, CAPSHEET_IDLE, 0), R_(CAPSHEET_REPLY_ANNOUNCE_INFO, ST, 0),
     R_(CAPSHEET_REPLY_ACK_THEN_BOOT, CAPSHEET_BOOT, 0), NO_RULE, R_(CAPSHEET_REPLY_CAL_DATA, ST, 0)},
    /* FAULT */
    {R_(CAPSHEET_REPLY_SAMPLE, ST, 0), R_(CAPSHEET_REPLY_ACK, CAPSHEET_FAULT, 1), R_(CAPSHEET_REPLY_ACK, ST, 1),
     R_(CAPSHEET_REPLY_ACK, ST, 0), R_(CAPSHEET_REPLY_ACK, ST, 0), R_(CAPSHEET_REPLY_ANNOUNCE_INFO, ST, 0),
     R_(CAPSHEET_REPLY_ACK_THEN_BOOT, CAPSHEET_BOOT, 0), NO_RULE, R_(CAPSHEET_REPLY_CAL_DATA, ST, 0)},
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

/* ------------------------------------------------------------------------------------------ */
/* Sending                                                                                     */
/* ------------------------------------------------------------------------------------------ */

/* Send one message; returns 1 (one frame) or a negative error. */
static int32_t send_msg(capsheet_chip_t *c, const capsheet_msg_t *m)
{
    int32_t n;
    if (c->config.transport == CAPSHEET_TRANSPORT_SERIAL) {
        n = capsheet_serial_encode(m, c->tx, sizeof c->tx);
        if (n < 0) {
            return n;
        }
        return (c->hal->send_bytes(c->hal->user, c->tx, (size_t)n) < 0) ? CAPSHEET_ERR_HAL : 1;
    } else {
        uint32_t id;
        bool fd;
        n = capsheet_can_encode(m, CAPSHEET_CAN_AUTO, &id, c->tx, CAPSHEET_CAN_CLASSIC_MTU, &fd);
        if (n < 0) {
            return n;
        }
        return (c->hal->send_can(c->hal->user, id, c->tx, (uint8_t)n, fd) < 0) ? CAPSHEET_ERR_HAL : 1;
    }
}

static void msg_init(capsheet_msg_t *m, uint8_t type, uint16_t node)
{
    memset(m, 0, sizeof *m);
    m->type = type;
    m->node = node;
}

static int32_t send_ack(capsheet_chip_t *c, uint8_t command)
{
    capsheet_msg_t m;
    msg_init(&m, CAPSHEET_ACK, c->node);
    m.u.ack.command = command;
    return send_msg(c, &m);
}

static int32_t send_nack(capsheet_chip_t *c, uint8_t command, uint8_t reason)
{
    capsheet_msg_t m;
    msg_init(&m, CAPSHEET_NACK, c->node);
    m.u.nack.command = command;
    m.u.nack.reason = reason;
    return send_msg(c, &m);
}

static uint16_t capabilities(const capsheet_chip_t *c)
{
    return (uint16_t)(c->config.capabilities | (c->config.can_fd ? CAPSHEET_CAP_CAN_FD : 0u));
}

static int32_t send_announce_info(capsheet_chip_t *c)
{
    capsheet_msg_t m;
    int32_t rc;
    msg_init(&m, CAPSHEET_ANNOUNCE, c->node);
    m.u.announce.uid = c->uid;
    rc = send_msg(c, &m);
    if (rc < 0) {
        return rc;
    }
    msg_init(&m, CAPSHEET_INFO, c->node);
    m.u.info.fw_major = CAPSHEET_FW_VERSION_MAJOR;
    m.u.info.fw_minor = CAPSHEET_FW_VERSION_MINOR;
    m.u.info.fw_patch = CAPSHEET_FW_VERSION_PATCH;
    m.u.info.protocol_version = (uint8_t)CAPSHEET_PROTOCOL_VERSION;
    m.u.info.capabilities = capabilities(c);
    m.u.info.adc_bits = 12;
    m.u.info.state = c->state;
    rc = send_msg(c, &m);
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

static int32_t send_status(capsheet_chip_t *c, uint64_t now_us)
{
    capsheet_msg_t m;
    msg_init(&m, CAPSHEET_STATUS, c->node);
    m.u.status.state = c->state;
    m.u.status.flags = status_flags(c);
    m.u.status.rx_errors = c->rx_errors;
    m.u.status.missed_syncs = c->missed_syncs;
    m.u.status.uptime_s = uptime_s(c, now_us);
    return send_msg(c, &m);
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
    /* next = max(previous deadline + period, now): no drift, no burst after a long gap */
    *deadline += period_us;
    if (*deadline < now_us) {
        *deadline = now_us;
    }
}

static int32_t boot(capsheet_chip_t *c, uint64_t now_us)
{
    c->uid = c->hal->read_uid(c->hal->user);
    c->state = CAPSHEET_BOOT;
    c->salt = 0;
    c->node = capsheet_provisional_node(c->uid, 0);
    c->link = 0;
    c->has_link = false;
    c->started = false;
    c->flags = 0;
    c->rx_errors = 0;
    c->missed_syncs = 0;
    c->have_sync = false;
    c->boot_us = now_us;
    c->next_announce_us = now_us + CAPSHEET_ANNOUNCE_PERIOD_US;
    c->heartbeat_on = false;
    c->next_heartbeat_us = 0;
    c->rate_hz = 145;
    c->range_code = 0;
    c->filter = 0;
    c->heartbeat_ms = CAPSHEET_DEFAULT_HEARTBEAT_MS;
    load_calibration(c);
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
        /* unanswered: a new provisional id (salt = ANNOUNCE rounds unanswered, docs §3.2) */
        c->salt++;
        c->node = capsheet_provisional_node(c->uid, c->salt);
        schedule(&c->next_announce_us, CAPSHEET_ANNOUNCE_PERIOD_US, now_us);
        return send_announce_info(c);
    }
    if (c->heartbeat_ms != 0u && c->heartbeat_on && now_us >= c->next_heartbeat_us) {
        schedule(&c->next_heartbeat_us, (uint64_t)((uint32_t)c->heartbeat_ms * 1000u), now_us);
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
    if (c->rx_errors < 0xFFu) {
        c->rx_errors++;
    }
}

/* The rule's field checks (CONFIG, CAL_WRITE): 0, or a NACK reason. */
static uint8_t check_fields(const capsheet_chip_t *c, const capsheet_msg_t *m)
{
    const uint16_t caps = capabilities(c);
    if (m->type == CAPSHEET_CONFIG) {
        if (m->u.config.rate_hz < 1u || m->u.config.rate_hz > 4000u || m->u.config.range > 3u
            || m->u.config.filter > 3u) {
            return CAPSHEET_NACK_BAD_VALUE;
        }
        if (m->u.config.range != 0u && !(caps & CAPSHEET_CAP_MULTI_RANGE)) {
            return CAPSHEET_NACK_UNSUPPORTED;
        }
    } else if (m->type == CAPSHEET_CAL_WRITE) {
        if ((m->u.cal.flags & 1u) && !(caps & CAPSHEET_CAP_CAL_STORAGE)) {
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

static int32_t on_sync(capsheet_chip_t *c, uint16_t counter, uint64_t now_us)
{
    capsheet_msg_t m;
    int16_t xyz[3] = {0, 0, 0};
    uint8_t status = 0;
    unsigned i;
    if (!c->started || (c->state != CAPSHEET_STREAMING && c->state != CAPSHEET_FAULT)) {
        return 0;
    }
    if (c->have_sync) {
        /* counters skipped; a repeated or older counter (gap >= 0x7FFF) adds nothing */
        const uint16_t gap = (uint16_t)(counter - c->last_sync - 1u);
        if (gap < 0x7FFFu) {
            const uint32_t missed = (uint32_t)c->missed_syncs + gap;
            c->missed_syncs = (missed > 0xFFu) ? 0xFFu : (uint8_t)missed;
        }
    }
    c->have_sync = true;
    c->last_sync = counter;
    msg_init(&m, CAPSHEET_SAMPLE, c->node);
    m.u.sample.counter = counter;
    if (c->state == CAPSHEET_FAULT) {
        m.u.sample.status = CAPSHEET_SAMPLE_INVALID;
        return send_msg(c, &m);
    }
    if (c->hal->read_axes(c->hal->user, now_us, xyz, &status) < 0) {
        status = CAPSHEET_SAMPLE_INVALID;
    }
    if (status & CAPSHEET_SAMPLE_INVALID) {
        c->state = CAPSHEET_FAULT;  /* the sensor did not answer: counts 0, its status bits */
        m.u.sample.status = status & 0xFu;
        return send_msg(c, &m);
    }
    for (i = 0; i < 3u; i++) {
        int16_t v = xyz[i] < -2048 ? -2048 : (xyz[i] > 2047 ? 2047 : xyz[i]);
        xyz[i] = asr(v, c->range_code);  /* the HAL reports ±2 g counts; range r scales by 2^-r */
    }
    m.u.sample.x = xyz[0];
    m.u.sample.y = xyz[1];
    m.u.sample.z = xyz[2];
    m.u.sample.status = status & 0xFu;
    return send_msg(c, &m);
}

/* React to a decoded frame (rc == 0), or a decode error rc < 0 with `m->type`/`m->node` from the
 * header when there was one (node 0xFFFF when not). */
static int32_t on_frame(capsheet_chip_t *c, int32_t rc, const capsheet_msg_t *m, uint64_t now_us)
{
    capsheet_rule_t rule;
    bool addressed;
    uint8_t reason;
    int32_t out;
    if (!c->powered) {
        return 0;
    }
    if (rc < 0) {
        count_rx_error(c);  /* every frame the receiver drops, whoever it was for */
    }
    if (m->node != c->node && m->node != CAPSHEET_NODE_BROADCAST) {
        return 0;  /* not for this chip; also every frame without a usable header (node 0xFFFF) */
    }
    addressed = (m->node == c->node);
    if (rc == CAPSHEET_ERR_BAD_VERSION) {
        return send_nack(c, m->type, CAPSHEET_NACK_BAD_VERSION);
    }
    if (m->type < CAPSHEET_HOST_TYPE_FIRST && capsheet_type_known(m->type)) {
        return 0;  /* another chip's frame */
    }
    if (rc < 0) {
        if (!addressed) {
            return 0;
        }
        if (rc == CAPSHEET_ERR_UNKNOWN_TYPE) {
            return send_nack(c, m->type, CAPSHEET_NACK_UNKNOWN_COMMAND);
        }
        if (m->type < CAPSHEET_HOST_TYPE_FIRST || m->type > CAPSHEET_HOST_TYPE_LAST) {
            return 0;
        }
        reason = (rc == CAPSHEET_ERR_BAD_LENGTH) ? (uint8_t)CAPSHEET_NACK_BAD_LENGTH : (uint8_t)CAPSHEET_NACK_BAD_VALUE;
        return send_nack(c, m->type, reason);
    }
    if (m->type == CAPSHEET_SYNC) {  /* the hot path: SAMPLE in STREAMING/FAULT, nothing elsewhere */
        return on_sync(c, m->u.sync.counter, now_us);
    }
    if (m->type == CAPSHEET_ASSIGN && m->u.assign.uid_low != (uint32_t)(c->uid & 0xFFFFFFFFu)) {
        return 0;  /* §4.10: meant for another chip that shares the node id */
    }
    if (capsheet_rule_for(c->state, m->type, &rule) != 1) {
        return addressed ? send_nack(c, m->type, CAPSHEET_NACK_BAD_STATE) : 0;
    }
    if (rule.validate) {
        reason = check_fields(c, m);
        if (reason != 0u) {
            return send_nack(c, m->type, reason);
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
        msg_init(&d, CAPSHEET_CAL_DATA, c->node);
        d.u.cal = c->cal[m->u.cal_read.axis];
        return send_msg(c, &d);
    }
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

/*
 * payload.c — the message types (sizes, priorities) and their payloads, encoded and decoded field by
 * field as protocol/messages/ lays them out. No state, no HAL; the frames around them: codec.c.
 */
#include "codec_internal.h"

/* ------------------------------------------------------------------------------------------ */
/* Types                                                                                       */
/* ------------------------------------------------------------------------------------------ */

/* Fixed payload size per type (0x01..0x19); 0xFF = not defined; 0xFE = variable (SNAPSHOT,
 * IMU_SAMPLE: 15 or 21, SNAPSHOT_IMU). */
#define VAR 0xFEu
#define UND 0xFFu
#define N_TYPES 0x1Cu
static const uint8_t k_size[N_TYPES] = {
    UND, 8, 8, 7, 8, 2, 2, 8, VAR,        /* 0x00..0x08 */
    8, 8, 8, 8, VAR, VAR, 8,               /* 0x09 GATEWAY_INFO; 0x0A..0x0E IMU, 1.2; 0x0F CAL_IMU_DATA, 1.3 */
    2, 8, 6, 0, 0, 0, 0, 8, 1, 4, 8, 2    /* 0x10..0x1B (0x19 CONFIG_IMU since 1.2; 0x1A, 0x1B CAL_IMU since 1.3) */
};
/* priority per type (docs §7.1, §4) */
static const uint8_t k_priority[N_TYPES] = {
    7, 5, 5, 2, 6, 3, 3, 5, 2,
    5, 2, 2, 2, 2, 2, 5,
    0, 4, 4, 4, 1, 4, 1, 4, 4, 4, 4, 4
};

bool capsheet_type_known(uint8_t type) { return type < N_TYPES && k_size[type] != UND; }

uint8_t capsheet_priority(uint8_t type) { return capsheet_type_known(type) ? k_priority[type] : 7u; }

uint16_t capsheet_provisional_node(uint64_t uid, uint32_t salt)
{
    uint32_t h = (uint32_t)((uid ^ (uid >> 32)) & 0xFFFFFFFFu) ^ (uint32_t)(salt * 0x9E3779B9u);
    uint32_t m;
    h ^= h >> 16;
    /* h % 0x7FFF without a divide (Cortex-M0+ has none): 2^15 == 1 (mod 2^15 - 1), so sum the
     * 15-bit digits and fold. */
    m = (h & 0x7FFFu) + ((h >> 15) & 0x7FFFu) + (h >> 30);
    while (m >= 0x7FFFu) {
        m -= 0x7FFFu;
    }
    return (uint16_t)(CAPSHEET_NODE_PROVISIONAL_MIN | m);
}

/* ------------------------------------------------------------------------------------------ */
/* Payloads                                                                                    */
/* ------------------------------------------------------------------------------------------ */

static void put_sample_word(uint8_t *p, int16_t x, int16_t y, int16_t z, uint8_t status)
{
    const uint32_t ux = (uint32_t)(uint16_t)x & 0xFFFu;
    const uint32_t uy = (uint32_t)(uint16_t)y & 0xFFFu;
    const uint32_t uz = (uint32_t)(uint16_t)z & 0xFFFu;
    p[0] = (uint8_t)(ux & 0xFFu);
    p[1] = (uint8_t)((ux >> 8) | ((uy & 0xFu) << 4));
    p[2] = (uint8_t)(uy >> 4);
    p[3] = (uint8_t)(uz & 0xFFu);
    p[4] = (uint8_t)((uz >> 8) | ((uint32_t)(status & 0xFu) << 4));
}

#if !CAPSHEET_CHIP_ONLY
/* the 40-bit sample word (§5.2) at p[0..4] */
static void get_sample_word(const uint8_t *p, int16_t *x, int16_t *y, int16_t *z, uint8_t *status)
{
    const uint32_t w = get_u32(p);
    *x = sext12(w);
    *y = sext12(w >> 12);
    *z = sext12((w >> 24) | ((uint32_t)p[4] << 8));
    *status = (uint8_t)(p[4] >> 4);
}

static void get_i16x3(const uint8_t *p, int16_t *a, int16_t *b, int16_t *c)
{
    *a = (int16_t)get_u16(p);
    *b = (int16_t)get_u16(p + 2);
    *c = (int16_t)get_u16(p + 4);
}
#endif

static void put_i16x3(uint8_t *p, int16_t a, int16_t b, int16_t c)
{
    put_u16(p, (uint16_t)a);
    put_u16(p + 2, (uint16_t)b);
    put_u16(p + 4, (uint16_t)c);
}

/* record size by format (§16.1): 0 for a format that is not 1 or 2 */
static void put_cal(uint8_t *p, const capsheet_cal_t *c)
{
    p[0] = c->axis;
    p[1] = c->flags;
    put_u16(p + 2, (uint16_t)c->offset_q4);
    put_u32(p + 4, float_bits(c->sensitivity));
}

/* new in 1.3 (§17.1): CAL_IMU_DATA / CAL_IMU_WRITE */
static void put_cal_imu(uint8_t *p, const capsheet_msg_t *m)
{
    p[0] = m->u.cal_imu.block;
    p[1] = m->u.cal_imu.index;
    p[2] = m->u.cal_imu.flags;
    p[3] = m->u.cal_imu.reserved;
    put_u32(p + 4, float_bits(m->u.cal_imu.value));
}


/* §16.1's record after its accelerometer word's position: the word, time_us (7 bytes at p) */
static void put_word_time(uint8_t *p, int16_t x, int16_t y, int16_t z, uint8_t status, int16_t time_us)
{
    put_sample_word(p, x, y, z, status);
    put_u16(p + 5, (uint16_t)time_us);
}

#if !CAPSHEET_CHIP_ONLY
/* The types a chip never sends: a gateway's and the host's. */
static CAPSHEET_WARN_UNUSED int32_t encode_other(const capsheet_msg_t *m, uint8_t *p)
{
    switch (m->type) {
    case CAPSHEET_CAL_WRITE:
        put_cal(p, &m->u.cal);
        return 8;
    case CAPSHEET_CAL_IMU_WRITE:
        put_cal_imu(p, m);
        return 8;
    case CAPSHEET_CAL_IMU_READ:
        p[0] = m->u.cal_imu_read.block;
        p[1] = m->u.cal_imu_read.index;
        return 2;
    case CAPSHEET_SNAPSHOT:
        if (m->u.snapshot.count == 0u || m->u.snapshot.words == NULL) {
            return CAPSHEET_ERR_ARGUMENT;
        }
        put_u16(p, m->u.snapshot.counter);
        put_u16(p + 2, m->u.snapshot.first_link);
        p[4] = m->u.snapshot.count;
        return 5;
    case CAPSHEET_GATEWAY_INFO:
        p[0] = m->u.gateway_info.flags;
        p[1] = m->u.gateway_info.sample_format;
        put_u16(p + 2, m->u.gateway_info.first_link);
        put_u16(p + 4, m->u.gateway_info.link_count);
        put_u16(p + 6, m->u.gateway_info.sync_rate_hz);
        return 8;
    case CAPSHEET_SNAPSHOT_IMU:
        if (m->u.snapshot_imu.count == 0u || m->u.snapshot_imu.records == NULL
            || capsheet_codec_imu_record_size(m->u.snapshot_imu.format) == 0u) {
            return CAPSHEET_ERR_ARGUMENT;
        }
        put_u16(p, m->u.snapshot_imu.counter);
        put_u16(p + 2, m->u.snapshot_imu.first_link);
        p[4] = m->u.snapshot_imu.count;
        p[5] = m->u.snapshot_imu.format;
        return 6;
    case CAPSHEET_SYNC:
        put_u16(p, m->u.sync.counter);
        return 2;
    case CAPSHEET_ASSIGN:
        put_u16(p, m->u.assign.new_node);
        put_u16(p + 2, m->u.assign.link);
        put_u32(p + 4, m->u.assign.uid_low);
        return 8;
    case CAPSHEET_CONFIG:
        put_u16(p, m->u.config.rate_hz);
        p[2] = m->u.config.range;
        p[3] = m->u.config.filter;
        put_u16(p + 4, m->u.config.heartbeat_ms);
        return 6;
    case CAPSHEET_START:
    case CAPSHEET_STOP:
    case CAPSHEET_GET_INFO:
    case CAPSHEET_RESET:
        return 0;
    case CAPSHEET_CAL_READ:
        p[0] = m->u.cal_read.axis;
        return 1;
    case CAPSHEET_CONFIG_IMU:
        p[0] = m->u.config_imu.format;
        p[1] = m->u.config_imu.gyro_range;
        p[2] = m->u.config_imu.mag_range;
        p[3] = m->u.config_imu.flags;
        return 4;
    default:
        return CAPSHEET_ERR_UNKNOWN_TYPE;
    }
}
#endif

/* Encode the fixed part of a payload into `p` (CAPSHEET_CODEC_FIXED_MAX bytes). Returns the number of bytes
 * written, or an error. The types a chip sends here, the others in encode_other. */
static CAPSHEET_WARN_UNUSED int32_t encode_fixed(const capsheet_msg_t *m, uint8_t *p)
{
    switch (m->type) {
    case CAPSHEET_ANNOUNCE:
        put_u32(p, (uint32_t)(m->u.announce.uid & 0xFFFFFFFFu));
        put_u32(p + 4, (uint32_t)(m->u.announce.uid >> 32));
        return 8;
    case CAPSHEET_INFO:
        p[0] = m->u.info.fw_major;
        p[1] = m->u.info.fw_minor;
        p[2] = m->u.info.fw_patch;
        p[3] = m->u.info.protocol_version;
        put_u16(p + 4, m->u.info.capabilities);
        p[6] = m->u.info.adc_bits;
        p[7] = m->u.info.state;
        return 8;
    case CAPSHEET_SAMPLE:
        put_u16(p, m->u.sample.counter);
        put_sample_word(p + 2, m->u.sample.x, m->u.sample.y, m->u.sample.z, m->u.sample.status);
        return 7;
    case CAPSHEET_STATUS:
        p[0] = m->u.status.state;
        p[1] = m->u.status.flags;
        p[2] = m->u.status.rx_errors;
        p[3] = m->u.status.missed_syncs;
        put_u32(p + 4, m->u.status.uptime_s);
        return 8;
    case CAPSHEET_ACK:
        p[0] = m->u.ack.command;
        p[1] = m->u.ack.detail;
        return 2;
    case CAPSHEET_NACK:
        p[0] = m->u.nack.command;
        p[1] = m->u.nack.reason;
        return 2;
    case CAPSHEET_CAL_DATA:
        put_cal(p, &m->u.cal);
        return 8;
    case CAPSHEET_CAL_IMU_DATA:
        put_cal_imu(p, m);
        return 8;
    case CAPSHEET_IMU_GYRO:
    case CAPSHEET_IMU_MAG:  /* the same layout: imu_gyro and imu_mag share their members' types (C99 6.5.2.3) */
        put_u16(p, m->u.imu_gyro.counter);
        put_i16x3(p + 2, m->u.imu_gyro.gx, m->u.imu_gyro.gy, m->u.imu_gyro.gz);
        return 8;
    case CAPSHEET_IMU_ACCEL:
        p[0] = m->u.imu_accel.counter_lo;
        put_word_time(p + 1, m->u.imu_accel.x, m->u.imu_accel.y, m->u.imu_accel.z, m->u.imu_accel.status,
                      m->u.imu_accel.time_us);
        return 8;
    case CAPSHEET_IMU_SAMPLE: {
        const size_t rec = capsheet_codec_imu_record_size(m->u.imu_sample.format);
        if (rec == 0u) {
            return CAPSHEET_ERR_ARGUMENT;
        }
        put_u16(p, m->u.imu_sample.counter);
        put_word_time(p + 2, m->u.imu_sample.x, m->u.imu_sample.y, m->u.imu_sample.z, m->u.imu_sample.status,
                      m->u.imu_sample.time_us);
        put_i16x3(p + 9, m->u.imu_sample.gx, m->u.imu_sample.gy, m->u.imu_sample.gz);
        if (rec == CAPSHEET_IMU9_RECORD_SIZE) {
            put_i16x3(p + 15, m->u.imu_sample.mx, m->u.imu_sample.my, m->u.imu_sample.mz);
        }
        return (int32_t)(2u + rec);
    }
    default:
#if CAPSHEET_CHIP_ONLY
        return CAPSHEET_ERR_UNKNOWN_TYPE;
#else
        return encode_other(m, p);
#endif
    }
}

/* The payload as (fixed part in `tmp`, SNAPSHOT words / SNAPSHOT_IMU records) spans; returns the
 * payload length. */
CAPSHEET_WARN_UNUSED int32_t capsheet_codec_payload_spans(const capsheet_msg_t *m, uint8_t tmp[CAPSHEET_CODEC_FIXED_MAX], span_t sp[2])
{
    const int32_t n = encode_fixed(m, tmp);
    if (n < 0) {
        return n;
    }
    sp[0].p = tmp;
    sp[0].n = (size_t)n;
    sp[1].p = NULL;
    sp[1].n = 0;
#if !CAPSHEET_CHIP_ONLY
    if (m->type == CAPSHEET_SNAPSHOT) {
        sp[1].p = m->u.snapshot.words;
        sp[1].n = (size_t)m->u.snapshot.count * CAPSHEET_SAMPLE_WORD_SIZE;
    } else if (m->type == CAPSHEET_SNAPSHOT_IMU) {
        sp[1].p = m->u.snapshot_imu.records;
        sp[1].n = (size_t)m->u.snapshot_imu.count * capsheet_codec_imu_record_size(m->u.snapshot_imu.format);
    }
#endif
    return (int32_t)(sp[0].n + sp[1].n);
}

int32_t capsheet_payload_encode(const capsheet_msg_t *msg, uint8_t *buf, size_t cap)
{
    uint8_t tmp[CAPSHEET_CODEC_FIXED_MAX];
    span_t sp[2];
    int32_t n;
    CAPSHEET_ASSERT(msg != NULL && (buf != NULL || cap == 0));
    n = capsheet_codec_payload_spans(msg, tmp, sp);
    if (n < 0) {
        return n;
    }
    if ((size_t)n > cap) {
        return CAPSHEET_ERR_CAPACITY;
    }
    if (sp[0].n) {
        memcpy(buf, sp[0].p, sp[0].n);
    }
    if (sp[1].n) {
        memcpy(buf + sp[0].n, sp[1].p, sp[1].n);
    }
    return n;
}

/* §17.1: block 0..4, index within the block */
static bool cal_imu_element_ok(uint8_t block, uint8_t index)
{
    return block <= 4u && index < ((block == 1u || block == 4u) ? 3u : 9u);
}

/* §17.1: CAL_IMU_DATA / CAL_IMU_WRITE fields; the value finite (exponent not all ones) */
static int32_t get_cal_imu(const uint8_t *p, capsheet_msg_t *out)
{
    const uint32_t bits = get_u32(p + 4);
    out->u.cal_imu.block = p[0];
    out->u.cal_imu.index = p[1];
    out->u.cal_imu.flags = p[2];
    out->u.cal_imu.reserved = p[3];
    out->u.cal_imu.value = bits_float(bits);
    return (cal_imu_element_ok(p[0], p[1]) && p[3] == 0u && (bits & 0x7F800000u) != 0x7F800000u)
               ? 0 : CAPSHEET_ERR_BAD_FIELD;
}

static bool sensitivity_ok(uint32_t bits)
{
    /* finite and > 0: sign clear, exponent not all ones, not +0 (no float arithmetic needed) */
    return bits != 0u && bits < 0x7F800000u;
}

static void get_cal(const uint8_t *p, capsheet_cal_t *c)
{
    c->axis = p[0];
    c->flags = p[1];
    c->offset_q4 = (int16_t)get_u16(p + 2);
    c->sensitivity = bits_float(get_u32(p + 4));
}

#if !CAPSHEET_CHIP_ONLY
/* The node -> host payloads (0x01..0x0F): what a host or gateway decodes; a chip ignores them (§8.1). */
static CAPSHEET_WARN_UNUSED int32_t decode_node_payload(uint8_t type, const uint8_t *p, size_t len, capsheet_msg_t *out)
{
    if (type == CAPSHEET_IMU_SAMPLE) {  /* §16.3: the length says the format */
        const uint8_t format = (len == 2u + CAPSHEET_IMU6_RECORD_SIZE)   ? CAPSHEET_IMU_FORMAT_6AXIS
                               : (len == 2u + CAPSHEET_IMU9_RECORD_SIZE) ? CAPSHEET_IMU_FORMAT_9AXIS : 0u;
        if (format == 0u) {
            return CAPSHEET_ERR_BAD_LENGTH;
        }
        out->u.imu_sample.format = format;
        out->u.imu_sample.counter = get_u16(p);
        get_sample_word(p + 2, &out->u.imu_sample.x, &out->u.imu_sample.y, &out->u.imu_sample.z,
                        &out->u.imu_sample.status);
        out->u.imu_sample.time_us = (int16_t)get_u16(p + 7);
        get_i16x3(p + 9, &out->u.imu_sample.gx, &out->u.imu_sample.gy, &out->u.imu_sample.gz);
        if (format == CAPSHEET_IMU_FORMAT_9AXIS) {
            get_i16x3(p + 15, &out->u.imu_sample.mx, &out->u.imu_sample.my, &out->u.imu_sample.mz);
        } else {
            out->u.imu_sample.mx = out->u.imu_sample.my = out->u.imu_sample.mz = 0;
        }
        return 0;
    }
    if (type == CAPSHEET_SNAPSHOT_IMU) {  /* §16.5: the format before the length it implies */
        size_t rec;
        if (len < CAPSHEET_SNAPSHOT_IMU_HEADER_SIZE) {
            return CAPSHEET_ERR_BAD_LENGTH;
        }
        out->u.snapshot_imu.counter = get_u16(p);
        out->u.snapshot_imu.first_link = get_u16(p + 2);
        out->u.snapshot_imu.count = p[4];
        out->u.snapshot_imu.format = p[5];
        out->u.snapshot_imu.records = p + CAPSHEET_SNAPSHOT_IMU_HEADER_SIZE;
        rec = capsheet_codec_imu_record_size(p[5]);
        if (rec == 0u) {
            return CAPSHEET_ERR_BAD_FIELD;
        }
        if (p[4] == 0u || len != CAPSHEET_SNAPSHOT_IMU_HEADER_SIZE + rec * (size_t)p[4]) {
            return CAPSHEET_ERR_BAD_LENGTH;
        }
        return ((uint32_t)out->u.snapshot_imu.first_link + p[4] > 0x10000u) ? CAPSHEET_ERR_BAD_FIELD : 0;
    }
    if (type == CAPSHEET_SNAPSHOT) {
        size_t count;
        if (len < CAPSHEET_SNAPSHOT_HEADER_SIZE + CAPSHEET_SAMPLE_WORD_SIZE) {
            return CAPSHEET_ERR_BAD_LENGTH;
        }
        count = p[4];
        if (len != CAPSHEET_SNAPSHOT_HEADER_SIZE + CAPSHEET_SAMPLE_WORD_SIZE * count) {
            return CAPSHEET_ERR_BAD_LENGTH;
        }
        out->u.snapshot.counter = get_u16(p);
        out->u.snapshot.first_link = get_u16(p + 2);
        out->u.snapshot.count = p[4];
        out->u.snapshot.words = p + CAPSHEET_SNAPSHOT_HEADER_SIZE;
        /* count >= 1 here (len >= 10); first_link + count must not pass 65536 */
        return ((uint32_t)out->u.snapshot.first_link + count > 0x10000u) ? CAPSHEET_ERR_BAD_FIELD : 0;
    }
    if (len != k_size[type]) {
        return CAPSHEET_ERR_BAD_LENGTH;
    }
    switch (type) {
    case CAPSHEET_ANNOUNCE:
        out->u.announce.uid = (uint64_t)get_u32(p) | ((uint64_t)get_u32(p + 4) << 32);
        return 0;
    case CAPSHEET_INFO:
        out->u.info.fw_major = p[0];
        out->u.info.fw_minor = p[1];
        out->u.info.fw_patch = p[2];
        out->u.info.protocol_version = p[3];
        out->u.info.capabilities = get_u16(p + 4);
        out->u.info.adc_bits = p[6];
        out->u.info.state = p[7];
        return (p[7] < CAPSHEET_STATE_COUNT) ? 0 : CAPSHEET_ERR_BAD_FIELD;
    case CAPSHEET_SAMPLE:
        out->u.sample.counter = get_u16(p);
        get_sample_word(p + 2, &out->u.sample.x, &out->u.sample.y, &out->u.sample.z, &out->u.sample.status);
        return 0;
    case CAPSHEET_IMU_GYRO:
    case CAPSHEET_IMU_MAG:  /* the same layout (C99 6.5.2.3: a common initial sequence) */
        out->u.imu_gyro.counter = get_u16(p);
        get_i16x3(p + 2, &out->u.imu_gyro.gx, &out->u.imu_gyro.gy, &out->u.imu_gyro.gz);
        return 0;
    case CAPSHEET_IMU_ACCEL:
        out->u.imu_accel.counter_lo = p[0];
        get_sample_word(p + 1, &out->u.imu_accel.x, &out->u.imu_accel.y, &out->u.imu_accel.z,
                        &out->u.imu_accel.status);
        out->u.imu_accel.time_us = (int16_t)get_u16(p + 6);
        return 0;
    case CAPSHEET_STATUS:
        out->u.status.state = p[0];
        out->u.status.flags = p[1];
        out->u.status.rx_errors = p[2];
        out->u.status.missed_syncs = p[3];
        out->u.status.uptime_s = get_u32(p + 4);
        return (p[0] < CAPSHEET_STATE_COUNT) ? 0 : CAPSHEET_ERR_BAD_FIELD;
    case CAPSHEET_ACK:
        out->u.ack.command = p[0];
        out->u.ack.detail = p[1];
        return 0;
    case CAPSHEET_NACK:
        out->u.nack.command = p[0];
        out->u.nack.reason = p[1];
        return (p[1] >= CAPSHEET_NACK_UNKNOWN_COMMAND && p[1] <= CAPSHEET_NACK_STORAGE_FAILED)
                   ? 0 : CAPSHEET_ERR_BAD_FIELD;
    case CAPSHEET_CAL_DATA:
        get_cal(p, &out->u.cal);
        return (p[0] <= 2u && sensitivity_ok(get_u32(p + 4))) ? 0 : CAPSHEET_ERR_BAD_FIELD;
    case CAPSHEET_CAL_IMU_DATA:
        return get_cal_imu(p, out);
    case CAPSHEET_GATEWAY_INFO:
        out->u.gateway_info.flags = p[0];
        out->u.gateway_info.sample_format = p[1];
        out->u.gateway_info.first_link = get_u16(p + 2);
        out->u.gateway_info.link_count = get_u16(p + 4);
        out->u.gateway_info.sync_rate_hz = get_u16(p + 6);
        return ((uint32_t)out->u.gateway_info.first_link + out->u.gateway_info.link_count > 0x10000u)
                   ? CAPSHEET_ERR_BAD_FIELD : 0;
    default:
        return CAPSHEET_ERR_UNKNOWN_TYPE;
    }
}
#endif

int32_t capsheet_payload_decode(uint8_t type, uint16_t node, const uint8_t *p, size_t len, capsheet_msg_t *out)
{
    CAPSHEET_ASSERT(out != NULL && (p != NULL || len == 0));
    out->type = type;
    out->node = node;
    if (!capsheet_type_known(type)) {
        return CAPSHEET_ERR_UNKNOWN_TYPE;
    }
    if (node == CAPSHEET_NODE_RESERVED) {
        return CAPSHEET_ERR_BAD_FIELD;
    }
    if (type < CAPSHEET_HOST_TYPE_FIRST) {
#if CAPSHEET_CHIP_ONLY
        return CAPSHEET_ERR_UNKNOWN_TYPE;  /* a chip build decodes no node -> host payload */
#else
        return decode_node_payload(type, p, len, out);
#endif
    }
    if (len != k_size[type]) {
        return CAPSHEET_ERR_BAD_LENGTH;
    }
    switch (type) {
    case CAPSHEET_CONFIG_IMU:
        out->u.config_imu.format = p[0];
        out->u.config_imu.gyro_range = p[1];
        out->u.config_imu.mag_range = p[2];
        out->u.config_imu.flags = p[3];
        return 0;
    case CAPSHEET_CAL_WRITE:
        get_cal(p, &out->u.cal);
        if (type == CAPSHEET_CAL_WRITE && node == CAPSHEET_NODE_BROADCAST) {
            return CAPSHEET_ERR_BAD_FIELD;
        }
        return (p[0] <= 2u && sensitivity_ok(get_u32(p + 4))) ? 0 : CAPSHEET_ERR_BAD_FIELD;
    case CAPSHEET_SYNC:
        out->u.sync.counter = get_u16(p);
        return (node == CAPSHEET_NODE_BROADCAST) ? 0 : CAPSHEET_ERR_BAD_FIELD;
    case CAPSHEET_ASSIGN:
        out->u.assign.new_node = get_u16(p);
        out->u.assign.link = get_u16(p + 2);
        out->u.assign.uid_low = get_u32(p + 4);
        return (node != CAPSHEET_NODE_BROADCAST && out->u.assign.new_node >= 1u
                && out->u.assign.new_node <= CAPSHEET_NODE_MAX_ASSIGNED) ? 0 : CAPSHEET_ERR_BAD_FIELD;
    case CAPSHEET_CONFIG:
        out->u.config.rate_hz = get_u16(p);
        out->u.config.range = p[2];
        out->u.config.filter = p[3];
        out->u.config.heartbeat_ms = get_u16(p + 4);
        return 0;
    case CAPSHEET_CAL_READ:
        out->u.cal_read.axis = p[0];
        return (node != CAPSHEET_NODE_BROADCAST && p[0] <= 2u) ? 0 : CAPSHEET_ERR_BAD_FIELD;
    case CAPSHEET_CAL_IMU_WRITE: {
        const int32_t rc = get_cal_imu(p, out);
        return (node == CAPSHEET_NODE_BROADCAST) ? CAPSHEET_ERR_BAD_FIELD : rc;
    }
    case CAPSHEET_CAL_IMU_READ:
        out->u.cal_imu_read.block = p[0];
        out->u.cal_imu_read.index = p[1];
        return (node != CAPSHEET_NODE_BROADCAST && cal_imu_element_ok(p[0], p[1])) ? 0 : CAPSHEET_ERR_BAD_FIELD;
    default:  /* START, STOP, GET_INFO, RESET: empty */
        return 0;
    }
}

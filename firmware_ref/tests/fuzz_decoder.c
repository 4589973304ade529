/*
 * fuzz_decoder.c — checks the guarantees of capsheet_fw.h against arbitrary input.
 *
 * One harness, three drivers:
 *   - libFuzzer (`make fuzz`, built with -DCAPSHEET_LIBFUZZER): LLVMFuzzerTestOneInput;
 *   - `driver --random N --seed S`: N deterministic pseudo-random inputs (raw bytes, damaged and
 *     structured frames), for the ASan/UBSan build in CI (`make asan`);
 *   - `driver FILE...`: replays a corpus; `driver --selftest`: known answers.
 *
 * Every buffer handed to the code under test is heap-allocated at its exact size, so ASan flags a
 * single byte of over-read or over-write; output buffers also get nanopb's canary: pre-filled with
 * 0xAA, and the byte after the declared capacity must still be 0xAA afterwards.
 * Properties checked beyond memory safety:
 *   - payload decode -> encode reproduces the payload byte for byte (for every accepted payload);
 *   - serial/CAN decode of an accepted frame -> encode reproduces it;
 *   - COBS decode(encode(x)) == x;
 *   - the stream decoder never holds more than its capacity;
 *   - every frame the chip sends decodes without error, and fits CAPSHEET_CHIP_TX_WIRE_SIZE;
 *     a chip with a gyroscope (and magnetometer) is driven too, and its IMU records (serial,
 *     classic CAN frames, CAN FD) decode as well.
 */
#include "capsheet_fw.h"

#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#define CHECK(cond)                                                                                \
    do {                                                                                           \
        if (!(cond)) {                                                                             \
            fprintf(stderr, "%s:%d: CHECK failed: %s\n", __FILE__, __LINE__, #cond);              \
            abort();                                                                               \
        }                                                                                          \
    } while (0)

/* ---------------------------------------------------------------------------------------- */
/* exact-size heap copies and canaries                                                       */
/* ---------------------------------------------------------------------------------------- */

static uint8_t *dup_exact(const uint8_t *p, size_t n)
{
    uint8_t *q = (uint8_t *)malloc(n ? n : 1u);
    CHECK(q != NULL);
    if (n) {
        memcpy(q, p, n);
    }
    return q;
}

/* a buffer of `cap` usable bytes + 1 canary byte, all 0xAA */
static uint8_t *canary_buf(size_t cap)
{
    uint8_t *q = (uint8_t *)malloc(cap + 1u);
    CHECK(q != NULL);
    memset(q, 0xAA, cap + 1u);
    return q;
}

/* ---------------------------------------------------------------------------------------- */
/* a fake HAL that checks everything the chip sends                                          */
/* ---------------------------------------------------------------------------------------- */

typedef struct {
    uint32_t reads;
    uint32_t sent;
    uint8_t fault_after;   /* read_axes fails from this read on (0: never) */
    capsheet_cal_t stored[3];
    uint8_t have[3];
    uint8_t store_fails;
    uint32_t imu_stored[CAPSHEET_IMU_CAL_COUNT];
    uint8_t imu_have[CAPSHEET_IMU_CAL_COUNT];
    uint32_t imu_reads;
    uint32_t imu_frames;   /* IMU_GYRO / IMU_MAG / IMU_ACCEL / IMU_SAMPLE frames sent */
} fake_t;

static int32_t fake_read_imu(void *user, uint64_t now_us, uint8_t gyro_range, uint8_t mag_range, bool want_mag,
                             capsheet_imu_reading_t *out)
{
    fake_t *f = (fake_t *)user;
    unsigned i;
    CHECK(gyro_range <= 4u && mag_range <= 3u);
    f->imu_reads++;
    for (i = 0; i < 3u; i++) {
        out->gyro[i] = (int16_t)((int32_t)((f->imu_reads * (7u + i) * 9973u) % 65536u) - 32768);
        out->mag[i] = want_mag ? (int16_t)((int32_t)(f->imu_reads * 131u % 65536u) - 32768) : 0;
    }
    out->latch_us = now_us + (f->imu_reads % 3u) * 20000u - 20000u;  /* before, at and after the SYNC */
    out->status = (uint8_t)(f->imu_reads % 5u == 4u ? CAPSHEET_SAMPLE_STALE : 0u);
    return 0;
}

static bool chip_type_ok(uint8_t type)
{
    return (type >= CAPSHEET_ANNOUNCE && type <= CAPSHEET_CAL_DATA)
           || (type >= CAPSHEET_IMU_GYRO && type <= CAPSHEET_IMU_SAMPLE);
}

static int32_t fake_read_axes(void *user, uint64_t now_us, int16_t xyz[3], uint8_t *status)
{
    fake_t *f = (fake_t *)user;
    f->reads++;
    (void)now_us;
    xyz[0] = (int16_t)((int32_t)(f->reads * 37u % 4096u) - 2048);
    xyz[1] = (int16_t)((int32_t)(f->reads * 11u % 4096u) - 2048);
    xyz[2] = 1024;
    *status = (uint8_t)(f->reads % 16u);
    return (f->fault_after && f->reads >= f->fault_after) ? -1 : 0;
}

static int32_t fake_send_bytes(void *user, const uint8_t *data, size_t len)
{
    fake_t *f = (fake_t *)user;
    uint8_t *copy;
    capsheet_msg_t m;
    CHECK(len >= 2u && len <= CAPSHEET_CHIP_TX_WIRE_SIZE);
    CHECK(data[len - 1u] == 0u);
    copy = dup_exact(data, len - 1u);
    CHECK(capsheet_serial_decode_frame(copy, len - 1u, &m, NULL) == 0);
    CHECK(chip_type_ok(m.type) && m.type != CAPSHEET_IMU_GYRO && m.type != CAPSHEET_IMU_MAG
          && m.type != CAPSHEET_IMU_ACCEL);
    f->imu_frames += m.type == CAPSHEET_IMU_SAMPLE;
    free(copy);
    f->sent++;
    return 0;
}

static int32_t fake_send_can(void *user, uint32_t id, const uint8_t *data, uint8_t len, bool is_fd)
{
    fake_t *f = (fake_t *)user;
    capsheet_msg_t m;
    uint8_t *copy = dup_exact(data, len);
    CHECK(len <= (is_fd ? 24u : 8u));
    CHECK(capsheet_can_decode(id, true, is_fd, copy, len, &m, NULL) == 0);
    CHECK(chip_type_ok(m.type) && is_fd == (m.type == CAPSHEET_IMU_SAMPLE));
    f->imu_frames += m.type >= CAPSHEET_IMU_GYRO && m.type <= CAPSHEET_IMU_SAMPLE;
    free(copy);
    f->sent++;
    return 0;
}

static uint64_t fake_uid(void *user)
{
    (void)user;
    return 0x0123456789ABCDEFull;
}

static int32_t fake_cal_load(void *user, uint8_t axis, capsheet_cal_t *cal)
{
    fake_t *f = (fake_t *)user;
    CHECK(axis < 3u);
    if (!f->have[axis]) {
        return -1;
    }
    *cal = f->stored[axis];
    return 0;
}

static int32_t fake_cal_store(void *user, uint8_t axis, const capsheet_cal_t *cal)
{
    fake_t *f = (fake_t *)user;
    CHECK(axis < 3u && cal->axis == axis);
    if (f->store_fails) {
        return -1;
    }
    f->stored[axis] = *cal;
    f->have[axis] = 1;
    return 0;
}

static int32_t fake_cal_imu_load(void *user, uint8_t element, uint32_t *bits)
{
    fake_t *f = (fake_t *)user;
    CHECK(element < CAPSHEET_IMU_CAL_COUNT);
    if (!f->imu_have[element]) {
        return -1;
    }
    *bits = f->imu_stored[element];
    return 0;
}

static int32_t fake_cal_imu_store(void *user, uint8_t element, uint32_t bits)
{
    fake_t *f = (fake_t *)user;
    CHECK(element < CAPSHEET_IMU_CAL_COUNT);
    if (f->store_fails) {
        return -1;
    }
    f->imu_stored[element] = bits;
    f->imu_have[element] = 1;
    return 0;
}

static void make_hal(capsheet_hal_t *hal, fake_t *f)
{
    memset(hal, 0, sizeof *hal);
    memset(f, 0, sizeof *f);
    hal->user = f;
    hal->read_axes = fake_read_axes;
    hal->send_bytes = fake_send_bytes;
    hal->send_can = fake_send_can;
    hal->read_uid = fake_uid;
    hal->cal_load = fake_cal_load;
    hal->cal_store = fake_cal_store;
    hal->read_imu = fake_read_imu;
    hal->cal_imu_load = fake_cal_imu_load;
    hal->cal_imu_store = fake_cal_imu_store;
}

/* ---------------------------------------------------------------------------------------- */
/* the properties                                                                            */
/* ---------------------------------------------------------------------------------------- */

static void check_payload_roundtrip(uint8_t type, uint16_t node, const uint8_t *data, size_t len)
{
    uint8_t *in = dup_exact(data, len);
    capsheet_msg_t m;
    if (capsheet_payload_decode(type, node, in, len, &m) == 0) {
        uint8_t *out = canary_buf(len);
        int32_t n = capsheet_payload_encode(&m, out, len);
        CHECK(n == (int32_t)len);
        CHECK(memcmp(out, in, len) == 0);
        CHECK(out[len] == 0xAA);
        if (len > 0u) {  /* one byte short: CAPACITY, and nothing written past the capacity */
            memset(out, 0xAA, len + 1u);
            CHECK(capsheet_payload_encode(&m, out, len - 1u) == CAPSHEET_ERR_CAPACITY);
            CHECK(out[len - 1u] == 0xAA);
        }
        free(out);
    }
    free(in);
}

static void check_serial_frame(const uint8_t *data, size_t len)
{
    uint8_t *frame = dup_exact(data, len);
    capsheet_msg_t m;
    uint8_t version = 0;
    int32_t rc = capsheet_serial_decode_frame(frame, len, &m, &version);
    CHECK(rc <= 0 && rc >= CAPSHEET_ERR_BAD_FIELD);
    if (rc == 0) {
        /* re-encoding gives back the same wire bytes */
        uint8_t *out = canary_buf(len + 1u);
        int32_t n = capsheet_serial_encode(&m, out, len + 1u);
        CHECK(n == (int32_t)len + 1);
        CHECK(memcmp(out, data, len) == 0 && out[len] == 0u);
        CHECK(out[len + 1u] == 0xAA);
        free(out);
    }
    free(frame);
}

static void check_cobs(const uint8_t *data, size_t len, size_t cap)
{
    uint8_t *in = dup_exact(data, len);
    uint8_t *out = canary_buf(cap);
    int32_t n = capsheet_cobs_decode(in, len, out, cap);
    CHECK(out[cap] == 0xAA);
    CHECK(n < 0 || (size_t)n <= cap);
    free(out);
    /* encode: into a buffer of exactly the worst case, then decode back */
    {
        const size_t ecap = CAPSHEET_COBS_ENCODED_SIZE(len);
        uint8_t *enc = canary_buf(ecap);
        uint8_t *dec;
        int32_t e = capsheet_cobs_encode(in, len, enc, ecap), d;
        size_t k;
        CHECK(e > 0 && (size_t)e <= ecap && enc[ecap] == 0xAA);
        for (k = 0; k < (size_t)e; k++) {
            CHECK(enc[k] != 0u);
        }
        dec = canary_buf(len);
        d = capsheet_cobs_decode(enc, (size_t)e, dec, len);
        CHECK(d == (int32_t)len && (len == 0 || memcmp(dec, in, len) == 0) && dec[len] == 0xAA);
        /* too small an output buffer: CAPACITY, canary intact */
        if (e > 1) {
            memset(enc, 0xAA, ecap + 1u);
            CHECK(capsheet_cobs_encode(in, len, enc, (size_t)e - 1u) == CAPSHEET_ERR_CAPACITY);
            CHECK(enc[e - 1] == 0xAA);
        }
        free(dec);
        free(enc);
    }
    free(in);
}

static void check_stream(const uint8_t *data, size_t len, size_t cap)
{
    uint8_t *buf = canary_buf(cap);
    capsheet_stream_t s;
    size_t i;
    CHECK(capsheet_stream_init(&s, buf, cap) == 0);
    for (i = 0; i < len; i++) {
        capsheet_msg_t m;
        int32_t rc = capsheet_stream_feed(&s, data[i], &m);
        CHECK(rc <= 1 && rc >= CAPSHEET_ERR_BAD_FIELD);
        CHECK(s.len <= s.cap);
        CHECK(buf[cap] == 0xAA);
    }
    free(buf);
}

static void check_can(const uint8_t *data, size_t len)
{
    uint32_t id;
    uint8_t flags, n;
    uint8_t *payload;
    capsheet_msg_t m;
    int32_t rc;
    if (len < 5u) {
        return;
    }
    id = (uint32_t)data[0] | ((uint32_t)data[1] << 8) | ((uint32_t)data[2] << 16) | ((uint32_t)data[3] << 24);
    flags = data[4];
    if (flags & 4u) {
        id &= 0x1FFFFFFFu;
        id = (id & ~(0xFu << 16)) | (CAPSHEET_PROTOCOL_VERSION << 16);
    }
    n = (uint8_t)((len - 5u) > 64u ? 64u : (len - 5u));
    payload = dup_exact(data + 5, n);
    rc = capsheet_can_decode(id, (flags & 1u) != 0u, (flags & 2u) != 0u, payload, n, &m, NULL);
    CHECK(rc <= 0 && rc >= CAPSHEET_ERR_BAD_FIELD);
    if (rc == 0) {
        uint8_t *out = canary_buf(64);
        uint32_t id2;
        bool fd2;
        int32_t k = capsheet_can_encode(&m, (flags & 2u) ? CAPSHEET_CAN_FD : CAPSHEET_CAN_CLASSIC, &id2, out, 64, &fd2);
        CHECK(out[64] == 0xAA);
        CHECK(k == (int32_t)n && memcmp(out, payload, n) == 0);
        /* every bit below the priority: type[25:20], version[19:16], node[15:0] (priority bits may
         * differ: receivers accept any, the encoder uses the table's) */
        CHECK((id2 & 0x03FFFFFFu) == (id & 0x03FFFFFFu));
        free(out);
    }
    free(payload);
}

/* Feed bytes to a serial chip and CAN chip, with polls in between. */
static void check_chips_raw(const uint8_t *data, size_t len)
{
    capsheet_hal_t hal;
    fake_t f;
    capsheet_chip_t chip;
    capsheet_chip_config_t cfg;
    uint8_t *rx = canary_buf(CAPSHEET_MIN_RX_BUFFER_SIZE);
    uint8_t *copy = dup_exact(data, len);
    make_hal(&hal, &f);
    cfg.transport = CAPSHEET_TRANSPORT_SERIAL;
    cfg.can_fd = false;
    cfg.capabilities = CAPSHEET_CAP_CAL_STORAGE;
    CHECK(capsheet_chip_init(&chip, &cfg, &hal, rx, CAPSHEET_MIN_RX_BUFFER_SIZE) == 0);
    CHECK(capsheet_chip_power_on(&chip, 0) == 2);
    CHECK(capsheet_chip_rx_bytes(&chip, copy, len, 1000) >= 0);
    CHECK(capsheet_chip_poll(&chip, 5000000) >= 0);
    CHECK(rx[CAPSHEET_MIN_RX_BUFFER_SIZE] == 0xAA);
    free(copy);
    free(rx);
}

/* Structured: the input is a script of host frames, so the fuzzer reaches every state.
 * Each step: [op][node sel][type][len][payload...]. */
static void check_chip_script(const uint8_t *data, size_t len, capsheet_transport_t transport)
{
    capsheet_hal_t hal;
    fake_t f;
    capsheet_chip_t chip;
    capsheet_chip_config_t cfg;
    uint8_t *rx = canary_buf(CAPSHEET_RX_BUFFER_SIZE);
    size_t i = 0;
    uint64_t now = 0;
    make_hal(&hal, &f);
    f.fault_after = (len > 0u && (data[0] & 1u)) ? (uint8_t)(data[0] >> 1) : 0u;
    cfg.transport = transport;
    cfg.can_fd = (len > 1u) && (data[1] & 1u);
    cfg.capabilities = (uint16_t)(len > 1u ? ((data[1] >> 1) & 0x3Fu) : 0u);
    if (len > 1u && (data[1] & 0x80u)) {  /* a 6-axis chip, 9-axis when data[0] bit 1 is set too */
        cfg.capabilities = (uint16_t)(cfg.capabilities | CAPSHEET_CAP_GYRO | CAPSHEET_CAP_SAMPLE_TIME
                                      | ((data[0] & 2u) ? CAPSHEET_CAP_MAG : 0u));
    }
    if (!(cfg.capabilities & CAPSHEET_CAP_CAL_STORAGE)) {
        hal.cal_load = NULL;
        hal.cal_store = NULL;
        hal.cal_imu_load = NULL;
        hal.cal_imu_store = NULL;
    }
    CHECK(capsheet_chip_init(&chip, &cfg, &hal, rx, CAPSHEET_RX_BUFFER_SIZE) == 0);
    CHECK(capsheet_chip_power_on(&chip, 0) == 2);
    i = 2;
    while (i + 4u <= len) {
        const uint8_t op = data[i], sel = data[i + 1], type = data[i + 2];
        size_t plen = data[i + 3];
        uint16_t node;
        uint8_t frame[CAPSHEET_MAX_WIRE_SIZE];
        i += 4;
        if (plen > len - i) {
            plen = len - i;
        }
        node = (sel % 4u == 0u) ? 0u : (sel % 4u == 1u) ? chip.node : (uint16_t)(sel * 257u);
        now += (uint64_t)(op >> 2) * 50000u;
        if (transport == CAPSHEET_TRANSPORT_SERIAL) {
            const uint8_t version = (op & 1u) ? (uint8_t)(op >> 4) : (uint8_t)CAPSHEET_PROTOCOL_VERSION;
            int32_t n = capsheet_serial_encode_raw(version, type, node, data + i, plen, frame, sizeof frame);
            CHECK(n > 0);
            if (op & 2u) {
                frame[(size_t)op % (size_t)n] ^= (uint8_t)(sel | 1u);  /* damage */
            }
            CHECK(capsheet_chip_rx_bytes(&chip, frame, (size_t)n, now) >= 0);
        } else {
            const uint32_t id = capsheet_can_make_id(op & 7u, type, (op & 1u) ? (uint8_t)(op >> 4) : 1u, node);
            uint8_t *p = dup_exact(data + i, plen > 64u ? 64u : plen);
            CHECK(capsheet_chip_rx_can(&chip, id, (op & 2u) == 0u, (op & 8u) != 0u, p, plen > 64u ? 64u : plen, now) >= 0);
            free(p);
        }
        CHECK(capsheet_chip_poll(&chip, now) >= 0);
        CHECK(chip.state < CAPSHEET_STATE_COUNT);
        CHECK(chip.state == CAPSHEET_BOOT ? chip.node >= CAPSHEET_NODE_PROVISIONAL_MIN
                                          : (chip.node >= 1u && chip.node <= CAPSHEET_NODE_MAX_ASSIGNED));
        i += plen;
    }
    CHECK(rx[CAPSHEET_RX_BUFFER_SIZE] == 0xAA);
    free(rx);
}

static int fuzz_one(const uint8_t *data, size_t size)
{
    static const size_t caps[4] = {1, CAPSHEET_MIN_RX_BUFFER_SIZE, 64, CAPSHEET_MAX_ENCODED_SIZE};
    size_t cap = caps[size ? data[0] % 4u : 0u];
    if (size > 4096u) {
        return 0;
    }
    check_serial_frame(data, size);
    check_stream(data, size, cap);
    check_cobs(data, size, size ? (size_t)data[size - 1] * 5u % (size + 1u) : 0u);
    check_can(data, size);
    if (size >= 2u) {
        const uint16_t node = (uint16_t)(data[1] * 0x0101u);
        check_payload_roundtrip(data[0] % 0x1Au, node, data + 2, size - 2u);
        check_payload_roundtrip((uint8_t)(data[0] % 0x1Au), (uint16_t)(node & 7u), data + 2, size - 2u);
    }
    check_chips_raw(data, size);
    check_chip_script(data, size, CAPSHEET_TRANSPORT_SERIAL);
    check_chip_script(data, size, CAPSHEET_TRANSPORT_CAN);
    return 0;
}

#ifdef CAPSHEET_LIBFUZZER
int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size);
int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size) { return fuzz_one(data, size); }
#else

/* ---------------------------------------------------------------------------------------- */
/* deterministic drivers                                                                     */
/* ---------------------------------------------------------------------------------------- */

static uint64_t rng_state;

static uint32_t rng(void)
{
    /* xorshift64* */
    rng_state ^= rng_state >> 12;
    rng_state ^= rng_state << 25;
    rng_state ^= rng_state >> 27;
    return (uint32_t)((rng_state * 0x2545F4914F6CDD1Dull) >> 32);
}

static void random_input(uint8_t *buf, size_t *len)
{
    const uint32_t kind = rng() % 4u;
    size_t n = rng() % 64u, i;
    if (rng() % 50u == 0u) {
        n = rng() % 2100u;
    }
    for (i = 0; i < n; i++) {
        buf[i] = (uint8_t)rng();
    }
    if (kind == 1u && n > 0u) {  /* a valid serial frame, maybe damaged */
        uint8_t payload[64];
        int32_t k;
        for (i = 0; i < sizeof payload; i++) {
            payload[i] = (uint8_t)rng();
        }
        k = capsheet_serial_encode_raw(1, (uint8_t)(rng() % 0x1Au), (uint16_t)rng(), payload, rng() % 12u, buf, 2100);
        CHECK(k > 0);
        n = (size_t)k - 1u;  /* without the delimiter */
        if (rng() % 2u) {
            buf[rng() % n] ^= (uint8_t)(1u << (rng() % 8u));
        }
    } else if (kind == 2u) {  /* sparse zeros: long COBS runs */
        for (i = 0; i < n; i++) {
            buf[i] = (uint8_t)(buf[i] | 1u);
        }
    }
    *len = n;
}

/* A 9-axis chip on each transport through CONFIG_IMU and START: one SYNC gives the record's frames. */
static void selftest_imu(capsheet_transport_t transport, uint8_t flags, int32_t frames)
{
    capsheet_hal_t hal;
    fake_t f;
    capsheet_chip_t chip;
    capsheet_chip_config_t cfg;
    capsheet_msg_t m;
    uint8_t *rx = canary_buf(CAPSHEET_RX_BUFFER_SIZE);
    uint8_t buf[64];
    uint32_t id;
    bool fd;
    int32_t n;
    uint16_t node;
    unsigned step;
    make_hal(&hal, &f);
    cfg.transport = transport;
    cfg.can_fd = true;
    cfg.capabilities = CAPSHEET_CAP_GYRO | CAPSHEET_CAP_MAG | CAPSHEET_CAP_SAMPLE_TIME;
    CHECK(capsheet_chip_init(&chip, &cfg, &hal, rx, CAPSHEET_RX_BUFFER_SIZE) == 0);
    CHECK(capsheet_chip_power_on(&chip, 0) == 2);
    node = chip.node;
    for (step = 0; step < 4u; step++) {
        memset(&m, 0, sizeof m);
        m.node = (step == 0u) ? node : 7u;
        if (step == 0u) {
            m.type = CAPSHEET_ASSIGN;
            m.u.assign.new_node = 7;
            m.u.assign.uid_low = 0x89ABCDEFu;
        } else if (step == 1u) {
            m.type = CAPSHEET_CONFIG_IMU;
            m.u.config_imu.format = CAPSHEET_IMU_FORMAT_9AXIS;
            m.u.config_imu.gyro_range = 4;
            m.u.config_imu.flags = flags;
        } else if (step == 2u) {
            m.type = CAPSHEET_START;
        } else {
            m.type = CAPSHEET_SYNC;
            m.node = 0;
            m.u.sync.counter = 0x0102;
        }
        if (transport == CAPSHEET_TRANSPORT_SERIAL) {
            n = capsheet_serial_encode(&m, buf, sizeof buf);
            CHECK(n > 0);
            n = capsheet_chip_rx_bytes(&chip, buf, (size_t)n, 1000u * (step + 1u));
        } else {
            n = capsheet_can_encode(&m, CAPSHEET_CAN_CLASSIC, &id, buf, sizeof buf, &fd);
            CHECK(n >= 0);
            n = capsheet_chip_rx_can(&chip, id, true, false, buf, (size_t)n, 1000u * (step + 1u));
        }
        CHECK(n == (step == 3u ? frames : 1));
    }
    CHECK(f.imu_reads == 1u && f.imu_frames == (uint32_t)frames && chip.state == CAPSHEET_STREAMING);
    free(rx);
}

static int selftest(void)
{
    static const uint8_t check[] = {'1', '2', '3', '4', '5', '6', '7', '8', '9'};
    /* tests/vectors/serial.json "sample_flat" */
    static const uint8_t sample_flat[] = {0x04, 0x01, 0x03, 0x01, 0x01, 0x01, 0x01, 0x01,
                                          0x01, 0x01, 0x04, 0x04, 0x16, 0x2e, 0x00};
    capsheet_msg_t m;
    uint8_t buf[64], *out;
    int32_t n;
    CHECK(capsheet_crc16(check, sizeof check, CAPSHEET_CRC_INIT) == 0x29B1u);
    CHECK(capsheet_provisional_node(0x0123456789ABCDEFull, 0) == 0x9112u);
    memset(&m, 0, sizeof m);
    m.type = CAPSHEET_SAMPLE;
    m.node = 1;
    m.u.sample.z = 1024;
    n = capsheet_serial_encode(&m, buf, sizeof buf);
    CHECK(n == (int32_t)sizeof sample_flat);
    CHECK(memcmp(buf, sample_flat, (size_t)n) == 0);
    /* exact capacity works, one less fails without writing past it */
    out = canary_buf((size_t)n);
    CHECK(capsheet_serial_encode(&m, out, (size_t)n) == n && out[n] == 0xAA);
    memset(out, 0xAA, (size_t)n + 1u);
    CHECK(capsheet_serial_encode(&m, out, (size_t)n - 1u) == CAPSHEET_ERR_CAPACITY && out[n - 1] == 0xAA);
    free(out);
    CHECK(capsheet_serial_decode_frame(buf, (size_t)n - 1u, &m, NULL) == 0);
    CHECK(m.type == CAPSHEET_SAMPLE && m.node == 1u && m.u.sample.z == 1024);
    fuzz_one(sample_flat, sizeof sample_flat);
    selftest_imu(CAPSHEET_TRANSPORT_SERIAL, 0, 1);
    selftest_imu(CAPSHEET_TRANSPORT_CAN, 0, 3);
    selftest_imu(CAPSHEET_TRANSPORT_CAN, CAPSHEET_IMU_FLAG_FD, 1);
    printf("selftest: ok (%u-bit)\n", (unsigned)(sizeof(void *) * 8u));
    return 0;
}

static int replay(const char *path)
{
    FILE *fp = fopen(path, "rb");
    static uint8_t buf[8192];
    size_t n;
    if (fp == NULL) {
        fprintf(stderr, "cannot open %s\n", path);
        return 1;
    }
    n = fread(buf, 1, sizeof buf, fp);
    fclose(fp);
    fuzz_one(buf, n);
    return 0;
}

int main(int argc, char **argv)
{
    int i, files = 0;
    for (i = 1; i < argc; i++) {
        if (strcmp(argv[i], "--selftest") == 0) {
            if (selftest() != 0) {
                return 1;
            }
        } else if (strcmp(argv[i], "--random") == 0 && i + 1 < argc) {
            unsigned long count = strtoul(argv[++i], NULL, 10), k;
            uint64_t seed = 1;
            static uint8_t buf[2200];
            if (i + 2 < argc && strcmp(argv[i + 1], "--seed") == 0) {
                seed = strtoull(argv[i + 2], NULL, 10);
                i += 2;
            }
            rng_state = seed * 0x9E3779B97F4A7C15ull + 1u;
            for (k = 0; k < count; k++) {
                size_t n;
                random_input(buf, &n);
                fuzz_one(buf, n);
            }
            printf("random: %lu inputs ok\n", count);
        } else {
            if (replay(argv[i]) != 0) {
                return 1;
            }
            files++;
        }
    }
    if (files) {
        printf("replay: %d files ok\n", files);
    }
    return 0;
}
#endif

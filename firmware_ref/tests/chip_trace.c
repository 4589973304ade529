/*
 * chip_trace.c — prints every frame a chip sends for a deterministic pseudo-random script of host
 * frames, so two builds can be compared byte for byte (`make check`: the default build and
 * -DCAPSHEET_CHIP_ONLY=1 must print the same trace; README.md "Build options").
 *
 * The script (xorshift, seed from argv): ASSIGN to the chip's current id, CONFIG, CONFIG_IMU of every
 * kind (valid and not, FD flag), START, STOP, SYNC runs, GET_INFO, RESET, CAL_READ, another node's
 * frames (node -> host types too: SAMPLE, IMU_SAMPLE, SNAPSHOT, padded FD frames), random types and
 * payloads, damaged serial frames, polls — on a 9-axis chip and a 6-axis chip, over serial and CAN
 * (classic and FD). Frames are built raw (capsheet_serial_encode_raw, raw CAN data): the encoders of
 * host types are not in a CAPSHEET_CHIP_ONLY build.
 */
#include "capsheet_fw.h"

#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static uint64_t rng_state;
static unsigned long frames_out;

static uint32_t rng(void)
{
    rng_state ^= rng_state >> 12;
    rng_state ^= rng_state << 25;
    rng_state ^= rng_state >> 27;
    return (uint32_t)((rng_state * 0x2545F4914F6CDD1Dull) >> 32);
}

static void print_hex(const char *tag, uint32_t id, const uint8_t *data, size_t len)
{
    size_t i;
    printf("%s %08lx ", tag, (unsigned long)id);
    for (i = 0; i < len; i++) {
        printf("%02x", data[i]);
    }
    printf("\n");
    frames_out++;
}

static uint32_t reads;

static int32_t read_axes(void *user, uint64_t now_us, int16_t xyz[3], uint8_t *status)
{
    (void)user;
    (void)now_us;
    reads++;
    xyz[0] = (int16_t)((int32_t)(reads * 37u % 4096u) - 2048);
    xyz[1] = (int16_t)((int32_t)(reads * 11u % 4096u) - 2048);
    xyz[2] = 1024;
    *status = (uint8_t)(reads % 97u == 50u ? CAPSHEET_SAMPLE_INVALID : reads % 3u);
    return 0;
}

static int32_t read_imu(void *user, uint64_t now_us, uint8_t gyro_range, uint8_t mag_range, bool want_mag,
                        capsheet_imu_reading_t *out)
{
    (void)user;
    out->gyro[0] = (int16_t)((int32_t)(reads * 9973u % 65536u) - 32768);
    out->gyro[1] = (int16_t)(gyro_range * 1000);
    out->gyro[2] = (int16_t)(reads % 7u == 3u ? 32767 : 5);
    if (want_mag) {
        out->mag[0] = (int16_t)(8192 >> mag_range);
        out->mag[1] = (int16_t)(reads % 11u == 4u ? -32768 : -4096);
        out->mag[2] = 1;
    }
    out->latch_us = now_us + (reads % 5u) * 700u - 1400u;
    out->status = (uint8_t)(reads % 13u == 6u ? CAPSHEET_SAMPLE_STALE : 0u);
    return 0;
}

static int32_t send_bytes(void *user, const uint8_t *data, size_t len)
{
    (void)user;
    print_hex("tx", 0, data, len);
    return 0;
}

static int32_t send_can(void *user, uint32_t id, const uint8_t *data, uint8_t len, bool is_fd)
{
    (void)user;
    print_hex(is_fd ? "fd" : "cl", id, data, len);
    return 0;
}

static uint64_t read_uid(void *user)
{
    (void)user;
    return 0x0123456789ABCDEFull;
}

static void put16(uint8_t *p, uint32_t v)
{
    p[0] = (uint8_t)(v & 0xFFu);
    p[1] = (uint8_t)((v >> 8) & 0xFFu);
}

/* One host frame into the chip: a (version, type, node, payload), serial or CAN. */
static void deliver(capsheet_chip_t *chip, uint8_t version, uint8_t type, uint16_t node, const uint8_t *payload,
                   size_t len, bool damage, bool fd, uint64_t now)
{
    int32_t rc;
    if (chip->config.transport == CAPSHEET_TRANSPORT_SERIAL) {
        uint8_t wire[CAPSHEET_MAX_WIRE_SIZE];
        int32_t n = capsheet_serial_encode_raw(version, type, node, payload, len, wire, sizeof wire);
        if (n <= 0) {
            exit(2);
        }
        if (damage) {
            wire[rng() % (uint32_t)(n - 1)] ^= (uint8_t)(1u << (rng() % 8u));
        }
        rc = capsheet_chip_rx_bytes(chip, wire, (size_t)n, now);
    } else {
        uint8_t data[64];
        size_t n = len > 64u ? 64u : len;
        int32_t fdlen = capsheet_can_fd_length(n);
        memset(data, 0, sizeof data);
        memcpy(data, payload, n);
        if (fd && fdlen > 0) {
            n = (size_t)fdlen;  /* padded with zeros (or, when damaged, not) */
            if (damage && n > len) {
                data[n - 1u] = 1u;
            }
        }
        rc = capsheet_chip_rx_can(chip, capsheet_can_make_id(4, type, version, node), !(damage && !fd), fd, data, n,
                                  now);
    }
    printf("rc %ld state %u node %04x rx_errors %u missed %u\n", (long)rc, chip->state, chip->node, chip->rx_errors,
           chip->missed_syncs);
}

static void run(capsheet_transport_t transport, uint16_t caps, bool can_fd, unsigned steps)
{
    static const capsheet_hal_t hal = {0, read_axes, send_bytes, send_can, read_uid, 0, 0, read_imu, 0, 0};
    capsheet_chip_config_t cfg;
    capsheet_chip_t chip;
    uint8_t rx[CAPSHEET_RX_BUFFER_SIZE];
    uint64_t now = 0;
    uint16_t counter = 0;
    unsigned k;
    cfg.transport = transport;
    cfg.can_fd = can_fd;
    cfg.capabilities = caps;
    if (capsheet_chip_init(&chip, &cfg, &hal, rx, sizeof rx) != 0 || capsheet_chip_power_on(&chip, 0) < 0) {
        exit(2);
    }
    for (k = 0; k < steps; k++) {
        uint8_t p[64];
        const uint32_t r = rng();
        const uint16_t node = (r & 0x300u) == 0u ? 0u : ((r & 0x300u) == 0x100u ? 0x1234u : chip.node);
        size_t i;
        bool fd = can_fd && (rng() % 4u == 0u);
        for (i = 0; i < sizeof p; i++) {
            p[i] = (uint8_t)rng();
        }
        now += (uint64_t)(rng() % 4u) * 7000u;
        switch (r % 16u) {
        case 0:  /* ASSIGN to the current id, its uid */
            put16(p, 1u + rng() % 3u);
            put16(p + 2, 5);
            p[4] = 0xEF; p[5] = 0xCD; p[6] = 0xAB; p[7] = 0x89;
            deliver(&chip, 1, CAPSHEET_ASSIGN, chip.node, p, 8, false, false, now);
            break;
        case 1:  /* CONFIG_IMU: formats 0..3, ranges around their limits, the FD flag */
        case 2:
            p[0] = (uint8_t)(rng() % 4u);
            p[1] = (uint8_t)(rng() % 6u);
            p[2] = (uint8_t)(rng() % 5u);
            p[3] = (uint8_t)(rng() % 3u);
            deliver(&chip, 1, CAPSHEET_CONFIG_IMU, node, p, (rng() % 8u) ? 4u : 3u, false, false, now);
            break;
        case 3:
            deliver(&chip, 1, CAPSHEET_START, node, p, 0, false, false, now);
            break;
        case 4:
            deliver(&chip, 1, CAPSHEET_STOP, node, p, 0, false, false, now);
            break;
        case 5: case 6: case 7: case 8:  /* SYNC runs */
            counter = (uint16_t)(counter + 1u + (rng() % 8u == 0u ? rng() % 5u : 0u));
            put16(p, counter);
            deliver(&chip, 1, CAPSHEET_SYNC, 0, p, 2, false, false, now);
            break;
        case 9:  /* CONFIG: rate, range, filter, heartbeat */
            put16(p, 145);
            p[2] = (uint8_t)(rng() % 2u);
            p[3] = 0;
            put16(p + 4, (rng() % 2u) ? 250u : 0u);
            deliver(&chip, 1, CAPSHEET_CONFIG, node, p, 6, false, false, now);
            break;
        case 10:  /* a node -> host frame of another chip (or addressed to this one) */
            deliver(&chip, 1, (uint8_t)(1u + rng() % 14u), node, p, rng() % 25u, false, fd, now);
            break;
        case 11:  /* any type and payload, maybe damaged, maybe another version */
            deliver(&chip, (rng() % 6u) ? 1u : 2u, (uint8_t)(rng() % 0x40u), node, p, rng() % 12u, rng() % 3u == 0u,
                    fd, now);
            break;
        case 12:
            deliver(&chip, 1, (rng() % 3u) ? CAPSHEET_GET_INFO : CAPSHEET_RESET, node, p, 0, false, false, now);
            break;
        case 13:
            p[0] = (uint8_t)(rng() % 4u);
            deliver(&chip, 1, CAPSHEET_CAL_READ, chip.node, p, 1, false, false, now);
            break;
        default:
            if (capsheet_chip_poll(&chip, now) < 0) {
                exit(2);
            }
            now += 250000u;
            break;
        }
    }
}

int main(int argc, char **argv)
{
    const unsigned long seed = argc > 1 ? strtoul(argv[1], NULL, 10) : 1ul;
    const unsigned steps = argc > 2 ? (unsigned)strtoul(argv[2], NULL, 10) : 20000u;
    const uint16_t nine = CAPSHEET_CAP_GYRO | CAPSHEET_CAP_MAG | CAPSHEET_CAP_SAMPLE_TIME | CAPSHEET_CAP_MULTI_RANGE;
    rng_state = (uint64_t)seed * 0x9E3779B97F4A7C15ull + 1u;
    run(CAPSHEET_TRANSPORT_SERIAL, nine, false, steps);
    run(CAPSHEET_TRANSPORT_SERIAL, CAPSHEET_CAP_GYRO, false, steps);
    run(CAPSHEET_TRANSPORT_CAN, nine, false, steps);
    run(CAPSHEET_TRANSPORT_CAN, nine, true, steps);
    fprintf(stderr, "chip_trace: %lu frames sent\n", frames_out);
    return 0;
}

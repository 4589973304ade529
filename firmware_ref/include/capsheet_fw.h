/*
 * capsheet_fw.h — reference chip firmware for the capsheet wire protocol (docs/protocol.md, revision below).
 *
 * Portable C99, no dynamic memory: every buffer is the caller's, with its capacity; time is passed
 * in (microseconds, `now_us`), never read; the hardware sits behind `capsheet_hal_t`.
 *
 * Two layers:
 *   1. the codec — pure functions, no state: CRC-16/CCITT-FALSE, COBS, message struct <-> payload
 *      bytes, serial frame, CAN identifier + data, and a byte-at-a-time serial stream decoder;
 *   2. the chip  — `capsheet_chip_t`: the chip side of the protocol (ANNOUNCE, ASSIGN, CONFIG,
 *      SYNC -> SAMPLE, STATUS heartbeat, NACKs, calibration; new in 1.2: CONFIG_IMU and the 6/9-axis
 *      IMU records of §16) driven by the state table of docs/protocol.md §8 (protocol/state.py),
 *      over serial or CAN.
 *
 * Return values: success is non-negative (0, or a length/count where stated); failure is one of
 * the negative CAPSHEET_ERR_* codes, each documented per function. Wire input never asserts:
 * damage is reported through return codes; CAPSHEET_ASSERT only guards programming errors
 * (a NULL pointer where the contract forbids one).
 *
 * Guarantees (checked by firmware_ref/tests/fuzz_decoder.c under ASan/UBSan and by libFuzzer):
 *   - a decoder never reads more than the `len` bytes it is given, and never writes more than
 *     the capacity it is given;
 *   - any byte sequence fed to the stream decoder produces only return codes, never a crash,
 *     and the decoder's buffered length never exceeds its capacity.
 */
#ifndef CAPSHEET_FW_H
#define CAPSHEET_FW_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

/* The assert is overridable: define CAPSHEET_ASSERT before including this header (or with -D). */
#ifndef CAPSHEET_ASSERT
#include <assert.h>
#define CAPSHEET_ASSERT(x) assert(x)
#endif

/* Every function that can fail (it returns a negative CAPSHEET_ERR_* code, or a HAL callback's
 * negative value) is marked CAPSHEET_WARN_UNUSED: a caller that ignores the result is warned, and
 * under the strict flags of firmware_ref/Makefile (-Werror) the build fails. GCC and Clang only
 * (an attribute, not C99: empty elsewhere). Under GCC a cast to (void) does not silence it: test
 * the result. Overridable like CAPSHEET_ASSERT: define it (empty) before including this header. */
#ifndef CAPSHEET_WARN_UNUSED
#if defined(__GNUC__) || defined(__clang__)
#define CAPSHEET_WARN_UNUSED __attribute__((warn_unused_result))
#else
#define CAPSHEET_WARN_UNUSED
#endif
#endif

#define CAPSHEET_FW_VERSION_MAJOR 1
#define CAPSHEET_FW_VERSION_MINOR 2
#define CAPSHEET_FW_VERSION_PATCH 0

/* ------------------------------------------------------------------------------------------ */
/* Protocol constants (protocol/messages/, framing.py, can.py)                                */
/* ------------------------------------------------------------------------------------------ */

#define CAPSHEET_PROTOCOL_VERSION 1u           /* on the wire: the major version (§12) */
#define CAPSHEET_SPEC_VERSION_MINOR 4u         /* the revision of docs/protocol.md implemented: 1.4 */
#define CAPSHEET_NODE_BROADCAST 0x0000u
#define CAPSHEET_NODE_MAX_ASSIGNED 0x7FFFu
#define CAPSHEET_NODE_PROVISIONAL_MIN 0x8000u
#define CAPSHEET_NODE_RESERVED 0xFFFFu
#define CAPSHEET_SAMPLE_WORD_SIZE 5u
#define CAPSHEET_SNAPSHOT_HEADER_SIZE 5u
#define CAPSHEET_SNAPSHOT_IMU_HEADER_SIZE 6u   /* §16.5: counter, first_link, count, format */
#define CAPSHEET_IMU6_RECORD_SIZE 13u          /* §16.1: accel word, time_us, gyroscope */
#define CAPSHEET_IMU9_RECORD_SIZE 19u          /* ... and magnetometer */
#define CAPSHEET_TIME_UNKNOWN (-32768)         /* §16.1 time_us: not known */
#define CAPSHEET_HEADER_SIZE 4u                  /* version, type, node (LE) */
#define CAPSHEET_CRC_SIZE 2u                     /* CRC-16/CCITT-FALSE, MSB first */
#define CAPSHEET_MAX_FRAME_SIZE 1024u            /* header + payload + CRC, before COBS (§6.3) */
#define CAPSHEET_MAX_PAYLOAD_SIZE 1018u
#define CAPSHEET_MAX_ENCODED_SIZE 1029u          /* COBS(1024): n + 1 + n / 254 */
#define CAPSHEET_MAX_WIRE_SIZE 1030u             /* ... plus the 0x00 delimiter */
#define CAPSHEET_COBS_ENCODED_SIZE(n) ((n) + 1u + (n) / 254u)
/* 6/9-axis chips (docs §16): a build-time option. 1 (the default): the chip can be built with a
 * gyroscope (and a magnetometer) — capability GYRO (MAG) with the HAL's read_imu — and answers SYNC
 * with IMU records after CONFIG_IMU selects them. 0: an accelerometer-only build; the IMU record path
 * and the larger TX buffer are compiled out (capsheet_chip_init refuses GYRO), CONFIG_IMU is still
 * checked as §16.2 says (format 0 ACKed, formats 1 and 2 UNSUPPORTED). The codec speaks every type
 * either way. */
#ifndef CAPSHEET_IMU
#define CAPSHEET_IMU 1
#endif
/* A chip's image: a build-time option. 0 (the default): the codec encodes and decodes every type
 * (a host, a gateway, a sniffer, the tests). 1: it decodes only host -> node payloads and encodes
 * only what a chip sends (ANNOUNCE, INFO, SAMPLE, STATUS, ACK, NACK, CAL_DATA, the IMU frames); the
 * other types give CAPSHEET_ERR_UNKNOWN_TYPE. The chip behaves identically either way: it ignores a
 * node -> host frame before its payload matters (§8.1 row 7) — only its flash is smaller. */
#ifndef CAPSHEET_CHIP_ONLY
#define CAPSHEET_CHIP_ONLY 0
#endif
/* Largest frame a chip ever sends, on the wire: ANNOUNCE/INFO/STATUS/CAL_DATA (8-byte payloads), or
 * with CAPSHEET_IMU a 9-axis IMU_SAMPLE (21-byte payload: 29 bytes on the wire; 24 on CAN FD). */
#if CAPSHEET_IMU
#define CAPSHEET_CHIP_TX_WIRE_SIZE (CAPSHEET_COBS_ENCODED_SIZE(CAPSHEET_HEADER_SIZE + 21u + CAPSHEET_CRC_SIZE) + 1u)
#else
#define CAPSHEET_CHIP_TX_WIRE_SIZE (CAPSHEET_COBS_ENCODED_SIZE(CAPSHEET_HEADER_SIZE + 8u + CAPSHEET_CRC_SIZE) + 1u)
#endif
/* Largest host -> chip frame (8-byte payload) between delimiters: the smallest useful RX buffer. */
#define CAPSHEET_MIN_RX_BUFFER_SIZE CAPSHEET_COBS_ENCODED_SIZE(CAPSHEET_HEADER_SIZE + 8u + CAPSHEET_CRC_SIZE)
#define CAPSHEET_CAN_CLASSIC_MTU 8u
#define CAPSHEET_CAN_FD_MTU 64u
#define CAPSHEET_ANNOUNCE_PERIOD_US 1000000u     /* §3.2, §14 */
#define CAPSHEET_DEFAULT_HEARTBEAT_MS 1000u      /* STATUS period until a CONFIG says otherwise */

/* Serial RX buffer of the chip: a build-time option (bytes between two 0x00 delimiters).
 * A chip only ever needs CAPSHEET_MIN_RX_BUFFER_SIZE (15): every host -> chip frame fits, longer
 * runs (other chips' frames, damage) are dropped as CAPSHEET_ERR_OVERSIZE and counted in
 * rx_errors. The default, 64, leaves room and keeps a serial chip within the 1 KiB RAM budget
 * (capsheet_chip_t + 64 B: see README.md "Size"). CAPSHEET_MAX_ENCODED_SIZE (1029) accepts every
 * frame the spec allows (a gateway or a sniffer), at 1 KiB of RAM. */
#ifndef CAPSHEET_RX_BUFFER_SIZE
#define CAPSHEET_RX_BUFFER_SIZE 64u
#endif

/* ------------------------------------------------------------------------------------------ */
/* Error codes (negative; success is >= 0)                                                     */
/* ------------------------------------------------------------------------------------------ */

#define CAPSHEET_ERR_ARGUMENT (-1)      /* an argument is out of its documented domain */
#define CAPSHEET_ERR_CAPACITY (-2)      /* the output buffer is too small */
/* decode errors: one per protocol.framing.ErrorReason (docs §6.4) */
#define CAPSHEET_ERR_BAD_COBS (-3)      /* not valid COBS */
#define CAPSHEET_ERR_SHORT (-4)         /* shorter than header + CRC (6 bytes) */
#define CAPSHEET_ERR_BAD_CRC (-5)       /* CRC mismatch */
#define CAPSHEET_ERR_OVERSIZE (-6)      /* longer than the receive buffer without a delimiter */
#define CAPSHEET_ERR_BAD_VERSION (-7)   /* protocol version is not CAPSHEET_PROTOCOL_VERSION */
#define CAPSHEET_ERR_UNKNOWN_TYPE (-8)  /* type code not defined */
#define CAPSHEET_ERR_BAD_LENGTH (-9)    /* payload length does not match the type */
#define CAPSHEET_ERR_BAD_FIELD (-10)    /* a field out of range */
#define CAPSHEET_ERR_NEEDS_FD (-11)     /* the payload does not fit classic CAN */
#define CAPSHEET_ERR_HAL (-12)          /* a HAL callback reported failure */

/* ------------------------------------------------------------------------------------------ */
/* Enumerations (values are the wire codes)                                                    */
/* ------------------------------------------------------------------------------------------ */

typedef enum {
    /* chip -> host */
    CAPSHEET_ANNOUNCE = 0x01, CAPSHEET_INFO = 0x02, CAPSHEET_SAMPLE = 0x03, CAPSHEET_STATUS = 0x04,
    CAPSHEET_ACK = 0x05, CAPSHEET_NACK = 0x06, CAPSHEET_CAL_DATA = 0x07, CAPSHEET_SNAPSHOT = 0x08,
    CAPSHEET_GATEWAY_INFO = 0x09,
    /* chip -> host, new in 1.2 (§16): classic CAN record frames, the record on serial / CAN FD, a gateway's packed records */
    CAPSHEET_IMU_GYRO = 0x0A, CAPSHEET_IMU_MAG = 0x0B, CAPSHEET_IMU_ACCEL = 0x0C, CAPSHEET_IMU_SAMPLE = 0x0D,
    CAPSHEET_SNAPSHOT_IMU = 0x0E,
    CAPSHEET_CAL_IMU_DATA = 0x0F,  /* new in 1.3 (§17) */
    /* host -> chip */
    CAPSHEET_SYNC = 0x10, CAPSHEET_ASSIGN = 0x11, CAPSHEET_CONFIG = 0x12, CAPSHEET_START = 0x13,
    CAPSHEET_STOP = 0x14, CAPSHEET_GET_INFO = 0x15, CAPSHEET_RESET = 0x16, CAPSHEET_CAL_WRITE = 0x17,
    CAPSHEET_CAL_READ = 0x18, CAPSHEET_CONFIG_IMU = 0x19,
    CAPSHEET_CAL_IMU_WRITE = 0x1A, CAPSHEET_CAL_IMU_READ = 0x1B  /* new in 1.3 (§17) */
} capsheet_msg_type_t;

#define CAPSHEET_HOST_TYPE_FIRST 0x10u
#define CAPSHEET_HOST_TYPE_LAST 0x1Bu
/* Every type in 0x01..0x0F, defined or not, goes node -> host: a chip ignores such frames (§4, §8.1). */
#define CAPSHEET_NODE_TO_HOST_FIRST 0x01u
#define CAPSHEET_NODE_TO_HOST_LAST 0x0Fu
#define CAPSHEET_LINK_NONE 0xFFFFu               /* ASSIGN link of a node on no link (a gateway, §13) */

typedef enum { CAPSHEET_BOOT = 0, CAPSHEET_IDLE = 1, CAPSHEET_STREAMING = 2, CAPSHEET_FAULT = 3 } capsheet_state_t;
#define CAPSHEET_STATE_COUNT 4u

/* Capability bits (INFO, §4.2) */
#define CAPSHEET_CAP_CAN_FD 0x0001u
#define CAPSHEET_CAP_SNAPSHOT 0x0002u
#define CAPSHEET_CAP_SELF_TEST 0x0004u
#define CAPSHEET_CAP_CAL_STORAGE 0x0008u
#define CAPSHEET_CAP_MULTI_RANGE 0x0010u
#define CAPSHEET_CAP_FILTER 0x0020u
#define CAPSHEET_CAP_GATEWAY 0x0040u            /* new in 1.1: the node is a gateway (never set by a chip) */
#define CAPSHEET_CAP_SYNC_SOURCE 0x0080u        /* new in 1.1: a gateway that can generate SYNC */
#define CAPSHEET_CAP_GYRO 0x0100u               /* new in 1.2: a triaxial gyroscope (CONFIG_IMU formats 1, 2) */
#define CAPSHEET_CAP_MAG 0x0200u                /* new in 1.2: a triaxial magnetometer (CONFIG_IMU format 2) */
#define CAPSHEET_CAP_SAMPLE_TIME 0x0400u        /* new in 1.2: IMU records carry a true time_us */

/* CONFIG_IMU (§16.2) */
#define CAPSHEET_IMU_FORMAT_ACCEL 0u            /* SAMPLE, as in 1.1 */
#define CAPSHEET_IMU_FORMAT_6AXIS 1u            /* accel + gyro: 13-byte records */
#define CAPSHEET_IMU_FORMAT_9AXIS 2u            /* accel + gyro + mag: 19-byte records */
#define CAPSHEET_IMU_FLAG_FD 0x01u              /* on CAN, one IMU_SAMPLE per record in an FD frame */
#define CAPSHEET_IMU_DEFAULT_GYRO_RANGE 3u      /* ±1000 °/s until a CONFIG_IMU */

/* STATUS flag bits (§4.4) */
#define CAPSHEET_FLAG_CAL_VALID 0x01u
#define CAPSHEET_FLAG_SELF_TEST_ON 0x02u
#define CAPSHEET_FLAG_ADC_FAULT 0x04u
#define CAPSHEET_FLAG_CONFIGURED 0x08u

/* SampleStatus bits (§5.2) */
#define CAPSHEET_SAMPLE_SATURATED 0x1u
#define CAPSHEET_SAMPLE_SELF_TEST 0x2u
#define CAPSHEET_SAMPLE_STALE 0x4u
#define CAPSHEET_SAMPLE_INVALID 0x8u

/* NACK reasons (§4.6) */
typedef enum {
    CAPSHEET_NACK_UNKNOWN_COMMAND = 1, CAPSHEET_NACK_BAD_LENGTH = 2, CAPSHEET_NACK_BAD_VALUE = 3,
    CAPSHEET_NACK_BAD_STATE = 4, CAPSHEET_NACK_UNSUPPORTED = 5, CAPSHEET_NACK_BAD_VERSION = 6,
    CAPSHEET_NACK_STORAGE_FAILED = 7
} capsheet_nack_reason_t;

/* ------------------------------------------------------------------------------------------ */
/* Messages                                                                                    */
/* ------------------------------------------------------------------------------------------ */

/* One axis of calibration (CAL_DATA, CAL_WRITE: §4.7, §4.15). */
typedef struct {
    uint8_t axis;          /* 0 = x, 1 = y, 2 = z */
    uint8_t flags;         /* bit 0: stored in (CAL_DATA) / store to (CAL_WRITE) non-volatile memory */
    int16_t offset_q4;     /* zero-g offset in 1/16 count */
    float sensitivity;     /* counts per g, IEEE-754 binary32, finite and > 0 */
} capsheet_cal_t;

/* A decoded or to-be-encoded message. `type` selects the member of `u`. */
typedef struct {
    uint8_t type;          /* capsheet_msg_type_t */
    uint16_t node;         /* source (chip -> host) or destination (host -> chip; 0 = broadcast) */
    union {
        struct { uint64_t uid; } announce;
        struct {
            uint8_t fw_major, fw_minor, fw_patch, protocol_version;
            uint16_t capabilities;
            uint8_t adc_bits, state;
        } info;
        struct { uint16_t counter; int16_t x, y, z; uint8_t status; } sample;
        struct { uint8_t state, flags, rx_errors, missed_syncs; uint32_t uptime_s; } status;
        struct { uint8_t command, detail; } ack;
        struct { uint8_t command, reason; } nack;
        capsheet_cal_t cal;    /* CAL_DATA and CAL_WRITE */
        struct {
            uint16_t counter, first_link;
            uint8_t count;
            const uint8_t *words;  /* count * 5 bytes; decode: points into the decoded buffer */
        } snapshot;
        struct {
            uint8_t flags, sample_format;
            uint16_t first_link, link_count, sync_rate_hz;
        } gateway_info;
        struct { uint16_t counter; } sync;
        struct { uint16_t new_node, link; uint32_t uid_low; } assign;
        struct { uint16_t rate_hz; uint8_t range, filter; uint16_t heartbeat_ms; } config;
        struct { uint8_t axis; } cal_read;
        /* new in 1.3 (§17): CAL_IMU_DATA and CAL_IMU_WRITE; CAL_IMU_READ */
        struct { uint8_t block, index, flags, reserved; float value; } cal_imu;
        struct { uint8_t block, index; } cal_imu_read;
        /* new in 1.2 (§16). IMU_SAMPLE: `format` 1 (6-axis, 15-byte payload) or 2 (9-axis, 21 bytes;
         * mx..mz only then); the status bits cover the whole record (§16.1). */
        struct {
            uint16_t counter;
            int16_t x, y, z;
            uint8_t status;
            uint8_t format;
            int16_t time_us;
            int16_t gx, gy, gz, mx, my, mz;
        } imu_sample;
        struct { uint16_t counter; int16_t gx, gy, gz; } imu_gyro;      /* IMU_GYRO (classic CAN) */
        struct { uint16_t counter; int16_t mx, my, mz; } imu_mag;       /* IMU_MAG (classic CAN) */
        struct {
            uint8_t counter_lo;
            int16_t x, y, z;
            uint8_t status;
            int16_t time_us;
        } imu_accel;                                                    /* IMU_ACCEL (classic CAN) */
        struct {
            uint16_t counter, first_link;
            uint8_t count, format;
            const uint8_t *records;  /* count * 13 (format 1) or 19 (format 2) bytes; decode: into the buffer */
        } snapshot_imu;
        struct { uint8_t format, gyro_range, mag_range, flags; } config_imu;
    } u;
} capsheet_msg_t;

/* ------------------------------------------------------------------------------------------ */
/* Codec: pure functions                                                                       */
/* ------------------------------------------------------------------------------------------ */

/* CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, xorout 0; check("123456789") =
 * 0x29B1). Pass CAPSHEET_CRC_INIT as `crc` to start, or a previous result to continue. */
#define CAPSHEET_CRC_INIT 0xFFFFu
uint16_t capsheet_crc16(const uint8_t *data, size_t len, uint16_t crc);

/* COBS-encode `len` bytes into `out` (no delimiter is added). `out` must not overlap `in`.
 * Returns the encoded length (at most CAPSHEET_COBS_ENCODED_SIZE(len)).
 * CAPSHEET_ERR_CAPACITY: `cap` is too small (nothing beyond `out[cap-1]` is written).
 * CAPSHEET_ERR_ARGUMENT: `len` > 0x7FFFFF00 (the length would not fit the int32_t result). */
CAPSHEET_WARN_UNUSED int32_t capsheet_cobs_encode(const uint8_t *in, size_t len, uint8_t *out, size_t cap);

/* COBS-decode `len` bytes (without the delimiter) into `out`; `out == in` is allowed (in-place).
 * Returns the decoded length (< len for len > 0).
 * CAPSHEET_ERR_BAD_COBS: a 0x00 byte inside, or a code byte that points past the end.
 * CAPSHEET_ERR_CAPACITY: the decoded bytes do not fit `cap`.
 * CAPSHEET_ERR_ARGUMENT: `len` > 0x7FFFFF00. */
CAPSHEET_WARN_UNUSED int32_t capsheet_cobs_decode(const uint8_t *in, size_t len, uint8_t *out, size_t cap);

/* The CAN priority of a type (docs §7.1); 7 for an unknown type. */
uint8_t capsheet_priority(uint8_t type);

/* Whether `type` is defined in protocol v1. */
bool capsheet_type_known(uint8_t type);

/* protocol/messages.py provisional_node(): 0x8000 | (h % 0x7FFF) where
 * h = (uint32)(uid ^ (uid >> 32)) ^ (uint32)(salt * 0x9E3779B9); h ^= h >> 16. */
uint16_t capsheet_provisional_node(uint64_t uid, uint32_t salt);

/* Message -> payload bytes (docs §4, §16), no header or CRC. Fields are not validated (a sender
 * composes what it means; the decoder is strict); a SNAPSHOT's or SNAPSHOT_IMU's `count` must be
 * 1..255, an IMU_SAMPLE's or SNAPSHOT_IMU's `format` 1 or 2. Returns the payload length.
 * CAPSHEET_ERR_UNKNOWN_TYPE: `msg->type` is not defined.
 * CAPSHEET_ERR_ARGUMENT: a SNAPSHOT (SNAPSHOT_IMU) with count 0 or words (records) == NULL, an
 * IMU_SAMPLE or SNAPSHOT_IMU whose format is not 1 or 2.
 * CAPSHEET_ERR_CAPACITY: the payload does not fit `cap`. */
CAPSHEET_WARN_UNUSED int32_t capsheet_payload_encode(const capsheet_msg_t *msg, uint8_t *buf, size_t cap);

/* Payload bytes -> message, with the same checks, in the same order, as
 * protocol.messages.decode_payload: type, then node 0xFFFF, then length, then fields.
 * Returns 0. `out->type` and `out->node` are always set; on CAPSHEET_ERR_BAD_FIELD the fields
 * are filled as decoded (so a chip can still, e.g., check an ASSIGN's uid_low).
 * A SNAPSHOT's `words` (a SNAPSHOT_IMU's `records`) point into `payload`; an IMU_SAMPLE's `format`
 * is 1 or 2 from its length (15 or 21 bytes).
 * CAPSHEET_ERR_UNKNOWN_TYPE, CAPSHEET_ERR_BAD_LENGTH, CAPSHEET_ERR_BAD_FIELD. */
CAPSHEET_WARN_UNUSED int32_t capsheet_payload_decode(uint8_t type, uint16_t node, const uint8_t *payload, size_t len,
                                capsheet_msg_t *out);

/* Message -> one serial frame: COBS(header + payload + CRC) + 0x00. Returns the wire length.
 * Errors as capsheet_payload_encode, and CAPSHEET_ERR_ARGUMENT if the frame would exceed
 * CAPSHEET_MAX_FRAME_SIZE. */
CAPSHEET_WARN_UNUSED int32_t capsheet_serial_encode(const capsheet_msg_t *msg, uint8_t *out, size_t cap);

/* Low level: a serial frame from its parts, unvalidated except for size (tests use it to build
 * frames a conforming sender never would). Errors: CAPSHEET_ERR_ARGUMENT (too big),
 * CAPSHEET_ERR_CAPACITY. */
CAPSHEET_WARN_UNUSED int32_t capsheet_serial_encode_raw(uint8_t version, uint8_t type, uint16_t node, const uint8_t *payload,
                                   size_t len, uint8_t *out, size_t cap);

/* Decode the bytes between two delimiters (without the 0x00), IN PLACE: `frame` is overwritten
 * with the decoded bytes, and a SNAPSHOT's `words` point into it. Checks in the order of
 * protocol.framing.decode_frame (docs §8.1). Returns 0.
 * CAPSHEET_ERR_OVERSIZE (len > CAPSHEET_MAX_ENCODED_SIZE, or more than CAPSHEET_MAX_FRAME_SIZE
 * bytes after COBS decoding), CAPSHEET_ERR_BAD_COBS,
 * CAPSHEET_ERR_SHORT, CAPSHEET_ERR_BAD_CRC: `out` is not touched.
 * CAPSHEET_ERR_BAD_VERSION: `out->type`/`out->node` hold the header's type and node and `*version`
 * (if not NULL) the peer's version. CAPSHEET_ERR_UNKNOWN_TYPE, CAPSHEET_ERR_BAD_LENGTH,
 * CAPSHEET_ERR_BAD_FIELD: as capsheet_payload_decode. */
CAPSHEET_WARN_UNUSED int32_t capsheet_serial_decode_frame(uint8_t *frame, size_t len, capsheet_msg_t *out, uint8_t *version);

/* Byte-at-a-time serial stream decoder over a caller-provided buffer (bounded: at most `cap`
 * bytes of one frame are held; a longer run without 0x00 is reported once as
 * CAPSHEET_ERR_OVERSIZE and skipped up to the next 0x00). Empty frames (0x00 0x00) are idle fill. */
typedef struct {
    uint8_t *buf;
    size_t cap;
    size_t len;
    bool discarding;
    uint8_t version;       /* version byte of the last BAD_VERSION frame */
    uint32_t frames;       /* frames decoded */
    uint32_t errors;       /* frames dropped */
} capsheet_stream_t;

/* `cap` must be >= 1; CAPSHEET_MAX_ENCODED_SIZE (1029) accepts every frame the spec allows.
 * Returns 0. CAPSHEET_ERR_ARGUMENT: `buf` is NULL or `cap` == 0. */
CAPSHEET_WARN_UNUSED int32_t capsheet_stream_init(capsheet_stream_t *s, uint8_t *buf, size_t cap);

/* Feed one byte. Returns 0: nothing complete; 1: a frame was decoded into `*out` (a SNAPSHOT's
 * words point into the stream buffer, valid until the next feed); a negative decode error: a
 * frame was dropped (codes and the state of `*out` as capsheet_serial_decode_frame;
 * CAPSHEET_ERR_OVERSIZE when the buffer overflows). */
CAPSHEET_WARN_UNUSED int32_t capsheet_stream_feed(capsheet_stream_t *s, uint8_t byte, capsheet_msg_t *out);

/* CAN (docs §7). Identifier: priority[28:26] type[25:20] version[19:16] node[15:0]. */
uint32_t capsheet_can_make_id(uint8_t priority, uint8_t type, uint8_t version, uint16_t node);

typedef enum {
    CAPSHEET_CAN_AUTO = 0,     /* FD only when the payload needs it (protocol.can.to_can fd=None) */
    CAPSHEET_CAN_CLASSIC = 1,  /* classic only: CAPSHEET_ERR_NEEDS_FD for a payload over 8 bytes */
    CAPSHEET_CAN_FD = 2        /* always FD, padded with 0x00 to the next FD length */
} capsheet_can_mode_t;

/* Message -> CAN frame: identifier with the type's priority, data (FD-padded), length and FD flag.
 * `cap` is the capacity of `data` (64 always suffices). Returns the data length.
 * Errors as capsheet_payload_encode, and CAPSHEET_ERR_NEEDS_FD. */
CAPSHEET_WARN_UNUSED int32_t capsheet_can_encode(const capsheet_msg_t *msg, capsheet_can_mode_t mode, uint32_t *id,
                            uint8_t *data, size_t cap, bool *is_fd);

/* Smallest CAN FD length >= n, or CAPSHEET_ERR_ARGUMENT for n > 64. */
CAPSHEET_WARN_UNUSED int32_t capsheet_can_fd_length(size_t n);

/* One received CAN frame -> message, with the checks of protocol.can.decode_can in its order:
 * CAPSHEET_ERR_BAD_FIELD (standard identifier, identifier over 29 bits, non-zero FD padding of a
 * SNAPSHOT, SNAPSHOT_IMU or IMU_SAMPLE), CAPSHEET_ERR_BAD_VERSION, CAPSHEET_ERR_BAD_LENGTH (invalid
 * CAN length; an FD IMU_SAMPLE not 16 or 24 bytes; a padded length that is not the count's), then as
 * capsheet_payload_decode. `out->type`/`out->node` are set from the identifier whenever it is a
 * 29-bit one; `*version` (if not NULL) gets the identifier's version. Returns 0. */
CAPSHEET_WARN_UNUSED int32_t capsheet_can_decode(uint32_t id, bool is_extended, bool is_fd, const uint8_t *data, size_t len,
                            capsheet_msg_t *out, uint8_t *version);

/* ------------------------------------------------------------------------------------------ */
/* The state table (docs §8, protocol/state.py RULES)                                          */
/* ------------------------------------------------------------------------------------------ */

typedef enum {
    CAPSHEET_REPLY_NONE = 0, CAPSHEET_REPLY_ACK = 1, CAPSHEET_REPLY_SAMPLE = 2,
    CAPSHEET_REPLY_ANNOUNCE_INFO = 3, CAPSHEET_REPLY_CAL_DATA = 4, CAPSHEET_REPLY_ACK_THEN_BOOT = 5,
    CAPSHEET_REPLY_CAL_IMU_DATA = 6
} capsheet_reply_t;

/* new in 1.3 (§17.1): the gyroscope's and magnetometer's calibration, 33 float32 elements: GYRO_MATRIX
 * 0..8, GYRO_BIAS 9..11, GYRO_G_SENS 12..20, MAG_MATRIX 21..29, MAG_HARD_IRON 30..32. */
#define CAPSHEET_IMU_CAL_COUNT 33u

#define CAPSHEET_STAY 0xFFu  /* next_state: no change */

typedef struct {
    uint8_t reply;       /* capsheet_reply_t */
    uint8_t next_state;  /* capsheet_state_t or CAPSHEET_STAY */
    uint8_t validate;    /* 1: fields are checked first (NACK BAD_VALUE / UNSUPPORTED) */
} capsheet_rule_t;

/* The rule for (state, host -> chip type). Returns 1 and fills `*rule`; 0 if the pair is not in
 * the table (NACK BAD_STATE when addressed, ignored when broadcast); CAPSHEET_ERR_ARGUMENT for a
 * state or type out of range. */
CAPSHEET_WARN_UNUSED int32_t capsheet_rule_for(uint8_t state, uint8_t type, capsheet_rule_t *rule);

/* ------------------------------------------------------------------------------------------ */
/* The chip                                                                                    */
/* ------------------------------------------------------------------------------------------ */

typedef enum { CAPSHEET_TRANSPORT_SERIAL = 0, CAPSHEET_TRANSPORT_CAN = 1 } capsheet_transport_t;

/* The hardware. `user` is passed back to every callback. Callbacks return 0 or negative (the chip
 * then returns CAPSHEET_ERR_HAL from the call that invoked it).
 *
 * Lifetime: the `data` given to send_bytes / send_can is the chip's own TX buffer (capsheet_chip_t
 * `tx`, CAPSHEET_CHIP_TX_WIRE_SIZE bytes: 29, or 17 with CAPSHEET_IMU 0, on both transports) and is
 * reused by the very next send (the 2-3 classic CAN frames of one IMU record go back to back): it
 * is valid only until the callback returns. A HAL that sends later (DMA, an interrupt-driven FIFO)
 * must copy it first.
 *
 * Concurrency: the library is not reentrant and takes no locks. Call every capsheet_chip_* function
 * for one chip from one context (the main loop, or one RTOS task), never from an interrupt
 * handler; an ISR should only move received bytes/frames into a queue that the main loop drains
 * into capsheet_chip_rx_bytes / capsheet_chip_rx_can (firmware_ref/ports/qemu-mps2/uart.c does so
 * with a single-producer ring). The callbacks are called from inside those functions, in the same
 * context; they must not call back into the chip. Different chips (capsheet_chip_t) are independent.
 * The codec functions are pure and may be called from any context. */
/* One gyroscope (and magnetometer) reading, filled by the HAL's read_imu (docs §16.1). */
typedef struct {
    int16_t gyro[3];       /* 16-bit counts at the gyro_range asked for, sensor frame */
    int16_t mag[3];        /* 16-bit counts at the mag_range asked for (read only when asked) */
    uint64_t latch_us;     /* when the reading was latched, on the `now_us` time base: the chip sends
                            * latch_us - (the SYNC's now_us) as time_us, clamped to ±32767 (with
                            * capability SAMPLE_TIME; without it, −32768) */
    uint8_t status;        /* SampleStatus bits for the record: STALE (no gyroscope conversion since
                            * the previous SYNC), SELF_TEST; INVALID is a sensor fault */
} capsheet_imu_reading_t;

typedef struct {
    void *user;
    /* Convert and read the three axes (ADC counts, clamped to -2048..2047 by the chip) and the
     * SampleStatus bits. A negative return, or the INVALID bit, is a sensor fault. */
    CAPSHEET_WARN_UNUSED int32_t (*read_axes)(void *user, uint64_t now_us, int16_t xyz[3], uint8_t *status);
    /* serial transport: send one whole frame (delimiter included) */
    CAPSHEET_WARN_UNUSED int32_t (*send_bytes)(void *user, const uint8_t *data, size_t len);
    /* CAN transport: send one frame with a 29-bit identifier */
    CAPSHEET_WARN_UNUSED int32_t (*send_can)(void *user, uint32_t id, const uint8_t *data, uint8_t len, bool is_fd);
    /* the chip's 64-bit unique id */
    uint64_t (*read_uid)(void *user);
    /* optional (NULL: none): load / store one axis of calibration in non-volatile memory.
     * cal_load returns 0 if the axis was stored, negative if not. */
    CAPSHEET_WARN_UNUSED int32_t (*cal_load)(void *user, uint8_t axis, capsheet_cal_t *cal);
    CAPSHEET_WARN_UNUSED int32_t (*cal_store)(void *user, uint8_t axis, const capsheet_cal_t *cal);
    /* 6/9-axis chips (capability GYRO; NULL otherwise, and unused with CAPSHEET_IMU 0): called at a
     * SYNC in CONFIG_IMU format 1 or 2, right after read_axes answered valid, for the gyroscope read
     * with the same latch as the accelerometer and — when `want_mag` — the magnetometer's latest
     * output, at CONFIG_IMU's range codes. `out` is zeroed before the call. A negative return, or
     * INVALID in `out->status`, is a sensor fault (an INVALID record, FAULT). */
    CAPSHEET_WARN_UNUSED int32_t (*read_imu)(void *user, uint64_t now_us, uint8_t gyro_range, uint8_t mag_range,
                                             bool want_mag, capsheet_imu_reading_t *out);
    /* optional (NULL: none; a GYRO chip with CAL_STORAGE needs both): load / store one element (0..32,
     * §17.1's order: block 0's nine, block 1's three, ...) of the gyro/mag calibration in non-volatile
     * memory, as its float32 bits. cal_imu_load returns 0 if the element was stored, negative if not;
     * cal_imu_store negative if storing failed (the chip NACKs STORAGE_FAILED). */
    CAPSHEET_WARN_UNUSED int32_t (*cal_imu_load)(void *user, uint8_t element, uint32_t *bits);
    CAPSHEET_WARN_UNUSED int32_t (*cal_imu_store)(void *user, uint8_t element, uint32_t bits);
} capsheet_hal_t;

typedef struct {
    capsheet_transport_t transport;
    bool can_fd;             /* the CAN controller takes FD frames (sets CAPSHEET_CAP_CAN_FD) */
    uint16_t capabilities;   /* INFO capabilities (CAL_STORAGE needs cal_load/cal_store; GYRO needs
                              * read_imu and CAPSHEET_IMU; format 2 needs GYRO and MAG) */
} capsheet_chip_config_t;

/* The chip's state. Allocate it (statically) and initialise it with capsheet_chip_init; the
 * fields are readable, not writable. */
typedef struct {
    const capsheet_hal_t *hal;
    capsheet_chip_config_t config;
    uint64_t uid;
    uint16_t node;
    uint16_t prev_node;      /* BOOT: the provisional id of the round before (ASSIGN only, §3.3) */
    bool has_prev;
    uint16_t link;
    bool has_link;
    uint8_t state;           /* capsheet_state_t */
    bool started;            /* START received (FAULT answers SYNC only then) */
    bool powered;            /* power_on was called */
    bool heartbeat_on;       /* STATUS heartbeat scheduled */
    uint8_t flags;           /* CAPSHEET_FLAG_CONFIGURED (the other STATUS flags are derived) */
    uint8_t rx_errors;       /* frames the receiver dropped, saturating at 255 */
    uint8_t missed_syncs;    /* SYNC counters skipped while streaming, saturating at 255 */
    bool have_sync;
    uint16_t last_sync;
    uint32_t salt;           /* periodic ANNOUNCEs unanswered since boot */
    uint64_t boot_us;        /* power-on: uptime_s counts from here (RESET does not restart it) */
    uint64_t next_announce_us;
    uint64_t next_heartbeat_us;
    uint16_t rate_hz;
    uint8_t range_code;
    uint8_t filter;
    uint16_t heartbeat_ms;
    uint8_t imu_format;      /* CONFIG_IMU (§16.2): 0 SAMPLE, 1 6-axis, 2 9-axis records */
    uint8_t gyro_range;      /* 0..4: ±125 .. ±2000 °/s */
    uint8_t mag_range;       /* 0..3: ±4 .. ±16 gauss */
    uint8_t imu_flags;       /* CAPSHEET_IMU_FLAG_FD */
    capsheet_cal_t cal[3];
#if CAPSHEET_IMU
    uint32_t imu_cal[CAPSHEET_IMU_CAL_COUNT];   /* new in 1.3 (§17): the elements in use, float32 bits (the
                                                 * stored copy is the HAL's: cal_imu_load/cal_imu_store) */
    uint8_t imu_cal_stored[(CAPSHEET_IMU_CAL_COUNT + 7u) / 8u]; /* bit k: element k in use is the stored one */
#endif
    capsheet_stream_t rx;    /* serial only */
    uint8_t tx[CAPSHEET_CHIP_TX_WIRE_SIZE];
#ifdef CAPSHEET_MUTANTS
    int32_t mutant;          /* capsheet_mutant_t: the rule this test build breaks (0: none) */
    bool has_frozen;         /* CAPSHEET_MUT_FROZEN_SAMPLE: the first SAMPLE's fields */
    int16_t frozen_xyz[3];
    uint8_t frozen_status;
#endif
} capsheet_chip_t;

/* Set up a chip (it stays silent until capsheet_chip_power_on). Serial needs `rx_buf` with
 * `rx_cap` >= CAPSHEET_MIN_RX_BUFFER_SIZE (CAPSHEET_RX_BUFFER_SIZE is the build's choice); CAN
 * needs none (NULL, 0). Returns 0.
 * CAPSHEET_ERR_ARGUMENT: a required HAL callback is NULL, CAL_STORAGE without cal_load/cal_store,
 * GYRO without read_imu (or in a CAPSHEET_IMU 0 build), or a serial RX buffer below the minimum. */
CAPSHEET_WARN_UNUSED int32_t capsheet_chip_init(capsheet_chip_t *chip, const capsheet_chip_config_t *config,
                           const capsheet_hal_t *hal, uint8_t *rx_buf, size_t rx_cap);

/* Boot: read the uid, load calibration, enter BOOT with a provisional node id, send ANNOUNCE + INFO.
 * Returns the number of frames sent, or CAPSHEET_ERR_HAL if a send failed. */
CAPSHEET_WARN_UNUSED int32_t capsheet_chip_power_on(capsheet_chip_t *chip, uint64_t now_us);

/* Serial: consume received bytes (any chunking), reacting to every complete frame.
 * Returns the number of frames sent, or CAPSHEET_ERR_HAL if a send failed (the remaining input
 * is still consumed). CAPSHEET_ERR_ARGUMENT: the chip was initialised for CAN. */
CAPSHEET_WARN_UNUSED int32_t capsheet_chip_rx_bytes(capsheet_chip_t *chip, const uint8_t *data, size_t len, uint64_t now_us);

/* CAN: react to one received frame. Returns the number of frames sent, or CAPSHEET_ERR_HAL.
 * CAPSHEET_ERR_ARGUMENT: the chip was initialised for serial. */
CAPSHEET_WARN_UNUSED int32_t capsheet_chip_rx_can(capsheet_chip_t *chip, uint32_t id, bool is_extended, bool is_fd,
                             const uint8_t *data, size_t len, uint64_t now_us);

/* The sensor stopped answering (e.g. a data-ready timeout seen by the application): an assigned
 * chip enters FAULT (SYNC answered with INVALID samples once started; STATUS flags ADC_FAULT).
 * A chip in BOOT is not affected. */
void capsheet_chip_sensor_fault(capsheet_chip_t *chip);

/* Time-driven work: re-ANNOUNCE every second while unassigned, STATUS every heartbeat period
 * while assigned (next deadline = previous + period, or now + period when that is already past:
 * docs §14). Call it at least every few milliseconds. Returns frames sent or CAPSHEET_ERR_HAL. */
CAPSHEET_WARN_UNUSED int32_t capsheet_chip_poll(capsheet_chip_t *chip, uint64_t now_us);

/* ------------------------------------------------------------------------------------------ */
/* Mutants: test builds only (-DCAPSHEET_MUTANTS)                                              */
/* ------------------------------------------------------------------------------------------ */

/* A test build compiled with -DCAPSHEET_MUTANTS breaks one rule of the spec per chip, chosen by the
 * chip's `mutant` field (0: none; set it after capsheet_chip_init), so that the conformance suite
 * can be shown to fail each (tests/host/conformance/mutants.py; docs/conformance.md). A production
 * build does not define CAPSHEET_MUTANTS: the field does not exist and every mutant branch is
 * `if (0)`, compiled away. */
typedef enum {
    CAPSHEET_MUT_NONE = 0,
    CAPSHEET_MUT_DEAD_SENSOR,         /* §5.2  the ADC reads (0, 0, 0), status OK */
    CAPSHEET_MUT_FROZEN_SAMPLE,       /* §5.3  after the first SYNC, repeats that SAMPLE's word, unflagged */
    CAPSHEET_MUT_WRONG_CRC,           /* §6.2  CRC-16/XMODEM (init 0) on every frame */
    CAPSHEET_MUT_WRONG_CRC_SAMPLE,    /* §6.2  a wrong CRC on every SAMPLE only */
    CAPSHEET_MUT_COUNTER_OFF_BY_ONE,  /* §5.1  SAMPLE carries counter + 1 */
    CAPSHEET_MUT_SYNC_TWICE,          /* §5.1  every SYNC answered with two SAMPLEs */
    CAPSHEET_MUT_SLOW_HEARTBEAT,      /* §8.4  STATUS at twice heartbeat_ms */
    CAPSHEET_MUT_NO_REANNOUNCE,       /* §3.2  no ANNOUNCE after the first while unassigned */
    CAPSHEET_MUT_WRONG_NACK_REASON,   /* §4.6  every NACK carries the next reason code */
    CAPSHEET_MUT_IGNORED_RESET,       /* §4.14 ACKs RESET and keeps its state */
    CAPSHEET_MUT_NACKS_BROADCAST,     /* §8.1  NACKs broadcasts (BAD_STATE, BAD_VERSION, ...) like addressed frames */
    CAPSHEET_MUT_NACKS_NODE_TYPES,    /* §8.1  NACKs UNKNOWN_COMMAND a node -> host type addressed to it */
    CAPSHEET_MUT_ACK_DETAIL,          /* §4.5  ACK detail 1 */
    CAPSHEET_MUT_NO_RX_ERRORS,        /* §4.4  rx_errors never counts */
    CAPSHEET_MUT_ASSIGN_IGNORES_UID,  /* §4.10 takes an ASSIGN whatever its uid_low */
    CAPSHEET_MUT_NO_PREVIOUS_ID,      /* §3.3  refuses an ASSIGN to the previous provisional id */
    CAPSHEET_MUT_UPTIME_RESET,        /* §4.4  uptime_s restarts at RESET */
    CAPSHEET_MUT_CAL_READ_NOMINAL,    /* §4.15 CAL_READ answers the nominal calibration */
    CAPSHEET_MUT_ACCEPTS_BAD_CONFIG,  /* §4.11 ACKs a CONFIG with fields out of range */
    CAPSHEET_MUT_IGNORES_CAPABILITY,  /* §4.11 ACKs range != 0 without MULTI_RANGE */
    CAPSHEET_MUT_START_NOT_IDEMPOTENT, /* §4.12 NACKs START while STREAMING */
    CAPSHEET_MUT_STREAMS_AFTER_STOP,  /* §4.12 keeps answering SYNC after STOP */
    CAPSHEET_MUT_MISSED_SYNCS_WRAP,   /* §5.1  counts the 0xFFFF -> 0 wrap as 65535 missed */
    CAPSHEET_MUT_CONFIG_WHILE_STREAMING, /* §8.2 ACKs CONFIG while STREAMING */
    CAPSHEET_MUT_RESERVED_CAPABILITY_BIT, /* §4.2 INFO capabilities with reserved bit 15 set */
    CAPSHEET_MUT_REFUSES_REPEATED_CONFIG, /* §8.3 NACKs BAD_STATE a CONFIG equal to the one it has */
    CAPSHEET_MUT_ANSWERS_BROADCAST,   /* §8.2  NACKs BAD_STATE a broadcast START the state table refuses */
    CAPSHEET_MUT_IGNORES_BROADCAST_START, /* §4.12 acts on START/STOP only when addressed */
    CAPSHEET_MUT_WRONG_PRIORITY,      /* §7.1  CAN: SAMPLE sent with priority 4 (the table: 2) */
    CAPSHEET_MUT_CAL_IMU_READ_NOMINAL, /* §17.2 CAL_IMU_READ answers the nominal value */
    CAPSHEET_MUT_IMU_ANSWERS_SAMPLE,  /* §16.3 takes CONFIG_IMU but answers SYNC with the SAMPLE alone */
    CAPSHEET_MUT_IMU_ACCEL_FIRST,     /* §16.4 classic CAN: IMU_ACCEL before IMU_GYRO (and IMU_MAG) */
    CAPSHEET_MUT_IMU_ACCEPTS_BAD_CONFIG, /* §16.2 ACKs a CONFIG_IMU with values out of range (changes nothing) */
    CAPSHEET_MUT_COUNT
} capsheet_mutant_t;

#ifdef CAPSHEET_MUTANTS
#define CAPSHEET_MUTANT(chip, m) ((chip)->mutant == (int32_t)(m))
#else
#define CAPSHEET_MUTANT(chip, m) 0
#endif

#ifdef __cplusplus
}
#endif

#endif /* CAPSHEET_FW_H */

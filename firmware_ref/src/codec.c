/*
 * codec.c — the pure part of capsheet_fw's framing: CRC, COBS, serial frames, CAN frames and the
 * serial stream decoder (the payloads inside them: payload.c). No state, no HAL. Layouts:
 * protocol/framing.py, protocol/can.py.
 */
#include "codec_internal.h"

/* ------------------------------------------------------------------------------------------ */
/* CRC-16/CCITT-FALSE                                                                          */
/* ------------------------------------------------------------------------------------------ */

uint16_t capsheet_crc16(const uint8_t *data, size_t len, uint16_t crc)
{
    size_t i;
    CAPSHEET_ASSERT(data != NULL || len == 0);
    /* Bitwise, no table: 512 bytes of flash saved on a small part; a SAMPLE frame is 11 bytes. */
    for (i = 0; i < len; i++) {
        unsigned b;
        crc = (uint16_t)(crc ^ (uint16_t)((uint16_t)data[i] << 8));
        for (b = 0; b < 8u; b++) {
            const bool top = (crc & 0x8000u) != 0u;
            crc = (uint16_t)((unsigned)crc << 1);
            if (top) {
                crc = (uint16_t)(crc ^ 0x1021u);
            }
        }
    }
    return crc;
}

/* ------------------------------------------------------------------------------------------ */
/* COBS over a list of byte spans (so a frame is encoded without assembling it first)          */
/* ------------------------------------------------------------------------------------------ */

static CAPSHEET_WARN_UNUSED int32_t cobs_encode_spans(const span_t *spans, size_t nspans, uint8_t *out, size_t cap)
{
    size_t total = 0, done = 0, s, i;
    size_t code_pos = 0, dst = 1;
    uint8_t code = 1;
    for (s = 0; s < nspans; s++) {
        total += spans[s].n;
    }
    if (cap < 1u) {
        return CAPSHEET_ERR_CAPACITY;
    }
    for (s = 0; s < nspans; s++) {
        for (i = 0; i < spans[s].n; i++) {
            const uint8_t byte = spans[s].p[i];
            done++;
            if (byte == 0u) {
                out[code_pos] = code;
                if (dst >= cap) {
                    return CAPSHEET_ERR_CAPACITY;
                }
                code_pos = dst++;
                code = 1;
            } else {
                if (dst >= cap) {
                    return CAPSHEET_ERR_CAPACITY;
                }
                out[dst++] = byte;
                code++;
                if (code == 0xFFu && done < total) {
                    out[code_pos] = code;
                    if (dst >= cap) {
                        return CAPSHEET_ERR_CAPACITY;
                    }
                    code_pos = dst++;
                    code = 1;
                }
            }
        }
    }
    out[code_pos] = code;
    return (int32_t)dst;
}

int32_t capsheet_cobs_encode(const uint8_t *in, size_t len, uint8_t *out, size_t cap)
{
    span_t sp;
    CAPSHEET_ASSERT((in != NULL || len == 0) && out != NULL);
    if (len > 0x7FFFFF00u) {
        return CAPSHEET_ERR_ARGUMENT;
    }
    sp.p = in;
    sp.n = len;
    return cobs_encode_spans(&sp, 1, out, cap);
}

int32_t capsheet_cobs_decode(const uint8_t *in, size_t len, uint8_t *out, size_t cap)
{
    size_t idx = 0, dst = 0;
    CAPSHEET_ASSERT((in != NULL || len == 0) && (out != NULL || cap == 0));
    if (len > 0x7FFFFF00u) {
        return CAPSHEET_ERR_ARGUMENT;
    }
    /* Same rules as the `cobs` package that protocol.framing uses: a code byte n copies n-1 bytes
     * and, unless n is 0xFF or the input ends, adds a 0x00. In place is safe: dst < idx always. */
    while (idx < len) {
        const uint8_t code = in[idx];
        size_t k, end;
        if (code == 0u) {
            return CAPSHEET_ERR_BAD_COBS;
        }
        idx++;
        end = idx + (size_t)code - 1u;
        if (end > len) {
            return CAPSHEET_ERR_BAD_COBS;
        }
        for (k = idx; k < end; k++) {
            if (in[k] == 0u) {
                return CAPSHEET_ERR_BAD_COBS;
            }
            if (dst >= cap) {
                return CAPSHEET_ERR_CAPACITY;
            }
            out[dst++] = in[k];
        }
        idx = end;
        if (idx < len && code != 0xFFu) {
            if (dst >= cap) {
                return CAPSHEET_ERR_CAPACITY;
            }
            out[dst++] = 0u;
        }
    }
    return (int32_t)dst;
}

/* ------------------------------------------------------------------------------------------ */
/* Serial frames                                                                               */
/* ------------------------------------------------------------------------------------------ */

static CAPSHEET_WARN_UNUSED int32_t serial_encode_spans(uint8_t version, uint8_t type, uint16_t node, const span_t *payload,
                                   size_t npayload, uint8_t *out, size_t cap)
{
    uint8_t header[CAPSHEET_HEADER_SIZE], crc_be[CAPSHEET_CRC_SIZE];
    span_t sp[4];
    size_t i, n = 0, plen = 0;
    uint16_t crc;
    int32_t len;
    header[0] = version;
    header[1] = type;
    put_u16(header + 2, node);
    sp[n].p = header;
    sp[n++].n = sizeof header;
    crc = capsheet_crc16(header, sizeof header, CAPSHEET_CRC_INIT);
    for (i = 0; i < npayload; i++) {
        plen += payload[i].n;
        crc = capsheet_crc16(payload[i].p, payload[i].n, crc);
        sp[n++] = payload[i];
    }
    if (plen > CAPSHEET_MAX_PAYLOAD_SIZE) {
        return CAPSHEET_ERR_ARGUMENT;
    }
    crc_be[0] = (uint8_t)(crc >> 8);
    crc_be[1] = (uint8_t)(crc & 0xFFu);
    sp[n].p = crc_be;
    sp[n++].n = sizeof crc_be;
    len = cobs_encode_spans(sp, n, out, cap);
    if (len < 0) {
        return len;
    }
    if ((size_t)len >= cap) {
        return CAPSHEET_ERR_CAPACITY;
    }
    out[len] = 0u;
    return len + 1;
}

int32_t capsheet_serial_encode_raw(uint8_t version, uint8_t type, uint16_t node, const uint8_t *payload,
                                   size_t len, uint8_t *out, size_t cap)
{
    span_t sp;
    CAPSHEET_ASSERT((payload != NULL || len == 0) && out != NULL);
    sp.p = payload;
    sp.n = len;
    return serial_encode_spans(version, type, node, &sp, 1, out, cap);
}

int32_t capsheet_serial_encode(const capsheet_msg_t *msg, uint8_t *out, size_t cap)
{
    uint8_t tmp[CAPSHEET_CODEC_FIXED_MAX];
    span_t sp[2];
    int32_t n;
    CAPSHEET_ASSERT(msg != NULL && out != NULL);
    n = capsheet_codec_payload_spans(msg, tmp, sp);
    if (n < 0) {
        return n;
    }
    return serial_encode_spans((uint8_t)CAPSHEET_PROTOCOL_VERSION, msg->type, msg->node, sp, 2, out, cap);
}

int32_t capsheet_serial_decode_frame(uint8_t *frame, size_t len, capsheet_msg_t *out, uint8_t *version)
{
    int32_t n;
    CAPSHEET_ASSERT(out != NULL && (frame != NULL || len == 0));
    if (len > CAPSHEET_MAX_ENCODED_SIZE) {
        return CAPSHEET_ERR_OVERSIZE;
    }
    n = capsheet_cobs_decode(frame, len, frame, len);
    if (n < 0) {
        return CAPSHEET_ERR_BAD_COBS;
    }
    if ((size_t)n > CAPSHEET_MAX_FRAME_SIZE) {
        return CAPSHEET_ERR_OVERSIZE;  /* COBS of a frame with zeros is shorter than the worst case (§6.3) */
    }
    if ((size_t)n < CAPSHEET_HEADER_SIZE + CAPSHEET_CRC_SIZE) {
        return CAPSHEET_ERR_SHORT;
    }
    if (capsheet_crc16(frame, (size_t)n, CAPSHEET_CRC_INIT) != 0u) {
        return CAPSHEET_ERR_BAD_CRC;
    }
    if (version != NULL) {
        *version = frame[0];
    }
    if (frame[0] != CAPSHEET_PROTOCOL_VERSION) {
        out->type = frame[1];
        out->node = get_u16(frame + 2);
        return CAPSHEET_ERR_BAD_VERSION;
    }
    return capsheet_payload_decode(frame[1], get_u16(frame + 2), frame + CAPSHEET_HEADER_SIZE,
                                   (size_t)n - CAPSHEET_HEADER_SIZE - CAPSHEET_CRC_SIZE, out);
}

int32_t capsheet_stream_init(capsheet_stream_t *s, uint8_t *buf, size_t cap)
{
    CAPSHEET_ASSERT(s != NULL);
    if (buf == NULL || cap == 0u) {
        return CAPSHEET_ERR_ARGUMENT;
    }
    s->buf = buf;
    s->cap = cap;
    s->len = 0;
    s->discarding = false;
    s->version = 0;
    s->frames = 0;
    s->errors = 0;
    return 0;
}

int32_t capsheet_stream_feed(capsheet_stream_t *s, uint8_t byte, capsheet_msg_t *out)
{
    int32_t rc;
    size_t len;
    CAPSHEET_ASSERT(s != NULL && out != NULL && s->buf != NULL && s->len <= s->cap);
    if (byte != 0u) {
        if (s->discarding) {
            return 0;
        }
        if (s->len >= s->cap || s->len >= CAPSHEET_MAX_ENCODED_SIZE) {
            s->len = 0;
            s->discarding = true;
            s->errors++;
            return CAPSHEET_ERR_OVERSIZE;
        }
        s->buf[s->len++] = byte;
        return 0;
    }
    len = s->len;
    s->len = 0;
    if (s->discarding) {
        s->discarding = false;
        return 0;
    }
    if (len == 0u) {
        return 0;  /* idle fill */
    }
    rc = capsheet_serial_decode_frame(s->buf, len, out, &s->version);
    if (rc < 0) {
        s->errors++;
        return rc;
    }
    s->frames++;
    return 1;
}

/* ------------------------------------------------------------------------------------------ */
/* CAN                                                                                         */
/* ------------------------------------------------------------------------------------------ */

uint32_t capsheet_can_make_id(uint8_t priority, uint8_t type, uint8_t version, uint16_t node)
{
    return ((uint32_t)(priority & 0x7u) << 26) | ((uint32_t)(type & 0x3Fu) << 20)
           | ((uint32_t)(version & 0xFu) << 16) | (uint32_t)node;
}

int32_t capsheet_can_fd_length(size_t n)
{
    static const uint8_t k_fd[7] = {12, 16, 20, 24, 32, 48, 64};
    unsigned i;
    if (n <= 8u) {
        return (int32_t)n;
    }
    for (i = 0; i < sizeof k_fd; i++) {
        if (k_fd[i] >= n) {
            return (int32_t)k_fd[i];
        }
    }
    return CAPSHEET_ERR_ARGUMENT;
}

int32_t capsheet_can_encode(const capsheet_msg_t *msg, capsheet_can_mode_t mode, uint32_t *id,
                            uint8_t *data, size_t cap, bool *is_fd)
{
    uint8_t tmp[CAPSHEET_CODEC_FIXED_MAX];
    span_t sp[2];
    int32_t n, padded;
    bool fd;
    CAPSHEET_ASSERT(msg != NULL && id != NULL && data != NULL && is_fd != NULL);
    n = capsheet_codec_payload_spans(msg, tmp, sp);
    if (n < 0) {
        return n;
    }
    fd = (mode == CAPSHEET_CAN_FD) || (mode == CAPSHEET_CAN_AUTO && n > (int32_t)CAPSHEET_CAN_CLASSIC_MTU);
    if (!fd && n > (int32_t)CAPSHEET_CAN_CLASSIC_MTU) {
        return CAPSHEET_ERR_NEEDS_FD;
    }
    padded = fd ? capsheet_can_fd_length((size_t)n) : n;
    if (padded < 0) {
        return CAPSHEET_ERR_NEEDS_FD;  /* over 64 bytes: does not fit any CAN frame */
    }
    if ((size_t)padded > cap) {
        return CAPSHEET_ERR_CAPACITY;
    }
    if (sp[0].n) {
        memcpy(data, sp[0].p, sp[0].n);
    }
    if (sp[1].n) {
        memcpy(data + sp[0].n, sp[1].p, sp[1].n);
    }
    memset(data + n, 0, (size_t)(padded - n));
    *id = capsheet_can_make_id(capsheet_priority(msg->type), msg->type, (uint8_t)CAPSHEET_PROTOCOL_VERSION,
                               msg->node);
    *is_fd = fd;
    return padded;
}

int32_t capsheet_can_decode(uint32_t id, bool is_extended, bool is_fd, const uint8_t *data, size_t len,
                            capsheet_msg_t *out, uint8_t *version)
{
    uint8_t type, ver;
    uint16_t node;
    CAPSHEET_ASSERT(out != NULL && (data != NULL || len == 0));
    if (!is_extended || id >= (1ul << 29)) {
        return CAPSHEET_ERR_BAD_FIELD;
    }
    type = (uint8_t)((id >> 20) & 0x3Fu);
    ver = (uint8_t)((id >> 16) & 0xFu);
    node = (uint16_t)(id & 0xFFFFu);
    out->type = type;
    out->node = node;
    if (version != NULL) {
        *version = ver;
    }
    if (ver != CAPSHEET_PROTOCOL_VERSION) {
        return CAPSHEET_ERR_BAD_VERSION;
    }
    if (len > (is_fd ? CAPSHEET_CAN_FD_MTU : CAPSHEET_CAN_CLASSIC_MTU)
        || (is_fd && capsheet_can_fd_length(len) != (int32_t)len)) {
        return CAPSHEET_ERR_BAD_LENGTH;
    }
#if !CAPSHEET_CHIP_ONLY
    {
        /* the padded types (§7.2, §16.3, §16.5): `need` payload bytes, padded with 0x00 on FD */
        size_t need = 0, expected, i;
        if (type == CAPSHEET_SNAPSHOT && len >= CAPSHEET_SNAPSHOT_HEADER_SIZE) {
            need = CAPSHEET_SNAPSHOT_HEADER_SIZE + CAPSHEET_SAMPLE_WORD_SIZE * (size_t)data[4];
        } else if (type == CAPSHEET_SNAPSHOT_IMU && len >= CAPSHEET_SNAPSHOT_IMU_HEADER_SIZE
                   && capsheet_codec_imu_record_size(data[5]) != 0u) {  /* another format: BAD_FIELD from the payload decoder */
            need = CAPSHEET_SNAPSHOT_IMU_HEADER_SIZE + capsheet_codec_imu_record_size(data[5]) * (size_t)data[4];
        } else if (type == CAPSHEET_IMU_SAMPLE && is_fd) {
            need = (len == 16u) ? 2u + CAPSHEET_IMU6_RECORD_SIZE : (len == 24u) ? 2u + CAPSHEET_IMU9_RECORD_SIZE : 0u;
            if (need == 0u) {
                return CAPSHEET_ERR_BAD_LENGTH;
            }
        }
        if (need == 0u) {
            return capsheet_payload_decode(type, node, data, len, out);
        }
        expected = (is_fd && need <= CAPSHEET_CAN_FD_MTU) ? (size_t)capsheet_can_fd_length(need) : need;
        if (len != expected) {
            return CAPSHEET_ERR_BAD_LENGTH;
        }
        for (i = need; i < len; i++) {
            if (data[i] != 0u) {
                return CAPSHEET_ERR_BAD_FIELD;
            }
        }
        return capsheet_payload_decode(type, node, data, need, out);
    }
#else
    return capsheet_payload_decode(type, node, data, len, out);  /* node -> host types: not decoded */
#endif
}

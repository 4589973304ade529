/* The serial stream decoder's scan in C (docs/protocol.md §6; protocol/framing.py's
 * StreamDecoder uses it when built, its numpy and per-frame Python code otherwise).
 *
 * One pass over a read's bytes: split at 0x00, COBS-decode, check the CRC and the header, and
 * classify each frame; SNAPSHOT words are unpacked as they are decoded. Only frames the exact
 * Python decoder (protocol.framing.decode_frame) would accept are taken; anything else is left
 * to it, so every error is still reported with its reason (tests/protocol/test_stream_kernel.py
 * compares the two on valid, damaged and random input). */
#include "stream.h"

#include <string.h>

static const uint16_t *crc_table(void)
{
    static uint16_t t[256];
    static int ready = 0;
    if (!ready) {
        for (int i = 0; i < 256; ++i) {
            uint16_t c = (uint16_t)(i << 8);
            for (int b = 0; b < 8; ++b)
                c = (uint16_t)((c & 0x8000) ? ((c << 1) ^ 0x1021) : (c << 1));
            t[i] = c;
        }
        ready = 1;
    }
    return t;
}

/* COBS-decode src[0..n) (no 0x00 inside: the caller split there) into dst (room for cap bytes).
 * Returns the decoded length, or -1 for invalid COBS or more than cap bytes: the `cobs` package's
 * rules (a code byte pointing past the end is an error; the last group adds no zero). */
static int64_t cobs_decode(const uint8_t *src, int64_t n, uint8_t *dst, int64_t cap)
{
    int64_t i = 0, o = 0;
    if (n == 0)
        return 0;
    for (;;) {
        const int64_t code = src[i++];
        const int64_t end = i + code - 1;
        if (end > n)
            return -1;
        if (o + (end - i) + 1 > cap + 1)
            return -1;
        memcpy(dst + o, src + i, (size_t)(end - i));
        o += end - i;
        i = end;
        if (i < n) {
            if (code < 0xFF) {
                if (o >= cap)
                    return -1;
                dst[o++] = 0;
            }
        } else {
            break;
        }
    }
    return o;
}

int64_t capsheet_scan_chunk(const uint8_t *chunk, int64_t n, int32_t version, int32_t max_frame,
                            int32_t n_fast, const int32_t *fast_type, const int32_t *fast_len,
                            int32_t snapshot_type, capsheet_scan_t *out)
{
    const uint16_t *T = crc_table();
    uint8_t body[2048];
    int64_t nf = 0, ns = 0, nsamp = 0, s = 0;
    const int64_t max_enc = (int64_t)max_frame + 1 + max_frame / 254;
    for (int64_t p = 0; p < n; ++p) {
        if (chunk[p] != 0)
            continue;
        const int64_t len = p - s, st = s;
        s = p + 1;
        if (len == 0)
            continue;  /* idle fill: not a frame */
        out->start[nf] = st;
        out->length[nf] = len;
        out->kind[nf] = 0;
        if (len <= max_enc) {
            const int64_t m = cobs_decode(chunk + st, len, body, max_frame);
            if (m >= 6) {
                uint16_t crc = 0xFFFF;
                for (int64_t k = 0; k < m; ++k)
                    crc = (uint16_t)((crc << 8) ^ T[((crc >> 8) ^ body[k]) & 0xFF]);
                const int32_t type = body[1];
                const uint32_t node = (uint32_t)body[2] | ((uint32_t)body[3] << 8);
                if (crc == 0 && body[0] == version && node != 0xFFFF) {
                    int32_t k;
                    for (k = 0; k < n_fast; ++k)
                        if (type == fast_type[k] && m == fast_len[k])
                            break;
                    if (k < n_fast) {
                        if (m <= out->row_stride) {
                            memcpy(out->rows + nf * out->row_stride, body, (size_t)m);
                            out->kind[nf] = (int8_t)(k + 1);
                        }
                    } else if (type == snapshot_type) {
                        const uint8_t *pl = body + 4;
                        const int64_t plen = m - 6;
                        if (plen >= 10) {
                            const uint32_t counter = (uint32_t)pl[0] | ((uint32_t)pl[1] << 8);
                            const uint32_t first = (uint32_t)pl[2] | ((uint32_t)pl[3] << 8);
                            const int64_t count = pl[4];
                            if (count >= 1 && plen == 5 + 5 * count && first + count <= 0x10000) {
                                out->kind[nf] = (int8_t)(n_fast + 1);
                                out->snap_node[ns] = (uint16_t)node;
                                out->snap_counter[ns] = (uint16_t)counter;
                                out->snap_first[ns] = (uint16_t)first;
                                out->snap_count[ns] = count;
                                ++ns;
                                for (int64_t j = 0; j < count; ++j) {
                                    const uint8_t *w = pl + 5 + 5 * j;
                                    const uint64_t word = (uint64_t)w[0] | ((uint64_t)w[1] << 8) |
                                                          ((uint64_t)w[2] << 16) | ((uint64_t)w[3] << 24) |
                                                          ((uint64_t)w[4] << 32);
                                    int16_t *c = out->s_counts + 3 * nsamp;
                                    for (int a = 0; a < 3; ++a) {
                                        const int32_t v = (int32_t)((word >> (12 * a)) & 0xFFF);
                                        c[a] = (int16_t)(v >= 0x800 ? v - 0x1000 : v);
                                    }
                                    out->s_status[nsamp] = (uint8_t)(word >> 36);
                                    out->s_counter[nsamp] = (uint16_t)counter;
                                    out->s_link[nsamp] = (int64_t)first + j;
                                    ++nsamp;
                                }
                            }
                        }
                    }
                }
            }
        }
        ++nf;
    }
    out->n_frames = nf;
    out->n_snaps = ns;
    out->n_samples = nsamp;
    return nf;
}

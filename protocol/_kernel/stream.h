/* The serial stream decoder's compiled scan (protocol.framing.StreamDecoder); see stream.c. */
#ifndef CAPSHEET_STREAM_H
#define CAPSHEET_STREAM_H

#include <stdint.h>

/* What a chunk's frames were classified as, and where their decoded parts went. */
typedef struct {
    /* per frame (capacity: the chunk's length / 2 + 1) */
    int64_t *start;         /* offset of the frame's first byte in the chunk */
    int64_t *length;        /* encoded length, without the 0x00 */
    int8_t *kind;           /* 0: not taken (the exact slow path), 1..n_fast: a fast kind, n_fast + 1: SNAPSHOT */
    uint8_t *rows;          /* (frames, row_stride): the decoded frame of a fast kind */
    int64_t row_stride;
    /* per SNAPSHOT frame (capacity: the chunk's length / 16 + 1) */
    uint16_t *snap_node, *snap_counter, *snap_first;
    int64_t *snap_count;
    /* per sample of the SNAPSHOT frames (capacity: the chunk's length / 5 + 1) */
    uint16_t *s_counter;
    int64_t *s_link;
    int16_t *s_counts;      /* (samples, 3) */
    uint8_t *s_status;
    /* out */
    int64_t n_frames, n_snaps, n_samples;
} capsheet_scan_t;

/* Split chunk (n bytes, ending with 0x00) at its delimiters and classify every non-empty frame.
 * A frame is taken (kind != 0) only when it is valid COBS, at most max_frame bytes decoded, its
 * CRC-16/CCITT-FALSE is 0, its version is `version`, its node is not 0xFFFF and either
 *   - its type and decoded length are fast_type[k-1] and fast_len[k-1] (kind k, 1..n_fast), or
 *   - its type is snapshot_type and its payload is a well-formed SNAPSHOT (counter u16,
 *     first_link u16, count u8 >= 1, exactly 5 * count bytes of 40-bit words, first_link + count
 *     <= 65536): kind n_fast + 1, unpacked into the per-sample arrays.
 * Everything else is kind 0, for the caller's exact (slow) decoder to report. Returns n_frames. */
int64_t capsheet_scan_chunk(const uint8_t *chunk, int64_t n, int32_t version, int32_t max_frame,
                            int32_t n_fast, const int32_t *fast_type, const int32_t *fast_len,
                            int32_t snapshot_type, capsheet_scan_t *out);

#endif

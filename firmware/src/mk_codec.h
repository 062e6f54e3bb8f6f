/* MK serial framing (quadlink/mk/PROTOCOL.md): base64 variant, checksum, frame encoder, streaming decoder.
 * Pure C: no AVR registers; compiles on the host for the tests. */
#ifndef QL_MK_CODEC_H
#define QL_MK_CODEC_H

#include <stdint.h>

#define QL_MK_FRAME_START '#'
#define QL_MK_FRAME_END '\r'
#define QL_MK_CHAR_OFFSET 61u           /* '=': 6-bit value 0 */
#define QL_MK_CHAR_MAX (QL_MK_CHAR_OFFSET + 63u) /* '|' */
#define QL_MK_ADDR_ANY 0u
#define QL_MK_ADDR_FC 1u
#define QL_MK_ADDR_MAX 25u              /* 'a' + 25 = 'z' */
#define QL_MK_OVERHEAD 6u               /* '#', address, command, crc1, crc2, '\r' */
/* FlightCtrl's receive buffer holds a whole frame: 220 bytes = 6 + 4 * 53 groups + 2 spare */
#define QL_MK_MAX_FRAME_LEN 220u
#define QL_MK_MAX_PAYLOAD 159u          /* 53 whole groups of 3 bytes */

/* Encoded frame length for a payload of len bytes. */
#define QL_MK_FRAME_LEN(len) (QL_MK_OVERHEAD + 4u * (((len) + 2u) / 3u))

/* Encode one frame into out (room for QL_MK_FRAME_LEN(len) bytes). Returns its length, 0 if the address,
 * command or length is invalid (the frame would not fit the board's receive buffer). */
uint8_t ql_mk_encode(uint8_t *out, uint8_t address, char command, const uint8_t *payload, uint8_t len);

typedef struct {
    uint32_t frames_ok;
    uint32_t bad_checksum;
    uint32_t overlong;
    uint32_t invalid_chars;
    uint32_t malformed;
    uint32_t truncated;
    uint32_t garbage_bytes;
    uint32_t dropped_bytes;
} ql_mk_stats_t;

typedef struct {
    uint8_t address;
    char command;
    uint8_t len; /* whole groups: a multiple of 3, trailing zero padding included */
    uint8_t payload[QL_MK_MAX_PAYLOAD];
} ql_mk_frame_t;

typedef struct {
    /* the per-byte fields first: the AVR's indexed loads reach 63 bytes past a pointer */
    uint8_t len;        /* pending bytes; buf[0] == '#' when len > 0 */
    uint8_t discarding; /* inside an overlong frame: skip to its '\r' or the next '#' */
    ql_mk_stats_t stats;
    uint8_t buf[QL_MK_MAX_FRAME_LEN];
} ql_mk_decoder_t;

void ql_mk_decoder_init(ql_mk_decoder_t *dec);
/* Feed one byte. Returns 1 and fills *out when the byte completes a valid frame, else 0. Never fails. */
uint8_t ql_mk_decoder_feed(ql_mk_decoder_t *dec, uint8_t byte, ql_mk_frame_t *out);
/* Feed bytes until one completes a valid frame or data[0..n) is used up; returns the bytes consumed (>= 1 when
 * n > 0), *got = 1 and *out filled when the last of them completed a frame. The same result and counters as
 * ql_mk_decoder_feed byte by byte, at a fraction of its cycles per byte inside a frame (one call, no byte rules
 * for the frame's plain characters). */
uint8_t ql_mk_decoder_feed_buf(ql_mk_decoder_t *dec, const uint8_t *data, uint8_t n, uint8_t *got,
                               ql_mk_frame_t *out);
/* Frames rejected so far (every drop counter but garbage bytes). */
uint32_t ql_mk_frames_dropped(const ql_mk_stats_t *s);

#endif

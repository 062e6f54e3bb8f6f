/* MK serial framing, written from quadlink/mk/PROTOCOL.md; the decoder follows its decoder rules byte for
 * byte so the board and the Python FrameDecoder count the same drops. */
#include "mk_codec.h"

#include <string.h>

static uint8_t is_letter(uint8_t c) { return (uint8_t)((c >= 'A' && c <= 'Z') || (c >= 'a' && c <= 'z')); }

static uint8_t is_data_char(uint8_t c) { return (uint8_t)(c >= QL_MK_CHAR_OFFSET && c <= QL_MK_CHAR_MAX); }

uint8_t ql_mk_encode(uint8_t *out, uint8_t address, char command, const uint8_t *payload, uint8_t len)
{
    if (address > QL_MK_ADDR_MAX || !is_letter((uint8_t)command) || len > QL_MK_MAX_PAYLOAD) {
        return 0;
    }
    /* the checksum (from '#' through the last data character, modulo 4096) summed as the bytes are written:
     * no second pass over the frame */
    uint8_t n = 0;
    uint8_t head0 = (uint8_t)('a' + address);
    uint16_t sum = (uint16_t)(QL_MK_FRAME_START + head0 + (uint8_t)command);
    out[n++] = QL_MK_FRAME_START;
    out[n++] = head0;
    out[n++] = (uint8_t)command;
    for (uint8_t i = 0; i < len; i = (uint8_t)(i + 3u)) {
        /* a short last group is zero-padded */
        uint8_t a = payload[i];
        uint8_t b = (uint8_t)(i + 1u < len ? payload[i + 1u] : 0u);
        uint8_t c = (uint8_t)(i + 2u < len ? payload[i + 2u] : 0u);
        uint8_t e0 = (uint8_t)(QL_MK_CHAR_OFFSET + (a >> 2));
        uint8_t e1 = (uint8_t)(QL_MK_CHAR_OFFSET + (((a & 3u) << 4) | (b >> 4)));
        uint8_t e2 = (uint8_t)(QL_MK_CHAR_OFFSET + (((b & 15u) << 2) | (c >> 6)));
        uint8_t e3 = (uint8_t)(QL_MK_CHAR_OFFSET + (c & 63u));
        out[n++] = e0;
        out[n++] = e1;
        out[n++] = e2;
        out[n++] = e3;
        sum = (uint16_t)(sum + e0 + e1 + e2 + e3);
    }
    sum &= 0x0FFFu; /* modulo 4096 */
    out[n++] = (uint8_t)(QL_MK_CHAR_OFFSET + (sum >> 6));
    out[n++] = (uint8_t)(QL_MK_CHAR_OFFSET + (sum & 63u));
    out[n++] = QL_MK_FRAME_END;
    return n;
}

void ql_mk_decoder_init(ql_mk_decoder_t *dec) { memset(dec, 0, sizeof(*dec)); }

uint32_t ql_mk_frames_dropped(const ql_mk_stats_t *s)
{
    return s->bad_checksum + s->overlong + s->invalid_chars + s->malformed + s->truncated;
}

/* Validate buf[0..n) = '#' addr cmd chars crc1 crc2 (no '\r'); 1 and the frame if valid, else count the drop. */
/* noinline: keeps the per-byte path of ql_mk_decoder_feed free of the register saves this needs */
__attribute__((noinline)) static uint8_t check_body(ql_mk_decoder_t *dec, uint8_t n, ql_mk_frame_t *out)
{
    const uint8_t *d = dec->buf;
    ql_mk_stats_t *s = &dec->stats;
    if (n < 5u || ((uint8_t)(n - 5u) & 3u) != 0u) {
        s->malformed++;
        return 0;
    }
    if (d[1] < 'a' || d[1] > 'a' + QL_MK_ADDR_MAX || !is_letter(d[2])) {
        s->invalid_chars++;
        return 0;
    }
    /* one pass: the characters' range and the checksum (from '#' through the last data character) */
    uint16_t sum = (uint16_t)(d[0] + d[1] + d[2]);
    for (uint8_t i = 3; i < n; i++) {
        if (!is_data_char(d[i])) {
            s->invalid_chars++;
            return 0;
        }
        if (i < (uint8_t)(n - 2u)) {
            sum = (uint16_t)(sum + d[i]);
        }
    }
    sum &= 0x0FFFu;
    if (d[n - 2u] != QL_MK_CHAR_OFFSET + (sum >> 6) || d[n - 1u] != QL_MK_CHAR_OFFSET + (sum & 63u)) {
        s->bad_checksum++;
        return 0;
    }
    out->address = (uint8_t)(d[1] - 'a');
    out->command = (char)d[2];
    uint8_t len = 0;
    for (uint8_t i = 3; i + 4u <= (uint8_t)(n - 2u); i = (uint8_t)(i + 4u)) {
        uint8_t v0 = (uint8_t)(d[i] - QL_MK_CHAR_OFFSET), v1 = (uint8_t)(d[i + 1u] - QL_MK_CHAR_OFFSET);
        uint8_t v2 = (uint8_t)(d[i + 2u] - QL_MK_CHAR_OFFSET), v3 = (uint8_t)(d[i + 3u] - QL_MK_CHAR_OFFSET);
        out->payload[len++] = (uint8_t)((v0 << 2) | (v1 >> 4));
        out->payload[len++] = (uint8_t)((v1 << 4) | (v2 >> 2));
        out->payload[len++] = (uint8_t)((v2 << 6) | v3);
    }
    out->len = len;
    s->frames_ok++;
    return 1;
}

uint8_t ql_mk_decoder_feed(ql_mk_decoder_t *dec, uint8_t byte, ql_mk_frame_t *out)
{
    ql_mk_stats_t *s = &dec->stats;
    if (dec->discarding) {
        if (byte != QL_MK_FRAME_START) {
            s->dropped_bytes++; /* the overlong frame's bytes through its '\r' */
            if (byte == QL_MK_FRAME_END) {
                dec->discarding = 0;
            }
            return 0;
        }
        dec->discarding = 0; /* a '#' ends the skip and starts a frame */
    }
    if (dec->len == 0u) {
        if (byte == QL_MK_FRAME_START) {
            dec->buf[0] = byte;
            dec->len = 1;
        } else {
            s->garbage_bytes++;
        }
        return 0;
    }
    if (byte == QL_MK_FRAME_START) { /* a new frame before this one ended */
        s->truncated++;
        s->dropped_bytes += dec->len;
        dec->buf[0] = byte;
        dec->len = 1;
        return 0;
    }
    if (byte == QL_MK_FRAME_END) {
        uint8_t n = dec->len;
        dec->len = 0;
        if (check_body(dec, n, out)) {
            return 1;
        }
        s->dropped_bytes += (uint32_t)n + 1u;
        return 0;
    }
    dec->buf[dec->len++] = byte;
    if (dec->len >= QL_MK_MAX_FRAME_LEN) { /* max length and no '\r' yet: can never fit */
        s->overlong++;
        s->dropped_bytes += dec->len;
        dec->len = 0;
        dec->discarding = 1;
    }
    return 0;
}

uint8_t ql_mk_decoder_feed_buf(ql_mk_decoder_t *dec, const uint8_t *data, uint8_t n, uint8_t *got,
                               ql_mk_frame_t *out)
{
    ql_mk_stats_t *s = &dec->stats;
    uint8_t i = 0;
    *got = 0;
    while (i < n) {
        uint8_t len = dec->len;
        uint8_t start = i;
        /* runs of bytes the byte rules would only count, counted once per run (a flood of junk costs the loop
         * per byte what a frame does) */
        if (len == 0u) { /* outside a frame: garbage, or the rest of an overlong frame, up to a '#' (or '\r') */
            if (dec->discarding) {
                while (i < n && data[i] != QL_MK_FRAME_START && data[i] != QL_MK_FRAME_END) {
                    i++;
                }
                if (i != start) {
                    s->dropped_bytes += (uint8_t)(i - start);
                }
            } else {
                while (i < n && data[i] != QL_MK_FRAME_START) {
                    i++;
                }
                if (i != start) {
                    s->garbage_bytes += (uint8_t)(i - start);
                }
            }
        } else if (len == 1u) { /* '#' then more '#': each one truncates the one-byte frame before it */
            while (i < n && data[i] == QL_MK_FRAME_START) {
                i++;
            }
            if (i != start) {
                s->truncated += (uint8_t)(i - start);
                s->dropped_bytes += (uint8_t)(i - start);
            }
        }
        if (i == n) {
            break;
        }
        if (len != 0u) { /* inside a frame (never while discarding): copy plain bytes without the byte rules */
            uint8_t *buf = dec->buf;
            while (i < n) {
                uint8_t b = data[i];
                if (b == QL_MK_FRAME_START || b == QL_MK_FRAME_END || len >= QL_MK_MAX_FRAME_LEN - 1u) {
                    break; /* ends or restarts the frame, or makes it overlong: the byte rules below decide */
                }
                buf[len++] = b;
                i++;
            }
            dec->len = len;
            if (i == n) {
                break;
            }
        }
        if (ql_mk_decoder_feed(dec, data[i++], out)) {
            *got = 1;
            break;
        }
    }
    return i;
}

/* Host-only flat API over the pure modules for the pytest suite (ctypes): no struct layouts cross the
 * boundary except opaque blobs whose sizes the tests ask for. Never built for the AVR. */
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "../src/attitude.h"
#include "../src/baro.h"
#include "../src/control.h"
#include "../src/fc.h"
#include "../src/fxmath.h"
#include "../src/mk_codec.h"
#include "../src/mk_msgs.h"
#include "../src/params.h"
#include "../src/safety.h"
#include "../src/sensors.h"

/* the constants the Python mirror must share */
const double qlh_gyro_lsb_rad_s = QL_GYRO_LSB_RAD_S;
const double qlh_accel_lsb_m_s2 = QL_ACCEL_LSB_M_S2;
const int qlh_imu_zero_count = QL_IMU_ZERO_COUNT;
const int qlh_att_cal_ticks = QL_ATT_CAL_TICKS;
const int qlh_baro_oversample = QL_BARO_OVERSAMPLE;
const int qlh_max_frame_len = QL_MK_MAX_FRAME_LEN;
const int qlh_params_image_len = QL_PARAMS_IMAGE_LEN;

/* ---- codec ---- */
size_t qlh_decoder_size(void) { return sizeof(ql_mk_decoder_t); }

/* Feed n bytes; completed frames are written to out as [address, command, len, payload...]; returns the number
 * of frames (stops writing, but keeps decoding, when out is full). batch 0: byte by byte (ql_mk_decoder_feed);
 * batch k: in chunks of at most k bytes through ql_mk_decoder_feed_buf (the firmware's main loop takes 32). */
int qlh_decoder_feed(ql_mk_decoder_t *dec, const uint8_t *data, int n, uint8_t *out, int cap, int batch)
{
    static ql_mk_frame_t f;
    int frames = 0, pos = 0;
    int chunk_end = 0;
    for (int i = 0; i < n;) {
        uint8_t got;
        if (batch <= 0) {
            got = ql_mk_decoder_feed(dec, data[i++], &f);
        } else {
            if (i >= chunk_end) {
                chunk_end = i + (batch > 255 ? 255 : batch);
            }
            int left = (chunk_end < n ? chunk_end : n) - i;
            i += ql_mk_decoder_feed_buf(dec, data + i, (uint8_t)left, &got, &f);
        }
        if (got) {
            frames++;
            if (pos + 3 + f.len <= cap) {
                out[pos++] = f.address;
                out[pos++] = (uint8_t)f.command;
                out[pos++] = f.len;
                memcpy(out + pos, f.payload, f.len);
                pos += f.len;
            }
        }
    }
    return frames;
}

void qlh_decoder_stats(const ql_mk_decoder_t *dec, uint32_t out[9])
{
    const ql_mk_stats_t *s = &dec->stats;
    out[0] = s->frames_ok;
    out[1] = s->bad_checksum;
    out[2] = s->overlong;
    out[3] = s->invalid_chars;
    out[4] = s->malformed;
    out[5] = s->truncated;
    out[6] = s->garbage_bytes;
    out[7] = s->dropped_bytes;
    out[8] = dec->len;
}

/* ---- messages ---- */
int qlh_pack_imu(uint8_t *out, const uint16_t accel[3], const uint16_t gyro[3], uint16_t counter)
{
    ql_imu_msg_t m;
    memcpy(m.accel, accel, sizeof(m.accel));
    memcpy(m.gyro, gyro, sizeof(m.gyro));
    m.counter = counter;
    return ql_pack_imu(out, &m);
}

int qlh_unpack_imu(const uint8_t *in, int len, uint16_t out[7])
{
    ql_imu_msg_t m;
    if (!ql_unpack_imu(in, (uint8_t)len, &m)) {
        return 0;
    }
    memcpy(out, m.accel, 6);
    memcpy(out + 3, m.gyro, 6);
    out[6] = m.counter;
    return 1;
}

int qlh_pack_setpoint(uint8_t *out, int16_t roll, int16_t pitch, int16_t yaw_rate, uint16_t thrust, uint8_t flags,
                      uint8_t seq)
{
    ql_setpoint_msg_t m = {roll, pitch, yaw_rate, thrust, flags, seq};
    return ql_pack_setpoint(out, &m);
}

int qlh_unpack_setpoint(const uint8_t *in, int len, int32_t out[6])
{
    ql_setpoint_msg_t m;
    if (!ql_unpack_setpoint(in, (uint8_t)len, &m)) {
        return 0;
    }
    out[0] = m.roll_cdeg;
    out[1] = m.pitch_cdeg;
    out[2] = m.yaw_rate_ddeg_s;
    out[3] = m.thrust;
    out[4] = m.flags;
    out[5] = m.seq;
    return 1;
}

int qlh_pack_status(uint8_t *out, uint8_t flags, uint8_t state, uint16_t mv, uint16_t errors, uint32_t t_ms,
                    uint32_t count, uint8_t seq)
{
    ql_status_msg_t m = {flags, state, mv, errors, t_ms, count, seq};
    return ql_pack_status(out, &m);
}

int qlh_pack_baro(uint8_t *out, int32_t alt_cm, int16_t climb_cm_s, uint32_t pa, uint8_t flags, uint8_t seq)
{
    ql_baro_msg_t m = {alt_cm, climb_cm_s, pa, flags, seq};
    return ql_pack_baro(out, &m);
}

int qlh_pack_data3d(uint8_t *out, const int16_t angle[3], const uint8_t centroid[3], const uint8_t reserve[5])
{
    ql_data3d_msg_t m;
    memcpy(m.angle_ddeg, angle, sizeof(m.angle_ddeg));
    memcpy(m.centroid, centroid, 3);
    memcpy(m.reserve, reserve, 5);
    return ql_pack_data3d(out, &m);
}

/* ---- attitude ---- */
size_t qlh_att_size(void) { return sizeof(ql_attitude_t); }

void qlh_att_get(const ql_attitude_t *a, int32_t out[11])
{
    out[0] = a->roll_q24;
    out[1] = a->pitch_q24;
    out[2] = a->yaw_q24;
    for (int i = 0; i < 3; i++) {
        out[3 + i] = a->rate_q8[i];
        out[6 + i] = a->bias_q16[i];
    }
    out[9] = a->calibrated;
    out[10] = a->saturated;
}

/* ---- baro ---- */
size_t qlh_baro_size(void) { return sizeof(ql_baro_t); }

void qlh_baro_get(const ql_baro_t *b, int32_t out[9])
{
    out[0] = b->p16;
    out[1] = b->pf16;
    out[2] = b->pref_q12;
    out[3] = b->h_q8;
    out[4] = b->v_t16;
    out[5] = ql_baro_valid(b);
    out[6] = b->saturated;
    out[7] = ql_baro_altitude_cm(b);
    out[8] = ql_baro_climb_cm_s(b);
}

/* ---- params ---- */
size_t qlh_params_size(void) { return sizeof(ql_params_t); }

void qlh_params_get(const ql_params_t *p, float out[25])
{
    const float v[25] = {p->angle_kp_1_s,         p->rate_kp_1_s,
                         p->rate_ki_1_s2,         p->rate_kd,
                         p->yaw_rate_kp_1_s,      p->yaw_rate_ki_1_s2,
                         p->max_tilt_rad,         p->max_rate_rad_s,
                         p->max_yaw_rate_rad_s,   p->integrator_limit_rad_s2,
                         p->setpoint_timeout_s,   p->landed_thrust_fraction,
                         p->failsafe_descent_m_s, p->failsafe_ground_speed_m_s,
                         p->mass_kg,              p->inertia_kg_m2[0],
                         p->inertia_kg_m2[1],     p->inertia_kg_m2[2],
                         p->arm_length_m,         (float)p->frame_x,
                         p->max_thrust_n,         p->idle_fraction,
                         p->drag_torque_per_thrust_m, (float)p->battery_low_mv,
                         (float)p->version};
    memcpy(out, v, sizeof(v));
}

void qlh_params_set_gain(ql_params_t *p, int index, float value)
{
    switch (index) { /* no pointers into the packed struct */
    case 0: p->angle_kp_1_s = value; break;
    case 1: p->rate_kp_1_s = value; break;
    case 2: p->rate_ki_1_s2 = value; break;
    case 3: p->rate_kd = value; break;
    case 4: p->yaw_rate_kp_1_s = value; break;
    case 5: p->yaw_rate_ki_1_s2 = value; break;
    default: break;
    }
}

/* ---- control ---- */
size_t qlh_ctrl_size(void) { return sizeof(ql_ctrl_t); }

/* SI floats in and out (the tests compare with sim_sitl's float model); the loop itself is integer */
static const float k_rate_r = QL_GYRO_LSB_RAD_S / 256.0f;

void qlh_ctrl_step(ql_ctrl_t *c, const ql_params_t *p, const float cmd[4], int landed, const int32_t att_q24[2],
                   const int32_t rate_r[3], float motor_n[4])
{
    ql_att_cmd_t k = {lroundf(cmd[0] * 16777216.0f), lroundf(cmd[1] * 16777216.0f), lroundf(cmd[2] / k_rate_r),
                      lroundf(cmd[3] * 4.0f * p->max_thrust_n * 65536.0f)};
    int32_t m[4];
    ql_ctrl_step(c, &k, (uint8_t)landed, att_q24[0], att_q24[1], rate_r, m);
    for (int i = 0; i < 4; i++) {
        motor_n[i] = (float)m[i] / 65536.0f;
    }
}

void qlh_mix(const ql_ctrl_t *c, float thrust_n, const float torque_nm[3], float motor_n[4])
{
    int32_t t[3] = {lroundf(torque_nm[0] * 65536.0f), lroundf(torque_nm[1] * 65536.0f),
                    lroundf(torque_nm[2] * 65536.0f)};
    int32_t m[4];
    ql_mix(c, lroundf(thrust_n * 65536.0f), t, m);
    for (int i = 0; i < 4; i++) {
        motor_n[i] = (float)m[i] / 65536.0f;
    }
}

int qlh_motor_byte(const ql_ctrl_t *c, float thrust_n) { return ql_motor_byte(c, lroundf(thrust_n * 65536.0f)); }

void qlh_ctrl_integ(const ql_ctrl_t *c, float out[3])
{
    for (int i = 0; i < 3; i++) {
        out[i] = (float)c->integ_q24[i] / 16777216.0f;
    }
}

/* ---- safety ---- */
size_t qlh_safety_size(void) { return sizeof(ql_safety_t); }

int qlh_safety_on_setpoint(ql_safety_t *s, const ql_params_t *p, int16_t roll, int16_t pitch, int16_t yaw_rate,
                           uint16_t thrust, uint8_t flags, uint8_t seq, uint32_t tick)
{
    ql_setpoint_msg_t m = {roll, pitch, yaw_rate, thrust, flags, seq};
    return ql_safety_on_setpoint(s, p, &m, tick);
}

int qlh_safety_step(ql_safety_t *s, const ql_params_t *p, uint32_t tick, float climb, int valid, int acc1g,
                    float fly[4])
{
    ql_att_cmd_t k = {0, 0, 0, 0};
    int run = ql_safety_step(s, p, tick, lroundf(climb * QL_CLIMB_T16_PER_M_S), (uint8_t)valid, (uint8_t)acc1g, &k);
    fly[0] = (float)k.roll_q24 / 16777216.0f;
    fly[1] = (float)k.pitch_q24 / 16777216.0f;
    fly[2] = (float)k.yaw_rate_r * k_rate_r;
    fly[3] = (float)k.thrust_f / (4.0f * p->max_thrust_n * 65536.0f);
    return run;
}

void qlh_safety_state(const ql_safety_t *s, int32_t out[4])
{
    out[0] = s->armed;
    out[1] = s->failsafe;
    out[2] = s->flight_state;
    out[3] = s->error_flags;
}

/* ---- the whole board core with captured port output ---- */
#define QLH_CAP 65536
typedef struct {
    ql_fc_t fc;
    uint8_t out[2][QLH_CAP];
    int len[2];
    int room[2]; /* free bytes the fake ring offers per tick (-1: unlimited) */
} qlh_board_t;

static uint8_t capture(void *ctx, uint8_t port, const uint8_t *frame, uint8_t len)
{
    qlh_board_t *b = (qlh_board_t *)ctx;
    if ((b->room[port] >= 0 && len > b->room[port]) || b->len[port] + len > QLH_CAP) {
        return 0;
    }
    if (b->room[port] >= 0) {
        b->room[port] -= len;
    }
    memcpy(b->out[port] + b->len[port], frame, len);
    b->len[port] += len;
    return 1;
}

qlh_board_t *qlh_board_new(const uint8_t *image, int image_len)
{
    qlh_board_t *b = calloc(1, sizeof(*b));
    b->room[0] = b->room[1] = -1;
    ql_fc_init(&b->fc, image, (uint16_t)image_len, capture, b);
    return b;
}

void qlh_board_free(qlh_board_t *b) { free(b); }

void qlh_board_set_room(qlh_board_t *b, int port, int room) { b->room[port] = room; }

void qlh_board_rx(qlh_board_t *b, const uint8_t *data, int n)
{
    for (int i = 0; i < n; i += 255) { /* the main loop's batch path */
        ql_fc_rx_bytes(&b->fc, data + i, (uint8_t)(n - i > 255 ? 255 : n - i));
    }
}

void qlh_board_tick(qlh_board_t *b, const uint16_t accel[3], const uint16_t gyro[3], const uint16_t baro[8],
                    uint16_t battery)
{
    ql_adc_sweep_t s;
    memcpy(s.accel, accel, 6);
    memcpy(s.gyro, gyro, 6);
    memcpy(s.baro, baro, sizeof(s.baro));
    s.battery = battery;
    ql_fc_tick(&b->fc, &s);
}

int qlh_board_take(qlh_board_t *b, int port, uint8_t *out, int cap)
{
    int n = b->len[port] < cap ? b->len[port] : cap;
    memcpy(out, b->out[port], (size_t)n);
    memmove(b->out[port], b->out[port] + n, (size_t)(b->len[port] - n));
    b->len[port] -= n;
    return n;
}

void qlh_board_state(const qlh_board_t *b, int32_t out[12])
{
    const ql_fc_t *fc = &b->fc;
    out[0] = fc->safety.armed;
    out[1] = fc->safety.failsafe;
    out[2] = fc->safety.flight_state;
    for (int i = 0; i < 4; i++) {
        out[3 + i] = fc->motor[i];
    }
    out[7] = (int32_t)fc->tx_dropped[0];
    out[8] = (int32_t)fc->tx_dropped[1];
    out[9] = (int32_t)fc->tick;
    out[10] = fc->params_ok;
    out[11] = (int32_t)ql_mk_frames_dropped(&fc->dec.stats);
}

void qlh_board_set_busy(qlh_board_t *b, uint16_t busy, uint16_t busy_max)
{
    b->fc.busy_cycles = busy;
    b->fc.busy_max = busy_max;
}

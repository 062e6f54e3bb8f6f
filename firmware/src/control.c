#include "control.h"

#include <math.h>

#include "fxmath.h"
#include "sensors.h"

#define RATE_R_RAD_S (QL_GYRO_LSB_RAD_S / 256.0f) /* rad/s per R */

static int32_t clamp32(int32_t v, int32_t lim) { return v > lim ? lim : (v < -lim ? -lim : v); }

static int32_t q(float v) { return (int32_t)lroundf(v); }

void ql_ctrl_init(ql_ctrl_t *c, const ql_params_t *p)
{
    /* Rotor positions in MK order (x: front-right, rear-left, rear-right, front-left; +: front, rear, right,
     * left), spin +1 for the rotors whose reaction yaws the body right. The allocation rows [1; -y; x; spin k]
     * are orthogonal for both frames, so its inverse is A^T scaled by 1 / |row|^2. */
    static const float ang_x_deg[QL_MOTORS] = {45.0f, -135.0f, 135.0f, -45.0f};
    static const float ang_p_deg[QL_MOTORS] = {0.0f, 180.0f, 90.0f, -90.0f};
    static const float spin[QL_MOTORS] = {1.0f, 1.0f, -1.0f, -1.0f};
    float x[QL_MOTORS], y[QL_MOTORS];
    float sx = 0.0f, sy = 0.0f;
    for (uint8_t i = 0; i < QL_MOTORS; i++) {
        float a = (p->frame_x ? ang_x_deg[i] : ang_p_deg[i]) * ((float)M_PI / 180.0f);
        x[i] = p->arm_length_m * cosf(a);
        y[i] = p->arm_length_m * sinf(a);
        sx += x[i] * x[i];
        sy += y[i] * y[i];
    }
    const float k = p->drag_torque_per_thrust_m;
    const float mix_scale = (float)(1L << QL_MIX_SHIFT);
    for (uint8_t i = 0; i < QL_MOTORS; i++) { /* A^-1 columns: -y / sum(y^2), x / sum(x^2), spin / (4 k) */
        float col[3] = {-y[i] / sy, x[i] / sx, spin[i] / (4.0f * k)};
        for (uint8_t j = 0; j < 3u; j++) {
            float mag = fabsf(col[j]);
            int8_t sign = (int8_t)(mag < 1e-3f ? 0 : (col[j] > 0.0f ? 1 : -1));
            c->mix_sign[i][j] = sign;
            if (sign != 0) {
                c->mix_gain[j] = q(mag * mix_scale);
            }
        }
    }
    const float dt = 1.0f / (float)QL_LOOP_HZ;
    const float L = RATE_R_RAD_S;
    const float J[3] = {p->inertia_kg_m2[0], p->inertia_kg_m2[1], p->inertia_kg_m2[2]}; /* packed struct */
    c->ka = q(p->angle_kp_1_s / (65536.0f * L) * 4096.0f);
    c->max_rate_r = q(p->max_rate_rad_s / L);
    for (uint8_t j = 0; j < 3u; j++) {
        const float kp = j < 2u ? p->rate_kp_1_s : p->yaw_rate_kp_1_s;
        const float ki = j < 2u ? p->rate_ki_1_s2 : p->yaw_rate_ki_1_s2;
        c->kp_j[j] = q(kp * J[j] * L * 65536.0f * 4096.0f);
        c->ki[j] = q(ki * L * dt * 16777216.0f * 256.0f);
        c->ilim_q24[j] = q(p->integrator_limit_rad_s2 * 16777216.0f);
        c->j_q18[j] = q(J[j] * 262144.0f);
        if (j < 2u) {
            c->kd_j[j] = q(p->rate_kd * J[j] * L / dt * 65536.0f * 4096.0f);
        }
    }
    /* w x (J w) = ((Jz - Jy) wy wz, (Jx - Jz) wz wx, (Jy - Jx) wx wy) */
    const float w64 = 64.0f * L;
    c->gyro_k[0] = q((J[2] - J[1]) * w64 * w64 * 65536.0f * 1048576.0f);
    c->gyro_k[1] = q((J[0] - J[2]) * w64 * w64 * 65536.0f * 1048576.0f);
    c->gyro_k[2] = q((J[1] - J[0]) * w64 * w64 * 65536.0f * 1048576.0f);
    c->max_f = q(p->max_thrust_n * 65536.0f);
    c->min_f = q(p->idle_fraction * p->max_thrust_n * 65536.0f);
    c->byte_k = q(255.0f * 65536.0f / (p->max_thrust_n * 65536.0f)); /* Q16: 51 for 5 N, exact */
    ql_ctrl_reset(c);
}

void ql_ctrl_reset(ql_ctrl_t *c)
{
    for (uint8_t i = 0; i < 3u; i++) {
        c->integ_q24[i] = 0;
        c->prev_rate_r[i] = 0;
    }
    c->have_prev = 0;
}

void ql_mix(const ql_ctrl_t *c, int32_t thrust_f, const int32_t torque_t[3], int32_t motor_f[QL_MOTORS])
{
    int32_t term[3], diff[QL_MOTORS];
    for (uint8_t j = 0; j < 3u; j++) {
        term[j] = (clamp32(torque_t[j], QL_T_LIMIT) * c->mix_gain[j]) >> QL_MIX_SHIFT;
    }
    int32_t lo = 0, hi = 0;
    for (uint8_t i = 0; i < QL_MOTORS; i++) {
        int32_t d = 0;
        for (uint8_t j = 0; j < 3u; j++) {
            d = c->mix_sign[i][j] > 0 ? d + term[j] : (c->mix_sign[i][j] < 0 ? d - term[j] : d);
        }
        diff[i] = d;
        if (i == 0u || d < lo) {
            lo = d;
        }
        if (i == 0u || d > hi) {
            hi = d;
        }
    }
    const int32_t room = c->max_f - c->min_f;
    const int32_t span = hi - lo;
    if (span > room) { /* the torque alone exceeds the motors' range: scale it down (Q12 factor; diff / 16
                          * keeps the product in int32 for |diff| < 2^27) */
        int32_t s = (room << 12) / span;
        for (uint8_t i = 0; i < QL_MOTORS; i++) {
            diff[i] = (QL_RSHIFT(diff[i], 4) * s) >> 8;
        }
        lo = (QL_RSHIFT(lo, 4) * s) >> 8;
        hi = (QL_RSHIFT(hi, 4) * s) >> 8;
    }
    int32_t base = thrust_f >> 2;
    if (base + hi > c->max_f) { /* attitude before altitude: shift the collective */
        base = c->max_f - hi;
    } else if (base + lo < c->min_f) {
        base = c->min_f - lo;
    }
    for (uint8_t i = 0; i < QL_MOTORS; i++) {
        int32_t m = base + diff[i];
        motor_f[i] = m < c->min_f ? c->min_f : (m > c->max_f ? c->max_f : m);
    }
}

void ql_ctrl_step(ql_ctrl_t *c, const ql_att_cmd_t *cmd, uint8_t landed, int32_t roll_q24, int32_t pitch_q24,
                  const int32_t rate_r[3], int32_t motor_f[QL_MOTORS])
{
    int32_t rate_sp[3], torque[3];
    /* angle P: the error clamped to 2 rad first (the rate clamp is reached at 0.5 rad) to stay in int32 */
    rate_sp[0] = clamp32((clamp32(QL_RSHIFT(cmd->roll_q24 - roll_q24, 8), INT32_C(131072)) * c->ka) >> 12,
                         c->max_rate_r);
    rate_sp[1] = clamp32((clamp32(QL_RSHIFT(cmd->pitch_q24 - pitch_q24, 8), INT32_C(131072)) * c->ka) >> 12,
                         c->max_rate_r);
    rate_sp[2] = cmd->yaw_rate_r;
    for (uint8_t i = 0; i < 3u; i++) {
        int32_t err = clamp32(rate_sp[i] - rate_r[i], QL_ERR_LIMIT_R);
        c->integ_q24[i] = landed ? 0 : clamp32(c->integ_q24[i] + ((err * c->ki[i]) >> 8), c->ilim_q24[i]);
        torque[i] = ((err * c->kp_j[i]) >> 12) + (((c->integ_q24[i] >> 12) * c->j_q18[i]) >> 14);
        if (i < 2u && c->have_prev) {
            torque[i] -= (clamp32(rate_r[i] - c->prev_rate_r[i], QL_ERR_LIMIT_R) * c->kd_j[i]) >> 12;
        }
        c->prev_rate_r[i] = rate_r[i];
    }
    c->have_prev = 1;
    /* gyroscopic feed-forward, rates in units of 64 R (|w| <= 2^11 for the gyro's range) */
    int32_t w[3];
    for (uint8_t i = 0; i < 3u; i++) {
        w[i] = clamp32(rate_r[i] >> 6, INT32_C(4095));
    }
    /* |w| <= 4095: 16 x 16 -> 32 bit products */
    torque[0] += ((((int32_t)(int16_t)w[1] * (int16_t)w[2]) >> 6) * c->gyro_k[0]) >> 14;
    torque[1] += ((((int32_t)(int16_t)w[2] * (int16_t)w[0]) >> 6) * c->gyro_k[1]) >> 14;
    torque[2] += ((((int32_t)(int16_t)w[0] * (int16_t)w[1]) >> 6) * c->gyro_k[2]) >> 14;
    int32_t thrust = cmd->thrust_f < 0 ? 0 : (cmd->thrust_f > 4 * c->max_f ? 4 * c->max_f : cmd->thrust_f);
    ql_mix(c, thrust, torque, motor_f);
}

uint8_t ql_motor_byte(const ql_ctrl_t *c, int32_t thrust_f)
{
    int32_t b = (thrust_f * c->byte_k + (INT32_C(1) << 15)) >> 16; /* a shift by 16: the high word, no loop */
    return (uint8_t)(b < 1 ? 1 : (b > 255 ? 255 : b));
}

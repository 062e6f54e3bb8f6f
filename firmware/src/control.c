#include "control.h"

#include <math.h>

#include "sensors.h"

static float clampf(float v, float lo, float hi) { return v < lo ? lo : (v > hi ? hi : v); }

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
    float k = p->drag_torque_per_thrust_m;
    c->motor_bytes_per_n = 255.0f / p->max_thrust_n;
    c->mix_gain[0] = 0.0f;
    c->mix_gain[1] = 0.0f;
    for (uint8_t i = 0; i < QL_MOTORS; i++) { /* A^-1 columns: -y / sum(y^2), x / sum(x^2), spin / (4 k) */
        float col[3] = {-y[i] / sy, x[i] / sx, spin[i] / (4.0f * k)};
        for (uint8_t j = 0; j < 3u; j++) {
            float mag = col[j] < 0.0f ? -col[j] : col[j];
            int8_t sign = (int8_t)(mag < 1e-6f * (1.0f / p->arm_length_m) ? 0 : (col[j] > 0.0f ? 1 : -1));
            c->mix_sign[i][j] = sign;
            if (sign != 0) {
                c->mix_gain[j] = mag;
            }
        }
    }
    const float dt = 1.0f / (float)QL_LOOP_HZ;
    for (uint8_t j = 0; j < 3u; j++) {
        const float J = p->inertia_kg_m2[j];
        c->kp_j[j] = J * (j < 2u ? p->rate_kp_1_s : p->yaw_rate_kp_1_s);
        c->ki_j_dt[j] = J * (j < 2u ? p->rate_ki_1_s2 : p->yaw_rate_ki_1_s2) * dt;
        c->ilim_j[j] = J * p->integrator_limit_rad_s2;
        if (j < 2u) {
            c->kd_j_dt[j] = J * p->rate_kd / dt;
        }
    }
    ql_ctrl_reset(c);
}

void ql_ctrl_reset(ql_ctrl_t *c)
{
    for (uint8_t i = 0; i < 3u; i++) {
        c->integ[i] = 0.0f;
        c->prev_rates[i] = 0.0f;
    }
    c->have_prev = 0;
}

void ql_mix(const ql_ctrl_t *c, float thrust_n, const float torque_nm[3], float min_n, float max_n,
            float motor_n[QL_MOTORS])
{
    float diff[QL_MOTORS];
    float term[3];
    for (uint8_t j = 0; j < 3u; j++) {
        term[j] = c->mix_gain[j] * torque_nm[j];
    }
    float lo = 0.0f, hi = 0.0f;
    for (uint8_t i = 0; i < QL_MOTORS; i++) {
        float d = 0.0f;
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
    float span = hi - lo;
    float room = max_n - min_n;
    if (span > room) { /* the torque alone exceeds the motors' range: scale it down */
        float s = room / span;
        for (uint8_t i = 0; i < QL_MOTORS; i++) {
            diff[i] *= s;
        }
        lo *= s;
        hi *= s;
    }
    float base = thrust_n * 0.25f;
    if (base + hi > max_n) { /* attitude before altitude: shift the collective */
        base = max_n - hi;
    } else if (base + lo < min_n) {
        base = min_n - lo;
    }
    for (uint8_t i = 0; i < QL_MOTORS; i++) {
        motor_n[i] = clampf(base + diff[i], min_n, max_n);
    }
}

void ql_ctrl_step(ql_ctrl_t *c, const ql_params_t *p, const ql_att_cmd_t *cmd, uint8_t landed,
                  const float att[2], const float rates[3], float dt_s, float motor_n[QL_MOTORS])
{
    /* torque = J (kp e + I - kd d(rate)/dt) + w x (J w), with J folded into the gains at init; dt_s must be the
     * loop period the gains were folded with (1 / QL_LOOP_HZ) */
    (void)dt_s;
    float rate_sp[3], torque[3];
    rate_sp[0] = clampf(p->angle_kp_1_s * (cmd->roll_rad - att[0]), -p->max_rate_rad_s, p->max_rate_rad_s);
    rate_sp[1] = clampf(p->angle_kp_1_s * (cmd->pitch_rad - att[1]), -p->max_rate_rad_s, p->max_rate_rad_s);
    rate_sp[2] = cmd->yaw_rate_rad_s;
    for (uint8_t i = 0; i < 3u; i++) {
        float err = rate_sp[i] - rates[i];
        c->integ[i] = landed ? 0.0f : clampf(c->integ[i] + c->ki_j_dt[i] * err, -c->ilim_j[i], c->ilim_j[i]);
        torque[i] = c->kp_j[i] * err + c->integ[i];
        if (i < 2u && c->have_prev) {
            torque[i] -= c->kd_j_dt[i] * (rates[i] - c->prev_rates[i]);
        }
        c->prev_rates[i] = rates[i];
    }
    c->have_prev = 1;
    /* gyroscopic feed-forward: w x (J w) */
    const float *J = p->inertia_kg_m2;
    const float jw0 = J[0] * rates[0], jw1 = J[1] * rates[1], jw2 = J[2] * rates[2];
    torque[0] += rates[1] * jw2 - rates[2] * jw1;
    torque[1] += rates[2] * jw0 - rates[0] * jw2;
    torque[2] += rates[0] * jw1 - rates[1] * jw0;
    uint8_t finite = 1;
    for (uint8_t i = 0; i < 3u; i++) {
        finite &= (uint8_t)(isfinite(torque[i]) != 0);
    }
    if (!finite) { /* never fly a NaN: drop the torque and the loop state */
        ql_ctrl_reset(c);
        torque[0] = torque[1] = torque[2] = 0.0f;
    }
    float thrust = isfinite(cmd->thrust) ? clampf(cmd->thrust, 0.0f, 1.0f) : 0.0f;
    ql_mix(c, thrust * (4.0f * p->max_thrust_n), torque, p->idle_fraction * p->max_thrust_n, p->max_thrust_n,
           motor_n);
}

uint8_t ql_motor_byte(float thrust_n, float bytes_per_n)
{
    float b = thrust_n * bytes_per_n + 0.5f;
    if (!(b >= 1.0f)) { /* also catches NaN */
        return 1u;
    }
    return b >= 255.0f ? 255u : (uint8_t)b;
}

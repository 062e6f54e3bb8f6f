#include "safety.h"

#include "sensors.h"

#include <math.h>

#define THRUST_FULL_SCALE 65535.0f
#define Q24 16777216.0f
#define RATE_R_RAD_S (QL_GYRO_LSB_RAD_S / 256.0f)

/* total thrust (F = N * 2^16) of a fraction of the motors' maximum */
static int32_t thrust_f_of(const ql_params_t *p, float fraction)
{
    return (int32_t)lroundf(fraction * 4.0f * p->max_thrust_n * 65536.0f);
}

static uint32_t ticks_of(float seconds) { return (uint32_t)(seconds * (float)QL_LOOP_HZ + 0.5f); }

void ql_safety_init(ql_safety_t *s, const ql_params_t *p)
{
    /* the setpoint conversions as integer multipliers, once (float costs ~120 cycles per operation) */
    s->max_tilt_q24 = (int32_t)lroundf(p->max_tilt_rad * Q24);
    s->max_yaw_r = (int32_t)lroundf(p->max_yaw_rate_rad_s / RATE_R_RAD_S);
    s->thrust_k8 = (int32_t)lroundf(4.0f * p->max_thrust_n * 65536.0f / THRUST_FULL_SCALE * 256.0f);
    s->landed_f = thrust_f_of(p, p->landed_thrust_fraction);
    s->timeout_ticks = ticks_of(p->setpoint_timeout_s);
    s->ground_t16 = (int32_t)lroundf(p->failsafe_ground_speed_m_s * QL_CLIMB_T16_PER_M_S);
    s->armed = s->failsafe = 0;
    s->flight_state = QL_STATE_LANDED;
    s->error_flags = 0;
    s->have_setpoint = 0;
    s->seq = 0;
    s->still_timing = 0;
    s->last_setpoint_tick = s->failsafe_start_tick = s->still_since_tick = 0;
    s->setpoints_received = 0;
    s->cmd.roll_q24 = s->cmd.pitch_q24 = s->cmd.yaw_rate_r = s->cmd.thrust_f = 0;
    s->cmd_flying = 0;
}

float ql_hover_thrust_fraction(const ql_params_t *p)
{
    return p->mass_kg * QL_GRAVITY_M_S2 / (4.0f * p->max_thrust_n);
}

static int32_t clamp32(int32_t v, int32_t lim) { return v > lim ? lim : (v < -lim ? -lim : v); }

uint8_t ql_safety_on_setpoint(ql_safety_t *s, const ql_params_t *p, const ql_setpoint_msg_t *m, uint32_t tick)
{
    /* integers on the wire: a NaN cannot arrive; the limits are the board's own; the loop's units out
     * (control.h): 0.01 deg -> Q24 rad x 2928.19 = 46851 / 16; 0.1 deg/s -> R x 43.685 = 11183 / 256 */
    (void)p;
    s->cmd.roll_q24 = clamp32((m->roll_cdeg * INT32_C(46851)) >> 4, s->max_tilt_q24);
    s->cmd.pitch_q24 = clamp32((m->pitch_cdeg * INT32_C(46851)) >> 4, s->max_tilt_q24);
    s->cmd.yaw_rate_r = clamp32((m->yaw_rate_ddeg_s * INT32_C(11183)) >> 8, s->max_yaw_r);
    s->cmd.thrust_f = ((int32_t)m->thrust * s->thrust_k8) >> 8;
    s->cmd_flying = (uint8_t)(s->cmd.thrust_f > s->landed_f);
    s->seq = m->seq;
    s->have_setpoint = 1;
    s->last_setpoint_tick = tick;
    s->setpoints_received++;
    s->failsafe = 0;
    s->error_flags &= (uint16_t)~QL_ERR_SETPOINT_TIMEOUT;
    uint8_t arm = (uint8_t)((m->flags & QL_SETPOINT_FLAG_ARMED) != 0u);
    uint8_t edge = (uint8_t)(arm && !s->armed);
    s->armed = arm;
    return edge;
}

static void disarm(ql_safety_t *s)
{
    s->armed = 0;
    s->failsafe = 0;
    s->flight_state = QL_STATE_LANDED;
    s->cmd.thrust_f = 0;
    s->cmd_flying = 0;
}

uint8_t ql_safety_step(ql_safety_t *s, const ql_params_t *p, uint32_t tick, int32_t climb_t16, uint8_t baro_valid,
                       uint8_t accel_1g, ql_att_cmd_t *fly)
{
    if (s->armed && !s->failsafe && s->have_setpoint &&
        tick - s->last_setpoint_tick > s->timeout_ticks) {
        s->error_flags |= QL_ERR_SETPOINT_TIMEOUT;
        if (s->flight_state == QL_STATE_FLYING) {
            s->failsafe = 1;
            s->failsafe_start_tick = tick;
            s->still_timing = 0;
        } else {
            disarm(s); /* not flying: just cut */
        }
    }
    if (!s->armed) {
        disarm(s);
        return 0;
    }
    if (s->failsafe) {
        float hover = ql_hover_thrust_fraction(p);
        float climb = baro_valid ? (float)climb_t16 * (1.0f / QL_CLIMB_T16_PER_M_S) : 0.0f; /* failsafe only */
        float scale = 1.0f + p->failsafe_climb_gain_1_m_s * (-p->failsafe_descent_m_s - climb);
        scale = scale < p->failsafe_thrust_min ? p->failsafe_thrust_min
                                               : (scale > p->failsafe_thrust_max ? p->failsafe_thrust_max : scale);
        fly->roll_q24 = fly->pitch_q24 = fly->yaw_rate_r = 0;
        fly->thrust_f = thrust_f_of(p, hover * scale);
        uint8_t slow = (uint8_t)(!baro_valid || (climb_t16 < s->ground_t16 && climb_t16 > -s->ground_t16));
        if (!(slow && accel_1g) || tick - s->failsafe_start_tick < QL_FS_MIN_TICKS) {
            s->still_timing = 0;
        } else if (!s->still_timing) {
            s->still_timing = 1;
            s->still_since_tick = tick;
        } else if (tick - s->still_since_tick > QL_FS_STILL_TICKS) {
            disarm(s); /* touchdown */
            return 0;
        }
        s->flight_state = QL_STATE_FAILSAFE_DESCEND;
        return 1;
    }
    *fly = s->cmd;
    s->flight_state = s->cmd_flying ? QL_STATE_FLYING : QL_STATE_LANDED;
    return 1;
}

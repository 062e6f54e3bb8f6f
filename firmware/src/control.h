/* The attitude loop and the mixer (float; sim_sitl/firmware.py and sim_sitl/motors.py are the reference):
 * angle P -> rate PID on roll/pitch (D on the measured rate), rate PI on yaw, gyroscopic feed-forward
 * torque = J alpha + w x (J w), then the mixer: per-motor thrust for the collective and the torque, the
 * torque scaled down if it alone exceeds the motors' range, then the collective shifted to fit. Pure C. */
#ifndef QL_CONTROL_H
#define QL_CONTROL_H

#include <stdint.h>

#include "params.h"

#define QL_MOTORS 4u

typedef struct {
    float roll_rad, pitch_rad, yaw_rate_rad_s;
    float thrust; /* fraction 0..1 of 4 x max_thrust_n */
} ql_att_cmd_t;

typedef struct {
    /* motor thrust per unit torque: mix_gain[axis] * mix_sign[motor][axis] (the allocation's inverse columns;
     * for both frames each column is one magnitude with signs -1, 0, +1, so the mixer needs no multiplies) */
    float mix_gain[3];
    int8_t mix_sign[QL_MOTORS][3];
    float motor_bytes_per_n; /* 255 / max_thrust_n */
    /* gains folded with the inertia at init (float multiplies are ~120 AVR cycles each) */
    float kp_j[3];     /* J * rate kp (yaw: yaw kp), N m per rad/s */
    float kd_j_dt[2];  /* J * kd / dt */
    float ki_j_dt[3];  /* J * ki * dt */
    float ilim_j[3];   /* J * integrator limit */
    float integ[3];    /* integrator, torque units (N m) = J * the Python model's rad/s^2 integrator */
    float prev_rates[3];
    uint8_t have_prev;
} ql_ctrl_t;

void ql_ctrl_init(ql_ctrl_t *c, const ql_params_t *p);
void ql_ctrl_reset(ql_ctrl_t *c);
/* One 500 Hz step. landed: the integrators are held at zero (no wind-up on the ground).
 * att: roll, pitch (rad); rates: p, q, r (rad/s). motor_n: per-motor thrust commands (N). */
void ql_ctrl_step(ql_ctrl_t *c, const ql_params_t *p, const ql_att_cmd_t *cmd, uint8_t landed,
                  const float att[2], const float rates[3], float dt_s, float motor_n[QL_MOTORS]);
void ql_mix(const ql_ctrl_t *c, float thrust_n, const float torque_nm[3], float min_n, float max_n,
            float motor_n[QL_MOTORS]);
/* Motor byte for the BL-Ctrl: round(thrust * 255 / max_thrust_n), 1..255 when armed (0 = stopped). */
uint8_t ql_motor_byte(float thrust_n, float bytes_per_n);

#endif

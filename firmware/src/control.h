/* The attitude loop and the mixer in fixed point (sim_sitl/firmware.py and sim_sitl/motors.py are the reference):
 * angle P -> rate PID on roll/pitch (D on the measured rate), rate PI on yaw, gyroscopic feed-forward
 * torque = J alpha + w x (J w), then the mixer: per-motor thrust for the collective and the torque, the torque
 * scaled down if it alone exceeds the motors' range, then the collective shifted to fit. Pure C.
 *
 * Why integers: the float version cost 12 000 of the tick's 40 000 cycles on the ATmega1284P (libgcc float,
 * ~120 cycles per operation); this one costs a fraction of that (firmware/README.md). The gains are float
 * parameters converted once, at init, to integer multipliers. Units:
 *   angles Q24 rad (the filter's), rates R = gyro count / 256 (the filter's rate_q8, 4.0e-5 rad/s),
 *   torque T = 2^-16 N m, thrust F = 2^-16 N. */
#ifndef QL_CONTROL_H
#define QL_CONTROL_H

#include <stdint.h>

#include "params.h"

#define QL_MOTORS 4u
#define QL_F_ONE INT32_C(65536)        /* 1 N in thrust units */
#define QL_T_LIMIT INT32_C(262143)     /* |torque| < 4 N m (z: 4 N m x 15.6 N/N m x 2^9 stays in int32) */
#define QL_ERR_LIMIT_R INT32_C(262144) /* |rate error|, |rate step| <= 10.5 rad/s */
#define QL_MIX_SHIFT 9                 /* mixer gains: N per N m * 2^9 */

typedef struct {
    int32_t roll_q24, pitch_q24; /* angle setpoints, rad * 2^24 */
    int32_t yaw_rate_r;          /* yaw rate setpoint, R */
    int32_t thrust_f;            /* collective, F (N * 2^16) */
} ql_att_cmd_t;

typedef struct {
    /* motor thrust per unit torque: mix_gain[axis] * mix_sign[motor][axis] (the allocation's inverse columns;
     * for both frames each column is one magnitude with signs -1, 0, +1) */
    int32_t mix_gain[3];
    int8_t mix_sign[QL_MOTORS][3];
    int32_t ka;           /* angle error (Q16 rad) -> rate setpoint (R), Q12 */
    int32_t max_rate_r;   /* roll/pitch rate setpoint clamp */
    int32_t kp_j[3];      /* rate error (R) -> torque (T), Q12 */
    int32_t ki[3];        /* rate error (R) -> integrator step (rad/s^2 * 2^24), Q8 */
    int32_t ilim_q24[3];  /* integrator limit, rad/s^2 * 2^24 */
    int32_t j_q18[3];     /* inertia * 2^18 (integrator -> torque) */
    int32_t kd_j[2];      /* rate step (R) -> torque (T), Q12 */
    int32_t gyro_k[3];    /* (J_b - J_c) (64 R)^2 -> T, Q20 */
    int32_t min_f, max_f; /* per-motor thrust range, F */
    int32_t byte_k;       /* F -> BL-Ctrl byte, Q16: 255 / max_thrust (51 for 5 N) */
    int32_t integ_q24[3]; /* integrator, rad/s^2 * 2^24 (the Python model's units) */
    int32_t prev_rate_r[3];
    uint8_t have_prev;
} ql_ctrl_t;

void ql_ctrl_init(ql_ctrl_t *c, const ql_params_t *p);
void ql_ctrl_reset(ql_ctrl_t *c);
/* One 500 Hz step. landed: the integrators are held at zero (no wind-up on the ground). */
void ql_ctrl_step(ql_ctrl_t *c, const ql_att_cmd_t *cmd, uint8_t landed, int32_t roll_q24, int32_t pitch_q24,
                  const int32_t rate_r[3], int32_t motor_f[QL_MOTORS]);
void ql_mix(const ql_ctrl_t *c, int32_t thrust_f, const int32_t torque_t[3], int32_t motor_f[QL_MOTORS]);
/* Motor byte for the BL-Ctrl: thrust * 255 / max_thrust rounded, 1..255 when armed (0 = stopped). */
uint8_t ql_motor_byte(const ql_ctrl_t *c, int32_t thrust_f);

#endif

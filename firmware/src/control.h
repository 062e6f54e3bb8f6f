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
    float mix[QL_MOTORS][3]; /* motor thrust per unit torque (x, y, z): the allocation's inverse columns */
    float integ[3];
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
/* Motor byte for the BL-Ctrl: round(thrust / max * 255), 1..255 when armed (0 = stopped). */
uint8_t ql_motor_byte(float thrust_n, float max_thrust_n);

#endif

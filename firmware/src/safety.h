/* Arming and failsafe (sim_sitl/firmware.py's logic, in ticks of the 500 Hz loop). Pure C.
 *
 * Arming follows the 's' frame's armed flag; clearing it cuts the motors at once. No valid setpoint for
 * setpoint_timeout_s while armed: flying -> failsafe (level, zero yaw rate, a descent held at
 * failsafe_descent_m_s on the baro climb rate), then a motor cut once on the ground (after 1 s of failsafe,
 * |climb| below failsafe_ground_speed_m_s and the accelerometer reading 1 g for 0.5 s); not flying -> cut at
 * once. A valid setpoint ends the failsafe. */
#ifndef QL_SAFETY_H
#define QL_SAFETY_H

#include <stdint.h>

#include "control.h"
#include "mk_msgs.h"
#include "params.h"

#define QL_FS_MIN_TICKS 500u      /* failsafe descends at least 1 s before it looks for the ground */
#define QL_FS_STILL_TICKS 250u    /* on the ground for 0.5 s -> cut */

typedef struct {
    uint8_t armed;
    uint8_t failsafe;
    uint8_t flight_state;
    uint16_t error_flags;
    uint8_t have_setpoint;
    uint8_t seq;
    uint8_t still_timing;
    uint32_t last_setpoint_tick;
    uint32_t timeout_ticks;
    int32_t max_tilt_q24, max_yaw_r, thrust_k8, landed_f; /* from the parameters, at init */
    int32_t ground_t16;                                   /* failsafe_ground_speed_m_s in climb_t16 units */
    uint32_t failsafe_start_tick;
    uint32_t still_since_tick;
    uint32_t setpoints_received;
    ql_att_cmd_t cmd; /* the last valid setpoint, clamped, in the loop's units */
    uint8_t cmd_flying; /* its thrust is above landed_thrust_fraction */
} ql_safety_t;

void ql_safety_init(ql_safety_t *s, const ql_params_t *p);
/* A decoded 's' frame at tick. Returns 1 on an arming edge (the caller resets its loops). */
uint8_t ql_safety_on_setpoint(ql_safety_t *s, const ql_params_t *p, const ql_setpoint_msg_t *m, uint32_t tick);
/* Per tick: climb_t16 (baro, up, the baro's v_t16 units: mm per tick * 2^16 = 131 072 per m/s), baro_valid,
 * accel_1g (|f| ~ 1 g). Fills *fly with what to fly and returns 1 while the motors run (armed), 0 when they are
 * cut (the caller resets its loops on a 1 -> 0 edge). */
#define QL_CLIMB_T16_PER_M_S 131072.0f
uint8_t ql_safety_step(ql_safety_t *s, const ql_params_t *p, uint32_t tick, int32_t climb_t16, uint8_t baro_valid,
                       uint8_t accel_1g, ql_att_cmd_t *fly);
float ql_hover_thrust_fraction(const ql_params_t *p);

#endif

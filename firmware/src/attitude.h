/* The board's attitude estimate: a fixed-point complementary filter at 500 Hz on the raw ADC counts.
 *
 * Gyro: body rates (bias removed) integrated through the ZYX Euler kinematics
 *   roll' = p + tan(pitch) (q sin(roll) + r cos(roll)),  pitch' = q cos(roll) - r sin(roll),
 *   yaw' = (q sin(roll) + r cos(roll)) / cos(pitch);
 * accelerometer: roll and pitch pulled towards the attitude of the measured specific force (FRD) when |f| is
 * near 1 g, through the sine of the error (no atan2 in the loop), fast while disarmed, slow in flight; yaw
 * from the gyro alone. During the power-up calibration the attitude is set from the accelerometer
 * (atan2(-fy, -fz), atan2(fx, sqrt(fy^2 + fz^2))).
 * Gyro zero offsets: the mean of the first 256 samples after power-up (the board sits still while it boots),
 * then tracked slowly while disarmed and still. The sines and cosines of roll and pitch are refreshed
 * alternately, one pair per tick (each sine costs ~1 100 AVR cycles; a 2-4 ms old angle moves the coupling
 * terms by less than the Q12 resolution at the loop's rates). Pure integer code; sim_sitl/board_estimators.py mirrors it. */
#ifndef QL_ATTITUDE_H
#define QL_ATTITUDE_H

#include <stdint.h>

#define QL_ATT_CAL_TICKS 256u            /* power-up gyro calibration (0.512 s); mean = sum / 256 in q8 */
#define QL_ATT_BIAS_SHIFT 9              /* still & disarmed: bias EMA, time constant 512 ticks (1 s) */
#define QL_ATT_STILL_Q8 (INT32_C(3) * INT32_C(256))      /* |gyro - bias| <= 3 counts on every axis = still */
#define QL_ATT_ACC_SHIFT_DISARMED 5      /* accelerometer gain while disarmed: tau = 32 ticks */
#define QL_ATT_ACC_SHIFT_ARMED 8         /* armed on the ground (motors idling): tau = 256 ticks (0.5 s) */
/* Flying: tau = 4096 ticks (8 s). In flight a quadrotor's accelerometer reads mostly thrust (f ~ (0, 0, -T/m)
 * whatever the tilt), so it pulls the estimate towards level; slow enough that a 0.5 s manoeuvre leaks ~6 %
 * of its tilt, fast enough to bound the gyro's bias walk (tests/unit/test_firmware_closed_loop.py). */
#define QL_ATT_ACC_SHIFT_FLYING 12
#define QL_ATT_ACC_MIN2 (INT32_C(205) * INT32_C(205))    /* |f| within 0.8 .. 1.2 g (counts^2) to trust the accelerometer */
#define QL_ATT_ACC_MAX2 (INT32_C(307) * INT32_C(307))
#define QL_ATT_RATE_LIMIT_Q6 INT32_C(65536)      /* Euler-rate clamp (q6 counts, 10.5 rad/s) keeps int32 in range */
#define QL_ATT_COS_MIN_Q12 INT32_C(1024)         /* cos(pitch) floor for tan/sec (|pitch| > 75.5 deg) */
#define QL_ATT_ROLL_ACC_MAX_PITCH_Q24 INT32_C(21958989) /* no accel roll correction beyond |pitch| 75 deg (1.309 rad) */
/* Q24 angle increment per tick per q6 rate count: gyro_lsb / 64 * 0.002 s * 2^24 = 5.36222 ~ 21964 / 4096 */
#define QL_ATT_DANG_K INT32_C(21964)
#define QL_ATT_DANG_SHIFT 12
#define QL_ATT_ERR_Q24_PER_COUNT_Q12 INT32_C(16) /* 2^24 / (256 counts per g * 4096) */

typedef struct {
    int32_t roll_q24, pitch_q24, yaw_q24; /* rad * 2^24 */
    int32_t rate_q8[3];                   /* body rates p, q, r: gyro counts * 256, bias removed */
    int32_t bias_q16[3];                  /* gyro zero, counts * 65536 */
    int32_t cal_sum[3];
    int32_t sin_roll, cos_roll, sin_pitch, cos_pitch; /* Q12, refreshed alternately (one pair per tick) */
    int32_t sec_pitch;  /* 1 / max(cos(pitch), 0.25), Q12: one Newton step per tick from the last value */
    uint16_t cal_ticks;
    uint8_t trig_phase;
    uint8_t calibrated;
    uint8_t saturated; /* a channel sat at 0 or 1023 this tick */
} ql_attitude_t;

void ql_attitude_init(ql_attitude_t *a);
/* accel and gyro: raw ADC counts (FRD); armed freezes the gyro offsets; armed and flying select the
 * accelerometer gain. */
void ql_attitude_update(ql_attitude_t *a, const uint16_t accel[3], const uint16_t gyro[3], uint8_t armed,
                        uint8_t flying);

#endif

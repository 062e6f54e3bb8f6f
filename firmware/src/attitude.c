#include "attitude.h"

#include "fxmath.h"
#include "sensors.h"

void ql_attitude_init(ql_attitude_t *a)
{
    a->roll_q24 = a->pitch_q24 = a->yaw_q24 = 0;
    for (uint8_t i = 0; i < 3u; i++) {
        a->rate_q8[i] = 0;
        a->bias_q16[i] = QL_IMU_ZERO_COUNT << 16;
        a->cal_sum[i] = 0;
    }
    a->sin_roll = a->sin_pitch = 0;
    a->cos_roll = a->cos_pitch = QL_Q12_ONE;
    a->sec_pitch = QL_Q12_ONE;
    a->cal_ticks = 0;
    a->trig_phase = 0;
    a->calibrated = 0;
    a->saturated = 0;
}

static int32_t clamp32(int32_t v, int32_t lim) { return v > lim ? lim : (v < -lim ? -lim : v); }

/* a 16 x 16 -> 32 bit product (the AVR's widening multiply, not a 32 x 32 library call); both operands must
 * fit int16, which the callers' ranges guarantee */
static inline int32_t mul16(int32_t a, int32_t b) { return (int32_t)(int16_t)a * (int16_t)b; }

void ql_attitude_update(ql_attitude_t *a, const uint16_t accel[3], const uint16_t gyro[3], uint8_t armed,
                        uint8_t flying)
{
    uint8_t sat = 0;
    int32_t f[3];
    for (uint8_t i = 0; i < 3u; i++) {
        sat |= (uint8_t)(gyro[i] == 0u || gyro[i] >= QL_IMU_COUNT_MAX || accel[i] == 0u ||
                         accel[i] >= QL_IMU_COUNT_MAX);
        f[i] = (int32_t)accel[i] - QL_IMU_ZERO_COUNT;
    }
    a->saturated = sat;

    int32_t norm2 = mul16(f[0], f[0]) + mul16(f[1], f[1]) + mul16(f[2], f[2]);
    uint8_t acc_ok = (uint8_t)(norm2 >= QL_ATT_ACC_MIN2 && norm2 <= QL_ATT_ACC_MAX2);
    if (!a->calibrated) {
        /* power-up: average the gyro, hold the attitude at the accelerometer's */
        for (uint8_t i = 0; i < 3u; i++) {
            a->cal_sum[i] += (int32_t)gyro[i];
            a->rate_q8[i] = 0;
        }
        /* the accelerometer's attitude: f = g [sin(pitch), -sin(roll) cos(pitch), -cos(roll) cos(pitch)] */
        a->roll_q24 = ql_atan2_q24(-f[1], -f[2]);
        a->pitch_q24 = ql_atan2_q24(f[0], (int32_t)ql_isqrt32((uint32_t)(f[1] * f[1] + f[2] * f[2])));
        if (++a->cal_ticks >= QL_ATT_CAL_TICKS) {
            for (uint8_t i = 0; i < 3u; i++) {
                a->bias_q16[i] = a->cal_sum[i] << 8; /* sum of 256 samples = mean * 256 (q8) -> q16 */
            }
            a->calibrated = 1;
            a->sin_roll = ql_sin_q12(a->roll_q24);
            a->cos_roll = ql_cos_q12(a->roll_q24);
            a->sin_pitch = ql_sin_q12(a->pitch_q24);
            a->cos_pitch = ql_cos_q12(a->pitch_q24);
        }
        return;
    }

    uint8_t still = acc_ok;
    for (uint8_t i = 0; i < 3u; i++) {
        int32_t g = ((int32_t)gyro[i] << 8) - QL_RSHIFT(a->bias_q16[i], 8);
        a->rate_q8[i] = g;
        still &= (uint8_t)(g <= QL_ATT_STILL_Q8 && g >= -QL_ATT_STILL_Q8);
    }
    if (!armed && still) {
        for (uint8_t i = 0; i < 3u; i++) {
            a->bias_q16[i] += (((int32_t)gyro[i] << 16) - a->bias_q16[i]) >> QL_ATT_BIAS_SHIFT;
        }
    }

    /* Euler kinematics in q6 rate counts and Q12 trigonometry */
    int32_t p = QL_RSHIFT(a->rate_q8[0], 2), q = QL_RSHIFT(a->rate_q8[1], 2), r = QL_RSHIFT(a->rate_q8[2], 2);
    if (a->trig_phase) {
        a->sin_pitch = ql_sin_q12(a->pitch_q24);
        a->cos_pitch = ql_cos_q12(a->pitch_q24);
    } else {
        a->sin_roll = ql_sin_q12(a->roll_q24);
        a->cos_roll = ql_cos_q12(a->roll_q24);
    }
    a->trig_phase ^= 1u;
    int32_t sr = a->sin_roll, cr = a->cos_roll;
    int32_t sp = a->sin_pitch, cp0 = a->cos_pitch;
    int32_t cp = cp0;
    if (cp < QL_ATT_COS_MIN_Q12) {
        cp = QL_ATT_COS_MIN_Q12; /* |pitch| near 90 deg: the Euler rates are singular; bounded instead */
    }
    /* 1 / cos(pitch) without a division each tick (a 32-bit division is ~650 AVR cycles): Newton's
     * r <- r (2 - c r) from the last tick's value, which pitch moves by well under 1 %; a value that is not
     * within 50 % (start, or a jump) is computed by the division (positive operands) */
    int32_t cr_prod = mul16(cp, a->sec_pitch) >> 12; /* cp <= 4096, sec <= 16384 */
    if (cr_prod < QL_Q12_ONE / 2 || cr_prod > QL_Q12_ONE + QL_Q12_ONE / 2) {
        a->sec_pitch = (QL_Q12_ONE * QL_Q12_ONE) / cp;
    } else {
        a->sec_pitch = (a->sec_pitch * (2 * QL_Q12_ONE - cr_prod)) >> 12;
    }
    int32_t sec_p = a->sec_pitch;
    int32_t tan_p = QL_RSHIFT(mul16(sp, sec_p), 12);
    int32_t u = QL_RSHIFT(q * sr + r * cr, 12);
    int32_t roll_rate = clamp32(p + QL_RSHIFT(tan_p * u, 12), QL_ATT_RATE_LIMIT_Q6);
    int32_t pitch_rate = clamp32(QL_RSHIFT(q * cr - r * sr, 12), QL_ATT_RATE_LIMIT_Q6);
    int32_t yaw_rate = clamp32(QL_RSHIFT(sec_p * u, 12), QL_ATT_RATE_LIMIT_Q6);
    a->roll_q24 += QL_RSHIFT(roll_rate * QL_ATT_DANG_K, QL_ATT_DANG_SHIFT);
    a->pitch_q24 += QL_RSHIFT(pitch_rate * QL_ATT_DANG_K, QL_ATT_DANG_SHIFT);
    a->yaw_q24 = ql_wrap_pi_q24(a->yaw_q24 + QL_RSHIFT(yaw_rate * QL_ATT_DANG_K, QL_ATT_DANG_SHIFT));

    if (acc_ok) {
        /* Pull towards the accelerometer without atan2: with the estimate's sines and cosines, the measured
         * specific force gives sin(error) scaled by |f| (counts, 256 per g):
         *   roll:  (-fy) cos(roll) - (-fz) sin(roll) = |f_yz| sin(roll - roll_est)
         *   pitch: fx cos(pitch) - f_yz sin(pitch)   = |f| sin(pitch - pitch_est), f_yz = (-fy) sin(roll) + (-fz) cos(roll)
         * Zero exactly at the accelerometer's attitude whatever |f| is; |f| only scales the gain (the gate
         * keeps it within 0.8 .. 1.2 g). Counts * Q12 -> Q24 rad at 1 g: * 2^24 / (256 * 4096) = * 16. */
        uint8_t shift = !armed ? QL_ATT_ACC_SHIFT_DISARMED : (flying ? QL_ATT_ACC_SHIFT_FLYING : QL_ATT_ACC_SHIFT_ARMED);
        int32_t f_yz = QL_RSHIFT(-mul16(f[1], sr) - mul16(f[2], cr), 12); /* |f| <= 512, Q12 <= 4096 */
        int32_t e_pitch = (mul16(f[0], cp0) - mul16(f_yz, sp)) * QL_ATT_ERR_Q24_PER_COUNT_Q12;
        a->pitch_q24 += QL_RSHIFT(e_pitch, shift);
        if (a->pitch_q24 < QL_ATT_ROLL_ACC_MAX_PITCH_Q24 && a->pitch_q24 > -QL_ATT_ROLL_ACC_MAX_PITCH_Q24) {
            int32_t e_roll = (-mul16(f[1], cr) + mul16(f[2], sr)) * QL_ATT_ERR_Q24_PER_COUNT_Q12;
            a->roll_q24 += QL_RSHIFT(e_roll, shift);
        }
    }
    a->roll_q24 = ql_wrap_pi_q24(a->roll_q24);
    a->pitch_q24 = clamp32(a->pitch_q24, QL_HALF_PI_Q24);
}

"""The FlightCtrl firmware's own estimators, bit for bit in Python (pure, step-based, 500 Hz).

``firmware/src/attitude.c`` (the fixed-point complementary filter on the raw IMU counts) and
``firmware/src/baro.c`` (ADC6 pressure -> altitude and climb) are the definition; this module repeats the same
integer arithmetic so the SITL's Python board model can fly on the board's estimate instead of the truth.
``tests/unit/test_firmware_estimators.py`` feeds the same random count streams to the C (the host build,
``make -C firmware host``) and to this mirror and asserts identical integer states.

Integer rules that make the two agree: every right shift of a signed value is arithmetic (Python's ``>>`` and
gcc's agree: floor), ``_rshift`` rounds half up as ``QL_RSHIFT``, and the only divisions (of non-negative values)
are the same in both languages. The C keeps every intermediate within int32; so does this mirror, by the same
ranges.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

# --- sensors (firmware/src/sensors.h; configs/vehicle.yaml imu:) ---------------------------------------------
IMU_ZERO_COUNT = 512
IMU_COUNT_MAX = 1023
GYRO_LSB_RAD_S = 0.0102276  # 0.586 deg/s per count
LOOP_HZ = 500

# --- fixed-point formats (firmware/src/fxmath.h) -----------------------------------------------------------
Q24_ONE = 1 << 24  # angles: rad * 2^24
PI_Q24 = 52707179  # round(pi * 2^24)
HALF_PI_Q24 = 26353589
TWO_PI_Q24 = 105414357
Q12_ONE = 4096  # sines and cosines
_SIN_8_OVER_42_Q16 = 12483
_SIN_16_OVER_20_Q16 = 52429
_SIN_2_OVER_3_Q16 = 43691
_Q15_ONE = 32768
_ATAN_PI4_Q15 = 25736
_ATAN_C0_Q15 = 8018
_ATAN_C1_Q15 = 2173
_Q15_ONE = 32768

# --- attitude filter (firmware/src/attitude.h) ---------------------------------------------------------------
ATT_CAL_TICKS = 256
ATT_BIAS_SHIFT = 9
ATT_STILL_Q8 = 3 * 256
ATT_ACC_SHIFT_DISARMED = 5
ATT_ACC_SHIFT_ARMED = 8  # armed on the ground
ATT_ACC_SHIFT_FLYING = 12
ATT_ACC_MIN2 = 205 * 205
ATT_ACC_MAX2 = 307 * 307
ATT_RATE_LIMIT_Q6 = 65536
ATT_COS_MIN_Q12 = 1024
ATT_ROLL_ACC_MAX_PITCH_Q24 = 21958989
ATT_DANG_K = 21964
ATT_DANG_SHIFT = 12
ATT_ERR_Q24_PER_COUNT_Q12 = 16

# --- baro (firmware/src/baro.h) -------------------------------------------------------------------------------
BARO_OVERSAMPLE = 8
BARO_P0_PA = 95000
BARO_P16_PER_SUM_K = 22222
BARO_P16_PER_SUM_SHIFT = 10
BARO_MM_PER_P16_K = 10655
BARO_MM_PER_P16_SHIFT = 11
BARO_LP_SHIFT = 5
BARO_REF_SHIFT = 8
BARO_REF_TICKS = 256
BARO_ALPHA_SHIFT = 7
BARO_BETA_SHIFT = 7
BARO_ADC_MAX = 1023
BARO_V_LIMIT_T16 = 6553600


def _rshift(x: int, s: int) -> int:
    """``QL_RSHIFT``: (x + 2^(s-1)) >> s, arithmetic (rounds half up)."""
    return (x + (1 << (s - 1))) >> s


def _clamp(v: int, lim: int) -> int:
    return lim if v > lim else (-lim if v < -lim else v)


def wrap_pi_q24(a: int) -> int:
    while a >= PI_Q24:
        a -= TWO_PI_Q24
    while a < -PI_Q24:
        a += TWO_PI_Q24
    return a


def sin_q12(a_q24: int) -> int:
    """``ql_sin_q12``: Taylor series to x^7 on [-pi/2, pi/2]; x in Q14, x^2 in Q12, Horner terms in Q15."""
    a = wrap_pi_q24(a_q24)
    if a > HALF_PI_Q24:
        a = PI_Q24 - a
    elif a < -HALF_PI_Q24:
        a = -PI_Q24 - a
    x = _rshift(a, 10)
    x2 = (x * x) >> 16
    t = _Q15_ONE - ((x2 * _SIN_8_OVER_42_Q16) >> 16)
    u = (x2 * t) >> 16
    t = _Q15_ONE - ((u * _SIN_16_OVER_20_Q16) >> 16)
    u = (x2 * t) >> 16
    t = _Q15_ONE - (2 * u + ((u * _SIN_2_OVER_3_Q16) >> 16))
    return max(-Q12_ONE, min(Q12_ONE, (x * t + (1 << 16)) >> 17))


def cos_q12(a_q24: int) -> int:
    return sin_q12(wrap_pi_q24(a_q24) + HALF_PI_Q24)


def _atan_unit_q24(z: int) -> int:
    t = (z * (_Q15_ONE - z)) >> 15
    poly = _ATAN_C0_Q15 + ((_ATAN_C1_Q15 * z) >> 15)
    return (((_ATAN_PI4_Q15 * z) >> 15) + ((t * poly) >> 15)) << 9


def atan2_q24(y: int, x: int) -> int:
    """``ql_atan2_q24`` (octant reduction and a rational-free polynomial, max error 1.5e-3 rad)."""
    ax, ay = abs(x), abs(y)
    if ax == 0 and ay == 0:
        return 0
    if ay <= ax:
        a = _atan_unit_q24((ay << 15) // ax)
    else:
        a = HALF_PI_Q24 - _atan_unit_q24((ax << 15) // ay)
    if x < 0:
        a = PI_Q24 - a
    return -a if y < 0 else a


@dataclass(frozen=True)
class BoardAttitude:
    """The board's attitude estimate after one tick: ZYX Euler angles (rad, FRD) and body rates (rad/s, FRD)."""

    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    rates_q_rad_s: tuple[float, float, float]
    calibrated: bool
    saturated: bool


class BoardAttitudeFilter:
    """Mirror of ``ql_attitude_update``: feed the six raw counts of each 2 ms tick, the arm state (freezes the
    gyro offsets) and whether the board flies (flight state not landed: the slowest accelerometer gain)."""

    def __init__(self) -> None:
        self.roll_q24 = 0
        self.pitch_q24 = 0
        self.yaw_q24 = 0
        self.rate_q8 = [0, 0, 0]
        self.bias_q16 = [IMU_ZERO_COUNT << 16] * 3
        self.cal_sum = [0, 0, 0]
        # Q12 sines and cosines of roll and pitch, refreshed alternately (one pair per tick), as the C
        self.sin_roll = self.sin_pitch = 0
        self.cos_roll = self.cos_pitch = Q12_ONE
        self.trig_phase = 0
        self.sec_pitch = Q12_ONE  # 1 / max(cos(pitch), 0.25), Q12, one Newton step per tick
        self.cal_ticks = 0
        self.calibrated = False
        self.saturated = False

    def update(self, accel_counts: Sequence[int], gyro_counts: Sequence[int], armed: bool = False,
               flying: bool = False) -> BoardAttitude:
        accel = [int(c) for c in accel_counts]
        gyro = [int(c) for c in gyro_counts]
        self.saturated = any(c == 0 or c >= IMU_COUNT_MAX for c in (*accel, *gyro))
        f = [c - IMU_ZERO_COUNT for c in accel]
        norm2 = f[0] * f[0] + f[1] * f[1] + f[2] * f[2]
        acc_ok = ATT_ACC_MIN2 <= norm2 <= ATT_ACC_MAX2

        if not self.calibrated:
            for i in range(3):
                self.cal_sum[i] += gyro[i]
                self.rate_q8[i] = 0
            self.roll_q24 = atan2_q24(-f[1], -f[2])
            self.pitch_q24 = atan2_q24(f[0], math.isqrt(f[1] * f[1] + f[2] * f[2]))
            self.cal_ticks += 1
            if self.cal_ticks >= ATT_CAL_TICKS:
                self.bias_q16 = [s << 8 for s in self.cal_sum]
                self.calibrated = True
                self.sin_roll, self.cos_roll = sin_q12(self.roll_q24), cos_q12(self.roll_q24)
                self.sin_pitch, self.cos_pitch = sin_q12(self.pitch_q24), cos_q12(self.pitch_q24)
            return self.estimate()

        still = acc_ok
        for i in range(3):
            g = (gyro[i] << 8) - _rshift(self.bias_q16[i], 8)
            self.rate_q8[i] = g
            still = still and -ATT_STILL_Q8 <= g <= ATT_STILL_Q8
        if not armed and still:
            for i in range(3):
                self.bias_q16[i] += ((gyro[i] << 16) - self.bias_q16[i]) >> ATT_BIAS_SHIFT

        p, q, r = (_rshift(g, 2) for g in self.rate_q8)
        if self.trig_phase:
            self.sin_pitch, self.cos_pitch = sin_q12(self.pitch_q24), cos_q12(self.pitch_q24)
        else:
            self.sin_roll, self.cos_roll = sin_q12(self.roll_q24), cos_q12(self.roll_q24)
        self.trig_phase ^= 1
        sr, cr, sp, cp0 = self.sin_roll, self.cos_roll, self.sin_pitch, self.cos_pitch
        cp = max(cp0, ATT_COS_MIN_Q12)
        cr_prod = (cp * self.sec_pitch) >> 12
        if cr_prod < Q12_ONE // 2 or cr_prod > Q12_ONE + Q12_ONE // 2:
            self.sec_pitch = (Q12_ONE * Q12_ONE) // cp
        else:
            self.sec_pitch = (self.sec_pitch * (2 * Q12_ONE - cr_prod)) >> 12
        sec_p = self.sec_pitch
        tan_p = _rshift(sp * sec_p, 12)
        u = _rshift(q * sr + r * cr, 12)
        roll_rate = _clamp(p + _rshift(tan_p * u, 12), ATT_RATE_LIMIT_Q6)
        pitch_rate = _clamp(_rshift(q * cr - r * sr, 12), ATT_RATE_LIMIT_Q6)
        yaw_rate = _clamp(_rshift(sec_p * u, 12), ATT_RATE_LIMIT_Q6)
        self.roll_q24 += _rshift(roll_rate * ATT_DANG_K, ATT_DANG_SHIFT)
        self.pitch_q24 += _rshift(pitch_rate * ATT_DANG_K, ATT_DANG_SHIFT)
        self.yaw_q24 = wrap_pi_q24(self.yaw_q24 + _rshift(yaw_rate * ATT_DANG_K, ATT_DANG_SHIFT))

        if acc_ok:
            shift = ATT_ACC_SHIFT_DISARMED if not armed else (ATT_ACC_SHIFT_FLYING if flying else ATT_ACC_SHIFT_ARMED)
            f_yz = _rshift(-f[1] * sr - f[2] * cr, 12)
            e_pitch = (f[0] * cp0 - f_yz * sp) * ATT_ERR_Q24_PER_COUNT_Q12
            self.pitch_q24 += _rshift(e_pitch, shift)
            if -ATT_ROLL_ACC_MAX_PITCH_Q24 < self.pitch_q24 < ATT_ROLL_ACC_MAX_PITCH_Q24:
                e_roll = (-f[1] * cr + f[2] * sr) * ATT_ERR_Q24_PER_COUNT_Q12
                self.roll_q24 += _rshift(e_roll, shift)
        self.roll_q24 = wrap_pi_q24(self.roll_q24)
        self.pitch_q24 = _clamp(self.pitch_q24, HALF_PI_Q24)
        return self.estimate()

    def estimate(self) -> BoardAttitude:
        lsb = GYRO_LSB_RAD_S / 256.0
        return BoardAttitude(
            roll_rad=self.roll_q24 / Q24_ONE,
            pitch_rad=self.pitch_q24 / Q24_ONE,
            yaw_rad=self.yaw_q24 / Q24_ONE,
            rates_q_rad_s=(self.rate_q8[0] * lsb, self.rate_q8[1] * lsb, self.rate_q8[2] * lsb),
            calibrated=self.calibrated,
            saturated=self.saturated,
        )


@dataclass(frozen=True)
class BoardBaroEstimate:
    """The board's barometric estimate (what its ``'Z'`` frame carries, before the frame's rounding)."""

    altitude_m: float  # above the reference (pressure averaged while disarmed), up positive
    climb_m_s: float  # up positive
    pressure_pa: int
    valid: bool  # reference taken and no ADC rail in this tick's samples
    saturated: bool


class BoardBaro:
    """Mirror of ``ql_baro_update``: feed the tick's ADC6 conversions (8, or one count repeated) and the arm state."""

    def __init__(self) -> None:
        self.p16 = 0
        self.pf16 = 0
        self.pref_q12 = 0  # Pa * 4096
        self.h_q8 = 0
        self.v_t16 = 0
        self.ref_ticks = 0
        self.started = False
        self.was_armed = False
        self.saturated = False

    def update(self, adc6_counts: int | Sequence[int], armed: bool = False) -> BoardBaroEstimate:
        counts = [int(adc6_counts)] * BARO_OVERSAMPLE if isinstance(adc6_counts, int) else list(adc6_counts)
        if len(counts) != BARO_OVERSAMPLE:
            raise ValueError(f"BoardBaro.update needs {BARO_OVERSAMPLE} ADC6 counts per tick, got {len(counts)}")
        counts = [min(c, BARO_ADC_MAX) for c in counts]
        self.saturated = any(c in (0, BARO_ADC_MAX) for c in counts)
        self.p16 = BARO_P0_PA * 16 + ((sum(counts) * BARO_P16_PER_SUM_K) >> BARO_P16_PER_SUM_SHIFT)
        if not self.started:
            self.pf16 = self.p16
            self.pref_q12 = self.p16 << 8
            self.started = True
        self.pf16 += _rshift(self.p16 - self.pf16, BARO_LP_SHIFT)
        if not armed:
            self.pref_q12 += _rshift((self.p16 << 8) - self.pref_q12, BARO_REF_SHIFT)
            self.ref_ticks = min(self.ref_ticks + 1, BARO_REF_TICKS)
        elif not self.was_armed:
            self.h_q8 = 0
            self.v_t16 = 0
        self.was_armed = bool(armed)
        meas_mm = ((_rshift(self.pref_q12, 8) - self.p16) * BARO_MM_PER_P16_K) >> BARO_MM_PER_P16_SHIFT
        self.h_q8 += _rshift(self.v_t16, 8)
        r = (meas_mm << 8) - self.h_q8
        self.h_q8 += _rshift(r, BARO_ALPHA_SHIFT)
        self.v_t16 = _clamp(self.v_t16 + _rshift(r, BARO_BETA_SHIFT), BARO_V_LIMIT_T16)
        return self.estimate()

    @property
    def valid(self) -> bool:
        return self.ref_ticks >= BARO_REF_TICKS and not self.saturated

    @property
    def altitude_cm(self) -> int:
        return ((self.h_q8 >> 9) * 3277) >> 14  # mm / 10 without a division, as the C

    @property
    def climb_cm_s(self) -> int:
        return max(-32768, min(32767, _rshift(self.v_t16 * 25, 15)))

    def estimate(self) -> BoardBaroEstimate:
        return BoardBaroEstimate(
            altitude_m=self.h_q8 / 256000.0,
            climb_m_s=self.v_t16 * LOOP_HZ / 65536.0 / 1000.0,
            pressure_pa=_rshift(self.pf16, 4),
            valid=self.valid,
            saturated=self.saturated,
        )


def baro_count_of_pressure(pressure_pa: float) -> float:
    """The ideal (unrounded, unclamped) ADC6 count for a static pressure, firmware/HARDWARE.md's amplifier law."""
    v_sensor = 5.0 * (0.009 * pressure_pa / 1000.0 - 0.095)
    v_adc = 2.5 + 10.0 * (v_sensor - 4.05)
    return v_adc / 5.0 * 1024.0

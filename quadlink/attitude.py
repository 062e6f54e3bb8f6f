"""Roll and pitch from the 500 Hz IMU: Mahony-style complementary filter, gyro low-pass, gyro bias
(paper 000 section IV, refs. [17], [18]: Mahony, Hamel, Pflimlin 2008).

The accelerometer measures specific force in body FRD (level at rest: ``(0, 0, -g)``); its direction is
compared with the estimated "up" in the body, ``-R^T e_z``, and the cross product drives a proportional
correction plus an integral term that converges to minus the gyro bias. The correction is gated when the
specific force is far from ``g`` (manoeuvres). Yaw is integrated from the gyro only (unobservable here).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from quadlink.frames import GRAVITY_M_S2

Vec3 = NDArray[np.float64]


@dataclass(frozen=True)
class AttitudeConfig:
    kp_rad_s: float = 1.0             # proportional gain on the gravity-direction error (1/s)
    ki_rad_s2: float = 0.05           # integral gain (bias estimation)
    gyro_lowpass_hz: float = 30.0     # cut-off of the first-order low-pass on the gyro (omega_hat)
    accel_gate_m_s2: float = 3.0      # no correction when | |f| - g | exceeds this
    max_bias_rad_s: float = 0.2       # clamp of the bias estimate
    max_dt_s: float = 0.05            # longer gaps are integrated as this (stale IMU)


@dataclass(frozen=True)
class AttitudeEstimate:
    stamp_s: float
    roll_rad: float
    pitch_rad: float
    yaw_gyro_rad: float               # gyro-integrated yaw (drifts; VO provides yaw)
    omega_q_rad_s: Vec3               # low-passed, bias-corrected body rates
    gyro_bias_rad_s: Vec3
    R_wq: NDArray[np.float64]         # body -> level world (yaw from gyro integration)


def orthonormalise(R: NDArray[np.float64]) -> NDArray[np.float64]:
    u, _, vt = np.linalg.svd(R)
    return u @ vt


def as_floats(v: Vec3 | Sequence[float]) -> Sequence[float]:
    """Python floats of a small vector: ``tolist`` for arrays (iterating numpy scalars costs more)."""
    if isinstance(v, np.ndarray):
        return v.tolist()
    return v if isinstance(v, list) else [float(x) for x in v]


def quat_exp(wx: float, wy: float, wz: float) -> tuple[float, float, float, float]:
    """exp(w/2) = [cos(|w|/2), sin(|w|/2) w/|w|], [w, x, y, z], of a rotation vector w."""
    theta = math.sqrt(wx * wx + wy * wy + wz * wz)
    if theta < 1e-12:
        return 1.0, 0.0, 0.0, 0.0
    h = 0.5 * theta
    k = math.sin(h) / theta
    return math.cos(h), wx * k, wy * k, wz * k


def qmul(q: Sequence[float], p: Sequence[float]) -> tuple[float, float, float, float]:
    """Hamilton product q ⊗ p of quaternions [w, x, y, z]; scalar math for speed."""
    w, x, y, z = q
    c, bx, by, bz = p
    return (w * c - x * bx - y * by - z * bz, w * bx + x * c + y * bz - z * by,
            w * by - x * bz + y * c + z * bx, w * bz + x * by - y * bx + z * c)


def normalised(q: Sequence[float]) -> list[float]:
    w, x, y, z = q
    k = 1.0 / math.sqrt(w * w + x * x + y * y + z * z)
    return [w * k, x * k, y * k, z * k]


def qmul_exp(q: list[float], wx: float, wy: float, wz: float) -> list[float]:
    """q ⊗ exp(w/2) for a rotation vector w (body frame), renormalised."""
    return normalised(qmul(q, quat_exp(wx, wy, wz)))


def _clamp(v: float, lim: float) -> float:
    """v limited to [-lim, lim] (conditionals: the min/max builtins cost more at 500 Hz)."""
    return lim if v > lim else -lim if v < -lim else v


class AttitudeFilter:
    """Complementary attitude filter; call :meth:`update` for each IMU sample (stamps in seconds).

    Written in scalar math (a 500 Hz loop in Python: a few microseconds per sample, no numpy overhead).
    """

    def __init__(self, config: AttitudeConfig | None = None) -> None:
        self.config = config or AttitudeConfig()
        self._q = [1.0, 0.0, 0.0, 0.0]      # body -> world, [w, x, y, z]
        self._bias_corr = [0.0, 0.0, 0.0]  # integral term = minus the gyro bias
        self._omega_lp = [0.0, 0.0, 0.0]
        self._stamp: float | None = None
        self._lowpass_tau_s = 1.0 / (2.0 * math.pi * self.config.gyro_lowpass_hz)
        self._accel_hold_until_s = -math.inf   # the accelerometer's correction is skipped before this (correct_tilt)

    def reset(self) -> None:
        self.__init__(self.config)  # type: ignore[misc]

    @property
    def initialised(self) -> bool:
        return self._stamp is not None

    def _init_from_accel(self, fx: float, fy: float, fz: float) -> None:
        if fx * fx + fy * fy + fz * fz < 1e-6:
            return
        # at rest f = -g R^T e_z: roll = atan2(-f_y, -f_z), pitch = atan2(f_x, sqrt(f_y^2 + f_z^2))
        roll = math.atan2(-fy, -fz)
        pitch = math.atan2(fx, math.hypot(fy, fz))
        cr, sr, cp, sp = math.cos(roll / 2), math.sin(roll / 2), math.cos(pitch / 2), math.sin(pitch / 2)
        self._q = [cr * cp, sr * cp, cr * sp, -sr * sp]

    def update(self, stamp_s: float, gyro_q_rad_s: Vec3 | Sequence[float],
               accel_q_m_s2: Vec3 | Sequence[float]) -> None:
        """One IMU sample (gyro rad/s, specific force m/s², body FRD); bad samples are ignored."""
        cfg = self.config
        gx, gy, gz = as_floats(gyro_q_rad_s)
        fx, fy, fz = as_floats(accel_q_m_s2)
        if not math.isfinite(gx + gy + gz + fx + fy + fz):   # any nan/inf (or absurd 1e308s) in the sample
            return
        if self._stamp is None:
            self._init_from_accel(fx, fy, fz)
            self._stamp = stamp_s
            self._omega_lp = [gx, gy, gz]
            return
        dt = stamp_s - self._stamp
        self._stamp = stamp_s
        if dt <= 0.0:
            return
        if dt > cfg.max_dt_s:
            dt = cfg.max_dt_s
        bx, by, bz = self._bias_corr
        ox, oy, oz = gx + bx, gy + by, gz + bz                # bias-corrected rate
        w, x, y, z = qmul(self._q, quat_exp(ox * dt, oy * dt, oz * dt))   # predict with the gyro to this sample
        norm_f = math.sqrt(fx * fx + fy * fy + fz * fz)
        if norm_f > 1e-3 and abs(norm_f - GRAVITY_M_S2) < cfg.accel_gate_m_s2 and stamp_s >= self._accel_hold_until_s:
            # estimated "up" in body: -R^T e_z (third row of R, negated)
            ux, uy, uz = -2.0 * (x * z - w * y), -2.0 * (y * z + w * x), -(1.0 - 2.0 * (x * x + y * y))
            mx, my, mz = fx / norm_f, fy / norm_f, fz / norm_f  # measured "up" (specific force)
            ex, ey, ez = my * uz - mz * uy, mz * ux - mx * uz, mx * uy - my * ux   # e = v_meas x v_est
            lim = cfg.max_bias_rad_s
            k = cfg.ki_rad_s2 * dt
            self._bias_corr = [_clamp(bx + k * ex, lim), _clamp(by + k * ey, lim), _clamp(bz + k * ez, lim)]
            # proportional correction q ⊗ exp(kp e dT / 2), to first order (renormalised below): the angle
            # kp |e| dT is ~1e-5 rad in flight, and its relative error (kp |e| dT)^2 / 12
            h = 0.5 * cfg.kp_rad_s * dt
            w, x, y, z = qmul((w, x, y, z), (1.0, h * ex, h * ey, h * ez))
        self._q = normalised((w, x, y, z))
        alpha = dt / (dt + self._lowpass_tau_s)
        lx, ly, lz = self._omega_lp
        self._omega_lp = [lx + alpha * (ox - lx), ly + alpha * (oy - ly), lz + alpha * (oz - lz)]

    def correct_tilt(self, stamp_s: float, roll_rad: float, pitch_rad: float, fraction: float,
                     accel_hold_s: float = 0.0, bias_dt_s: float = 0.0, max_error_rad: float = math.radians(15.0)
                     ) -> bool:
        """Turn the estimate's tilt a ``fraction`` (0..1) of the way toward a reference attitude's roll and pitch
        (a visual odometry's: good through a manoeuvre, where the accelerometer's direction is the thrust axis, not
        gravity), feed the integral (gyro bias) term as the accelerometer's error would over ``bias_dt_s``, and skip
        the accelerometer's correction until ``stamp_s + accel_hold_s``. Nothing is done (False) for a non-finite
        reference, before the first IMU sample, or for a reference more than ``max_error_rad`` away."""
        if self._stamp is None or not (math.isfinite(roll_rad) and math.isfinite(pitch_rad)):
            return False
        w, x, y, z = self._q
        ux, uy, uz = -2.0 * (x * z - w * y), -2.0 * (y * z + w * x), -(1.0 - 2.0 * (x * x + y * y))   # estimated up
        sp, cp = math.sin(pitch_rad), math.cos(pitch_rad)
        mx, my, mz = sp, -math.sin(roll_rad) * cp, -math.cos(roll_rad) * cp     # the reference's up, in body
        ex, ey, ez = my * uz - mz * uy, mz * ux - mx * uz, mx * uy - my * ux    # e = v_ref x v_est
        sin_a = math.sqrt(ex * ex + ey * ey + ez * ez)
        angle = math.atan2(sin_a, mx * ux + my * uy + mz * uz)
        if angle > max_error_rad:
            return False
        if sin_a > 1e-12:
            k = min(max(fraction, 0.0), 1.0) * angle / sin_a
            self._q = normalised(qmul((w, x, y, z), quat_exp(k * ex, k * ey, k * ez)))
            lim = self.config.max_bias_rad_s
            ki = self.config.ki_rad_s2 * max(bias_dt_s, 0.0)
            bx, by, bz = self._bias_corr
            self._bias_corr = [_clamp(bx + ki * ex, lim), _clamp(by + ki * ey, lim), _clamp(bz + ki * ez, lim)]
        self._accel_hold_until_s = stamp_s + accel_hold_s
        return True

    @property
    def gyro_bias_rad_s(self) -> Vec3:
        return -np.array(self._bias_corr)

    def estimate(self, stamp_s: float | None = None) -> AttitudeEstimate:
        w, x, y, z = self._q
        roll = math.atan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
        pitch = math.asin(max(-1.0, min(1.0, 2.0 * (w * y - z * x))))
        yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
        R = np.array([
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
        return AttitudeEstimate(stamp_s if stamp_s is not None else (self._stamp or 0.0), roll, pitch, yaw,
                                np.array(self._omega_lp), -np.array(self._bias_corr), R)

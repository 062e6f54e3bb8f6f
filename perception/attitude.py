"""Roll and pitch from the 500 Hz IMU: Mahony-style complementary filter, gyro low-pass, gyro bias
(paper 000 section IV, refs. [17], [18]: Mahony, Hamel, Pflimlin 2008).

The accelerometer measures specific force in body FRD (level at rest: ``(0, 0, -g)``); its direction is
compared with the estimated "up" in the body, ``-R^T e_z``, and the cross product drives a proportional
correction plus an integral term that converges to minus the gyro bias. The correction is gated when the
specific force is far from ``g`` (manoeuvres). Yaw is integrated from the gyro only (unobservable here).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from quadlink.frames import GRAVITY_M_S2, skew

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


def so3_exp(w: Vec3) -> NDArray[np.float64]:
    theta = float(np.linalg.norm(w))
    W = skew(w)
    if theta < 1e-9:
        return np.eye(3) + W
    return np.eye(3) + math.sin(theta) / theta * W + (1.0 - math.cos(theta)) / theta**2 * (W @ W)


def orthonormalise(R: NDArray[np.float64]) -> NDArray[np.float64]:
    u, _, vt = np.linalg.svd(R)
    return u @ vt


def qmul_exp(q: list[float], wx: float, wy: float, wz: float) -> list[float]:
    """q ⊗ exp(w/2) for a rotation vector w (body frame), renormalised; scalar math for speed."""
    theta = math.sqrt(wx * wx + wy * wy + wz * wz)
    if theta < 1e-12:
        return q
    h = 0.5 * theta
    c = math.cos(h)
    k = math.sin(h) / theta
    bx, by, bz = wx * k, wy * k, wz * k
    w, x, y, z = q
    out = [w * c - x * bx - y * by - z * bz, w * bx + x * c + y * bz - z * by,
           w * by - x * bz + y * c + z * bx, w * bz + x * by - y * bx + z * c]
    n = math.sqrt(out[0] ** 2 + out[1] ** 2 + out[2] ** 2 + out[3] ** 2)
    return [v / n for v in out]


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

    def update(self, stamp_s: float, gyro_q_rad_s: Vec3 | list[float], accel_q_m_s2: Vec3 | list[float]) -> None:
        """One IMU sample (gyro rad/s, specific force m/s², body FRD); bad samples are ignored."""
        cfg = self.config
        gx, gy, gz = (float(v) for v in gyro_q_rad_s)
        fx, fy, fz = (float(v) for v in accel_q_m_s2)
        if not all(math.isfinite(v) for v in (gx, gy, gz, fx, fy, fz)):
            return
        if self._stamp is None:
            self._init_from_accel(fx, fy, fz)
            self._stamp = stamp_s
            self._omega_lp = [gx, gy, gz]
            return
        dt = min(max(stamp_s - self._stamp, 0.0), cfg.max_dt_s)
        self._stamp = stamp_s
        if dt <= 0.0:
            return
        b = self._bias_corr
        ox, oy, oz = gx + b[0], gy + b[1], gz + b[2]           # bias-corrected rate
        q = qmul_exp(self._q, ox * dt, oy * dt, oz * dt)      # predict with the gyro to this sample
        norm_f = math.sqrt(fx * fx + fy * fy + fz * fz)
        if norm_f > 1e-3 and abs(norm_f - GRAVITY_M_S2) < cfg.accel_gate_m_s2:
            w, x, y, z = q
            # estimated "up" in body: -R^T e_z (third row of R, negated)
            ux, uy, uz = -2.0 * (x * z - w * y), -2.0 * (y * z + w * x), -(1.0 - 2.0 * (x * x + y * y))
            mx, my, mz = fx / norm_f, fy / norm_f, fz / norm_f  # measured "up" (specific force)
            ex, ey, ez = my * uz - mz * uy, mz * ux - mx * uz, mx * uy - my * ux   # e = v_meas x v_est
            lim = cfg.max_bias_rad_s
            k = cfg.ki_rad_s2 * dt
            self._bias_corr = [min(lim, max(-lim, b[0] + k * ex)), min(lim, max(-lim, b[1] + k * ey)),
                               min(lim, max(-lim, b[2] + k * ez))]
            kp = cfg.kp_rad_s * dt
            q = qmul_exp(q, kp * ex, kp * ey, kp * ez)          # proportional correction
        self._q = q
        alpha = dt / (dt + 1.0 / (2.0 * math.pi * cfg.gyro_lowpass_hz))
        lp = self._omega_lp
        self._omega_lp = [lp[0] + alpha * (ox - lp[0]), lp[1] + alpha * (oy - lp[1]), lp[2] + alpha * (oz - lp[2])]

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

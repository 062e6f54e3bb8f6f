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

from quadlink.frames import GRAVITY_M_S2, euler_from_R, skew

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


class AttitudeFilter:
    """Complementary attitude filter; call :meth:`update` for each IMU sample (stamps in seconds)."""

    def __init__(self, config: AttitudeConfig | None = None) -> None:
        self.config = config or AttitudeConfig()
        self._R = np.eye(3)
        self._integral = np.zeros(3)
        self._omega_lp: Vec3 | None = None
        self._stamp: float | None = None
        self._n = 0

    def reset(self) -> None:
        self.__init__(self.config)  # type: ignore[misc]

    @property
    def initialised(self) -> bool:
        return self._stamp is not None

    def _init_from_accel(self, accel_q: Vec3) -> None:
        f = np.asarray(accel_q, dtype=float)
        if np.linalg.norm(f) < 1e-3:
            return
        # at rest f = -g R^T e_z: roll = atan2(-f_y, -f_z), pitch = atan2(f_x, sqrt(f_y^2 + f_z^2))
        roll = math.atan2(-f[1], -f[2])
        pitch = math.atan2(f[0], math.hypot(f[1], f[2]))
        from quadlink.frames import R_from_euler

        self._R = R_from_euler(roll, pitch, 0.0)

    def update(self, stamp_s: float, gyro_q_rad_s: Vec3, accel_q_m_s2: Vec3) -> AttitudeEstimate:
        cfg = self.config
        gyro = np.asarray(gyro_q_rad_s, dtype=float)
        accel = np.asarray(accel_q_m_s2, dtype=float)
        if not (np.all(np.isfinite(gyro)) and np.all(np.isfinite(accel))):
            return self.estimate(stamp_s)  # bad sample: keep the state
        if self._stamp is None:
            self._init_from_accel(accel)
            self._stamp = stamp_s
            self._omega_lp = gyro.copy()
            return self.estimate(stamp_s)
        dt = min(max(stamp_s - self._stamp, 0.0), cfg.max_dt_s)
        self._stamp = stamp_s
        if dt <= 0.0:
            return self.estimate(stamp_s)
        norm_f = float(np.linalg.norm(accel))
        e = np.zeros(3)
        if norm_f > 1e-3 and abs(norm_f - GRAVITY_M_S2) < cfg.accel_gate_m_s2:
            v_meas = accel / norm_f                      # measured "up" in body (specific force)
            v_est = -self._R[2, :]                        # estimated "up": -R^T e_z
            e = np.cross(v_meas, v_est)
            self._integral = np.clip(self._integral + cfg.ki_rad_s2 * e * dt, -cfg.max_bias_rad_s,
                                     cfg.max_bias_rad_s)
        omega = gyro + self._integral                     # bias-corrected rate
        self._R = self._R @ so3_exp((omega + cfg.kp_rad_s * e) * dt)
        self._n += 1
        if self._n % 500 == 0:
            self._R = orthonormalise(self._R)
        alpha = dt / (dt + 1.0 / (2.0 * math.pi * cfg.gyro_lowpass_hz))
        assert self._omega_lp is not None
        self._omega_lp = self._omega_lp + alpha * (omega - self._omega_lp)
        return self.estimate(stamp_s)

    def estimate(self, stamp_s: float | None = None) -> AttitudeEstimate:
        roll, pitch, yaw = euler_from_R(self._R)
        omega = self._omega_lp if self._omega_lp is not None else np.zeros(3)
        return AttitudeEstimate(stamp_s if stamp_s is not None else (self._stamp or 0.0), roll, pitch, yaw,
                                omega.copy(), -self._integral.copy(), self._R.copy())

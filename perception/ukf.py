"""Unscented Kalman filter fusing the IMU with the visual-odometry pose (paper 003, eqs. 7-11).

State (eq. 7): position ``x`` and velocity ``v`` in the local world W (NED-like), attitude quaternion
``Phi = [q0 q1 q2 q3]`` (eq. 8, ``[w, x, y, z]``, body Q -> W) and accelerometer bias ``a_b`` (eq. 9).
The attitude is carried as a quaternion in the mean and as a 3-vector body-frame error in the
covariance (12×12), so sigma points are ``q ⊗ exp(dtheta)``.

* **Prediction** (eq. 10), with the IMU input ``u = [Omega, a]`` (gyro, specific force in body FRD) and
  additive Gaussian process noise: ``x += v dT``, ``v += (R (a - a_b) + g) dT``, ``q ⊗= exp(Omega dT)``,
  ``a_b`` a random walk. IMU samples are averaged over ``predict_period_s`` (default 10 ms), so the
  filter's output rate is 100 Hz whatever the IMU rate.
* **Update** (eq. 11) with the odometry pose of the body, linear in the state: ``z = [x, dtheta] + eta``. The
  pipeline gives it the odometry's position and heading with the attitude filter's roll and pitch: the
  odometry's tilt drifts from gravity's, and a tilted world would be read as an accelerometer bias.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from quadlink.frames import GRAVITY_M_S2, R_from_quat_wxyz, euler_from_R, quat_wxyz_from_R
from quadlink.lie import so3_exp, so3_exp_batch, so3_log_batch

Vec3 = NDArray[np.float64]
N_ERR = 12  # p(3) v(3) dtheta(3) b_a(3)


@dataclass(frozen=True)
class UkfConfig:
    predict_period_s: float = 0.01        # 100 Hz prediction/output
    gyro_noise_rad_s: float = 0.02        # white noise std of the gyro (per sample, 500 Hz)
    accel_noise_m_s2: float = 0.5
    accel_bias_walk_m_s3: float = 0.01
    position_noise_m: float = 0.003       # VO position noise (1 sigma; frame-to-frame VO is ~1 mm)
    attitude_noise_rad: float = 0.02      # VO attitude noise (1 sigma)
    imu_rate_hz: float = 500.0
    alpha: float = 1.0                    # unscented transform spread
    beta: float = 2.0
    kappa: float = 0.0
    init_velocity_sigma_m_s: float = 0.5
    init_bias_sigma_m_s2: float = 0.3


@dataclass(frozen=True)
class UkfState:
    stamp_s: float
    position_w_m: Vec3
    velocity_w_m_s: Vec3
    q_wq_wxyz: NDArray[np.float64]
    accel_bias_m_s2: Vec3
    covariance: NDArray[np.float64]       # 12x12 error-state covariance

    @property
    def R_wq(self) -> NDArray[np.float64]:
        return R_from_quat_wxyz(self.q_wq_wxyz)

    @property
    def v_h_m_s(self) -> Vec3:
        """Velocity in H (world velocity rotated by minus the heading)."""
        yaw = euler_from_R(self.R_wq)[2]
        c, s = math.cos(yaw), math.sin(yaw)
        v = self.velocity_w_m_s
        return np.array([c * v[0] + s * v[1], -s * v[0] + c * v[1], v[2]])

    @property
    def v_h_cov(self) -> NDArray[np.float64]:
        yaw = euler_from_R(self.R_wq)[2]
        c, s = math.cos(yaw), math.sin(yaw)
        Rz_t = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
        return Rz_t @ self.covariance[3:6, 3:6] @ Rz_t.T


class Ukf:
    """Call :meth:`on_imu` at the IMU rate and :meth:`on_pose` per odometry pose; :attr:`state` at 100 Hz."""

    def __init__(self, config: UkfConfig | None = None) -> None:
        self.config = config or UkfConfig()
        cfg = self.config
        n = N_ERR
        lam = cfg.alpha**2 * (n + cfg.kappa) - n
        self._gamma = math.sqrt(n + lam)
        self._wm = np.full(2 * n + 1, 1.0 / (2.0 * (n + lam)))
        self._wc = self._wm.copy()
        self._wm[0] = lam / (n + lam)
        self._wc[0] = lam / (n + lam) + (1.0 - cfg.alpha**2 + cfg.beta)
        self._p = np.zeros(3)
        self._v = np.zeros(3)
        self._R = np.eye(3)
        self._b = np.zeros(3)
        self._P = np.diag([1e-4] * 3 + [cfg.init_velocity_sigma_m_s**2] * 3 + [0.05**2] * 3
                          + [cfg.init_bias_sigma_m_s2**2] * 3)
        self._t: float | None = None
        self._acc_gyro = np.zeros(3)
        self._acc_accel = np.zeros(3)
        self._acc_n = 0
        self._acc_t0: float | None = None
        self.initialised = False
        self.predictions = 0

    def initialise(self, stamp_s: float, R_wq: NDArray[np.float64], position_w_m: Vec3 | None = None) -> None:
        self._R = np.asarray(R_wq, dtype=float).copy()
        self._p = np.zeros(3) if position_w_m is None else np.asarray(position_w_m, dtype=float).copy()
        self._t = stamp_s
        self._acc_t0 = stamp_s
        self.initialised = True

    @property
    def state(self) -> UkfState:
        return UkfState(self._t or 0.0, self._p.copy(), self._v.copy(), quat_wxyz_from_R(self._R), self._b.copy(),
                        self._P.copy())

    def on_imu(self, stamp_s: float, gyro_q_rad_s: Vec3, accel_q_m_s2: Vec3) -> UkfState | None:
        """Accumulate a sample; returns the new state when a 100 Hz prediction ran."""
        if not self.initialised or self._acc_t0 is None:
            return None
        g = np.asarray(gyro_q_rad_s, dtype=float)
        a = np.asarray(accel_q_m_s2, dtype=float)
        if not (np.all(np.isfinite(g)) and np.all(np.isfinite(a))):
            return None
        self._acc_gyro += g
        self._acc_accel += a
        self._acc_n += 1
        dt = stamp_s - self._acc_t0
        if dt + 1e-9 < self.config.predict_period_s:
            return None
        self.predict(min(dt, 0.1), self._acc_gyro / self._acc_n, self._acc_accel / self._acc_n)
        self._t = stamp_s
        self._acc_t0 = stamp_s
        self._acc_gyro[:] = 0.0
        self._acc_accel[:] = 0.0
        self._acc_n = 0
        return self.state

    def _sigma(self) -> NDArray[np.float64]:
        n = N_ERR
        try:
            S = np.linalg.cholesky(self._P)
        except np.linalg.LinAlgError:
            w, V = np.linalg.eigh(0.5 * (self._P + self._P.T))
            S = V @ np.diag(np.sqrt(np.maximum(w, 1e-12)))
        D = np.zeros((2 * n + 1, n))
        D[1:n + 1] = self._gamma * S.T
        D[n + 1:] = -self._gamma * S.T
        return D

    def predict(self, dt_s: float, gyro_q_rad_s: Vec3, accel_q_m_s2: Vec3) -> None:
        """Unscented prediction over ``dt_s`` with the (averaged) IMU input, eq. (10)."""
        cfg = self.config
        D = self._sigma()
        p = self._p + D[:, 0:3]
        v = self._v + D[:, 3:6]
        R = self._R @ so3_exp_batch(D[:, 6:9])
        b = self._b + D[:, 9:12]
        f = accel_q_m_s2 - b                                         # bias-corrected specific force
        a_w = np.einsum("nij,nj->ni", R, f) + np.array([0.0, 0.0, GRAVITY_M_S2])
        p = p + v * dt_s + 0.5 * a_w * dt_s**2
        v = v + a_w * dt_s
        R = R @ so3_exp(np.asarray(gyro_q_rad_s, dtype=float) * dt_s)
        # mean: arithmetic for vectors, attitude about the propagated central point
        R0 = R[0]
        dth = so3_log_batch(np.einsum("ji,njk->nik", R0, R))
        wm, wc = self._wm, self._wc
        mean_dth = wm @ dth
        self._p, self._v, self._b = wm @ p, wm @ v, wm @ b
        self._R = R0 @ so3_exp(mean_dth)
        E = np.hstack([p - self._p, v - self._v, dth - mean_dth, b - self._b])
        P = (E * wc[:, None]).T @ E
        n_samples = max(1.0, dt_s * cfg.imu_rate_hz)
        # the mean of n white samples of std s, integrated over dt: variance s^2 dt^2 / n
        q_gyro = cfg.gyro_noise_rad_s**2 * dt_s**2 / n_samples
        q_acc = cfg.accel_noise_m_s2**2 * dt_s**2 / n_samples
        Q = np.diag([0.25 * q_acc * dt_s**2] * 3 + [q_acc] * 3 + [q_gyro] * 3
                    + [cfg.accel_bias_walk_m_s3**2 * dt_s] * 3)
        self._P = 0.5 * (P + P.T) + Q
        self.predictions += 1

    def on_pose(self, stamp_s: float, position_w_m: Vec3, R_wq: NDArray[np.float64]) -> UkfState:
        """Linear update with the odometry pose of the body, eq. (11)."""
        cfg = self.config
        if not self.initialised:
            self.initialise(stamp_s, R_wq, position_w_m)
            return self.state
        H = np.zeros((6, N_ERR))
        H[0:3, 0:3] = np.eye(3)
        H[3:6, 6:9] = np.eye(3)
        dth = so3_log_batch((self._R.T @ np.asarray(R_wq, dtype=float))[None])[0]
        y = np.concatenate([np.asarray(position_w_m, dtype=float) - self._p, dth])
        Rn = np.diag([cfg.position_noise_m**2] * 3 + [cfg.attitude_noise_rad**2] * 3)
        S = H @ self._P @ H.T + Rn
        K = np.linalg.solve(S, H @ self._P).T
        dx = K @ y
        self._p = self._p + dx[0:3]
        self._v = self._v + dx[3:6]
        self._R = self._R @ so3_exp(dx[6:9])
        self._b = self._b + dx[9:12]
        I_KH = np.eye(N_ERR) - K @ H
        self._P = I_KH @ self._P @ I_KH.T + K @ Rn @ K.T   # Joseph form
        return self.state

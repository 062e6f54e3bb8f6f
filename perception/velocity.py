"""Velocity of the body in the horizontal frame H from the visual odometry (paper 000 eqs. 9-13).

Per camera frame k with the odometry pose ``T_c0_ck`` (camera k in the first camera frame):

* 1€-filter the position ``C0 p_Ck`` and the orientation ``R_C0Ck`` (eq. 10's hatted quantities);
* camera velocity in Ck: ``Ck v_Ck = R_CkC0 (p_k - p_km1) / dT``            (eq. 10)
* body velocity in Q: ``Q v_Q = R_QC Ck v_Ck - omega_Q x Q p_C``            (eq. 12, from eq. 11)
* velocity in H:     ``H v_Q = R_HQ(roll, pitch) Q v_Q``                     (eq. 13)

Also gives the body pose in the local world W (NED-like: the level frame whose x is the body heading at
the first frame) for the position/yaw outputs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from perception.one_euro import OneEuroConfig, OneEuroFilter, OneEuroQuaternion
from quadlink.attitude import qmul
from quadlink.frames import R_hq, euler_from_R, quat_wxyz_from_R

Vec3 = NDArray[np.float64]


@dataclass(frozen=True)
class VelocityConfig:
    position_filter: OneEuroConfig = OneEuroConfig(min_cutoff_hz=2.0, beta=4.0, d_cutoff_hz=1.0)
    rotation_filter: OneEuroConfig = OneEuroConfig(min_cutoff_hz=3.0, beta=2.0, d_cutoff_hz=1.0)
    sigma_m_s: float = 0.05          # 1-sigma of each velocity component when the odometry is ok
    sigma_lost_m_s: float = 1.0      # ... when it failed (the estimate is held, decaying)
    max_dt_s: float = 0.5            # a longer gap restarts the differentiation
    lost_decay_s: float = 0.5        # while the odometry fails, the last velocity decays to 0 with this time
                                     # constant (0: held as it was): the map's time update (eq. 14) moves on it,
                                     # and the vehicle, in HOLD, brakes. Held, a wrong last reading (3.5 m/s of
                                     # climb read in front of the SITL's black partition) moved the map 1 m in
                                     # 0.6 s of failure and its floor became a wall at the vehicle's level

    def __post_init__(self) -> None:
        if not self.lost_decay_s >= 0.0:
            raise ValueError(f"lost_decay_s must be >= 0 s, got {self.lost_decay_s}")


@dataclass(frozen=True)
class VelocityEstimate:
    stamp_s: float
    v_h_m_s: Vec3
    v_q_m_s: Vec3
    v_c_m_s: Vec3
    v_h_cov: NDArray[np.float64]
    valid: bool


def body_pose_in_world(T_c0_ck: NDArray[np.float64], R_qc: NDArray[np.float64], p_qc_m: Vec3,
                       R_w_q0: NDArray[np.float64]) -> tuple[NDArray[np.float64], Vec3]:
    """Body orientation ``R_w_qk`` and position ``w p_qk`` from the camera odometry pose.

    ``T_q0_qk = T_qc T_c0_ck T_qc^-1``; the world is the body frame at k=0 levelled by ``R_w_q0``
    (roll/pitch of the first frame, yaw 0), origin at the first body position.
    """
    R_c = T_c0_ck[:3, :3]
    t_c = T_c0_ck[:3, 3]
    R_q0_qk = R_qc @ R_c @ R_qc.T
    # p_q0_qk = R_qc t_c + p_qc - R_q0_qk p_qc
    p_q0_qk = R_qc @ t_c + p_qc_m - R_q0_qk @ p_qc_m
    return R_w_q0 @ R_q0_qk, R_w_q0 @ p_q0_qk


class VelocityEstimator:
    """Eqs. (10)-(13) on a stream of odometry poses."""

    def __init__(self, R_qc: NDArray[np.float64], p_qc_m: Vec3, config: VelocityConfig | None = None) -> None:
        self.config = config or VelocityConfig()
        self.R_qc = np.asarray(R_qc, dtype=float)
        self.p_qc_m = np.asarray(p_qc_m, dtype=float)
        self._pos = OneEuroFilter(self.config.position_filter)
        self._rot = OneEuroQuaternion(self.config.rotation_filter)
        self._prev_p: list[float] | None = None
        self._prev_t: float | None = None
        self._last_v_c = np.zeros(3)
        self._last_valid_s: float | None = None
        # the two covariances handed out (read-only, shared by every estimate)
        self._cov_ok = _read_only(np.eye(3) * self.config.sigma_m_s**2)
        self._cov_lost = _read_only(np.eye(3) * self.config.sigma_lost_m_s**2)

    def reset(self) -> None:
        self._pos.reset()
        self._rot.reset()
        self._prev_p = None
        self._prev_t = None
        self._last_v_c = np.zeros(3)
        self._last_valid_s = None

    def update(self, stamp_s: float, T_c0_ck: NDArray[np.float64], odometry_ok: bool, omega_q_rad_s: Vec3,
               roll_rad: float, pitch_rad: float) -> VelocityEstimate:
        cfg = self.config
        p_hat = self._pos.filter(stamp_s, T_c0_ck[:3, 3].tolist())
        q_hat = self._rot.filter(stamp_s, quat_wxyz_from_R(T_c0_ck[:3, :3]).tolist())
        valid = False
        if self._prev_p is not None and self._prev_t is not None:
            dt = stamp_s - self._prev_t
            if 0.0 < dt <= cfg.max_dt_s and odometry_ok:
                dp = [(a - b) / dt for a, b in zip(p_hat, self._prev_p, strict=True)]
                # eq. (10): R_hat^T dp / dT, as q_hat^-1 ⊗ dp ⊗ q_hat
                self._last_v_c = np.array(qmul(qmul(_conj(q_hat), (0.0, *dp)), q_hat)[1:])
                self._last_valid_s = stamp_s
                valid = True
        if self._prev_t is None or stamp_s > self._prev_t:
            self._prev_p, self._prev_t = p_hat, stamp_s
        v_c = self._last_v_c
        if not valid and cfg.lost_decay_s > 0.0 and self._last_valid_s is not None:
            v_c = v_c * math.exp(-max(stamp_s - self._last_valid_s, 0.0) / cfg.lost_decay_s)
        wx, wy, wz = np.asarray(omega_q_rad_s, dtype=float).tolist()
        px, py, pz = self.p_qc_m.tolist()
        # eq. (12): - omega x Q p_C, written out (np.cross costs ~50 us on 3-vectors)
        v_q = self.R_qc @ v_c - np.array([wy * pz - wz * py, wz * px - wx * pz, wx * py - wy * px])
        v_h = R_hq(roll_rad, pitch_rad) @ v_q                                 # eq. (13)
        return VelocityEstimate(stamp_s, v_h, v_q, v_c.copy(), self._cov_ok if valid else self._cov_lost, valid)


def _read_only(a: NDArray[np.float64]) -> NDArray[np.float64]:
    a.flags.writeable = False
    return a


def _conj(q: list[float]) -> tuple[float, float, float, float]:
    return q[0], -q[1], -q[2], -q[3]


def yaw_of(R_w_q: NDArray[np.float64]) -> float:
    return euler_from_R(R_w_q)[2]

"""Haptic force feedback, paper 000 eqs. (15)-(18). Pure: inputs and time in, force out.

``tau = -B q' - K_f q - K (q - q~)`` (eq. (15)) with ``q~`` the device position that would command
what the vehicle actually does:

* ``q~_x = (cos a, sin a) . (v_x, v_y)_H / k_v``                     eq. (16)
* ``q~_psi = (psi' - psi_s') / (yaw_sign k_psi)``                    eq. (17)
* ``q~_z = v_z,H / k_v``                                             eq. (18)

eq. (17) is written with the sign of the mapping (eq. (3) has psi_d' = -k_psi q_y), so that q = q~
exactly when the vehicle follows the command, and the cue vanishes. The paper's mapping has no dead-band;
ours has one (the device's and the companion's, ``MappingGains.command_onset_m``), so ``q~`` adds back
``sign(q) min(|q|, onset)``: beyond the onset the cue is ``K (v_commanded - v) / k`` and it vanishes when the
vehicle follows; inside it the cue is the vehicle's own motion ``-K v / k``, with no extra stiffness.
Without it the cue held a 6 mm offset, 0.38 N against every push at ``K`` 60 N/m, and the handle
stopped at less than half the travel the operator's force asked for. The force is saturated (norm,
direction kept) at the device limit and multiplied by a link gain that ramps (rate-limited, never
a jump) to 0 when the vehicle link is lost and back to 1 when it returns.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from teleop.config import ForceConfig
from teleop.mapping import MappingGains

Vec3 = NDArray[np.float64]


@dataclass(frozen=True)
class VehicleMotion:
    """What the vehicle does, from TELEOP_FEEDBACK (H frame, NED, SI)."""

    v_h_m_s: tuple[float, float, float]     # estimated velocity in H (eq. (13))
    alpha_rad: float                        # forward direction of the command in H (eq. (6))
    yaw_rate_rad_s: float                   # estimated (gyro) yaw rate
    pan_scan_yaw_rate_rad_s: float          # pan-scan component of the yaw rate (psi_s')


def q_tilde(motion: VehicleMotion, gains: MappingGains, q_m: Vec3 | None = None) -> Vec3:
    """eqs. (16)-(18): device position equivalent to the vehicle's actual motion.

    With the handle's position ``q_m``, the mapping's dead-band is added back (module docstring); without
    it, the paper's eqs. as written (a mapping without dead-band).
    """
    vx, vy, vz = motion.v_h_m_s
    q_x = (math.cos(motion.alpha_rad) * vx + math.sin(motion.alpha_rad) * vy) / gains.k_v_xy_per_s  # eq. (16)
    q_psi = (motion.yaw_rate_rad_s - motion.pan_scan_yaw_rate_rad_s) / (gains.yaw_sign * gains.k_psi_rad_s_m)  # (17)
    q_z = vz / gains.k_v_z_per_s  # eq. (18)
    qt = [v if math.isfinite(v) else 0.0 for v in (q_x, q_psi, q_z)]
    if q_m is not None:
        for i, onset in enumerate(gains.command_onset_m):
            q = float(q_m[i])
            if math.isfinite(q):
                qt[i] += math.copysign(min(abs(q), onset), q)
    return np.array(qt)


def saturate(force_n: Vec3, limit_n: float) -> Vec3:
    """Scale the force down to the device limit, keeping its direction."""
    norm = float(np.linalg.norm(force_n))
    if not math.isfinite(norm):
        return np.zeros(3)
    return force_n * (limit_n / norm) if norm > limit_n else force_n


def force_law(q_m: Vec3, qdot_m_s: Vec3, q_tilde_m: Vec3 | None, cfg: ForceConfig, force_limit_n: float,
              link_gain: float = 1.0, cue_gain: float = 1.0) -> Vec3:
    """eq. (15), saturated, times the link gain in [0, 1]. ``q_tilde_m=None``: no feedback yet (no cue).

    ``cue_gain`` in [0, 1] scales the haptic-cue term K (q - q~): the station fades it out while the
    companion flies autonomously (take-off, landing), where the vehicle's motion is not the operator's
    command and feeding it back would pull the handle (and, through the mapping, the next command).
    Plain floats inside: this runs at 1 kHz and numpy's per-call overhead dominates on 3-vectors.
    """
    q, qd = [float(v) for v in q_m], [float(v) for v in qdot_m_s]
    cue = min(max(cue_gain, 0.0), 1.0) if q_tilde_m is not None else 0.0
    qt = [float(v) for v in q_tilde_m] if q_tilde_m is not None else [0.0, 0.0, 0.0]
    B, K_f, K = cfg.B_n_s_m, cfg.K_f_n_m, cfg.K_n_m
    tau = [-B[i] * qd[i] - K_f[i] * q[i] - cue * K[i] * (q[i] - qt[i]) for i in range(3)]
    norm = math.sqrt(tau[0] * tau[0] + tau[1] * tau[1] + tau[2] * tau[2])
    if not math.isfinite(norm):
        return np.zeros(3)
    scale = min(max(link_gain, 0.0), 1.0) * (force_limit_n / norm if norm > force_limit_n else 1.0)
    return np.array([scale * t for t in tau])


class LinkFade:
    """Link gain that moves toward 1 (link ok) or 0 (link lost) at most ``1/fade_time_s`` per second.

    Pure: ``update`` takes the time; the gain is continuous in time whatever the link does.
    """

    def __init__(self, fade_time_s: float, initial_gain: float = 0.0) -> None:
        self.rate_per_s = 1.0 / fade_time_s
        self.gain = initial_gain
        self._t_s: float | None = None

    def update(self, link_ok: bool, t_s: float) -> float:
        dt = 0.0 if self._t_s is None else max(t_s - self._t_s, 0.0)
        self._t_s = t_s
        target = 1.0 if link_ok else 0.0
        step = self.rate_per_s * dt
        self.gain = min(self.gain + step, target) if target > self.gain else max(self.gain - step, target)
        return self.gain


def link_ok(last_feedback_t_s: float | None, t_s: float, timeout_s: float) -> bool:
    return last_feedback_t_s is not None and 0.0 <= t_s - last_feedback_t_s <= timeout_s

"""The companion's position loop on a trajectory (pure): v_ref = v_d - k_p e_x, with a_d as feed-forward.

Issue 19: the companion stays the one arbiter of motion. It closes the position loop on its own odometry and
hands the autopilot a velocity reference plus the trajectory's acceleration (SET_POSITION_TARGET_LOCAL_NED with
the velocity and acceleration bits); the reference passes through the same safety layer as every other command
before it leaves. Wiring: the arbiter (:mod:`companion.arbiter`) takes a ground station's position + velocity +
acceleration setpoints and calls :func:`position_loop` at camera rate; its velocity goes through
:func:`companion.reference.reference_velocity` like any command, and :func:`feed_forward_after_safety` decides
whether the acceleration goes with the result.

With the bridge's geometric tracker (``firmware_bridge.geometric_tracker``, velocity-only mode) the cascade is
paper 003's eq. (4) exactly:

    a = a_d - k_v (v - v_ref) = a_d - k_v e_v - (k_v k_p) e_x        (e_x = x - x_d, e_v = v - v_d, eq. 6)

so eq. (4)'s k_x / m is ``k_v * k_p`` (defaults: 3.2 * 1.25 = 4.0 1/s^2, the tracker's own k_x).

Frames: local NED (the odometry's frame; the trajectory's waypoints are in it). :meth:`FollowCommand.in_h`
rotates into the yaw-aligned H for consumers that work there.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from quadlink.frames import Rz
from quadlink.mavlink import mavlink
from quadlink.mavlink.setpoint_masks import TM_VELOCITY_ACCEL_YAW_RATE
from quadlink.trajectory import MinSnapTrajectory, TrajectorySample

Vec3 = NDArray[np.float64]

#: velocity + acceleration + yaw rate (position and yaw ignored): 1479 (the companion's velocity setpoint) with the
#: acceleration bits cleared
TYPE_MASK_VELOCITY_ACCEL_YAW_RATE = TM_VELOCITY_ACCEL_YAW_RATE


@dataclass(frozen=True)
class FollowGains:
    k_p_1_s: float = 1.25  # m/s of velocity correction per m of position error
    max_correction_m_s: float = 1.0  # |k_p e_x| is clamped to this (a large error is not a sprint)


@dataclass(frozen=True)
class FollowCommand:
    """What the companion sends toward the autopilot for one step (local NED)."""

    t_s: float  # trajectory time
    v_ref_ned_m_s: Vec3
    a_ff_ned_m_s2: Vec3
    e_x_ned_m: Vec3  # x - x_d
    p_d_ned_m: Vec3
    yaw_rad: float | None = None

    def in_h(self, yaw_rad: float) -> tuple[Vec3, Vec3]:
        R_hw = Rz(-yaw_rad)
        return R_hw @ self.v_ref_ned_m_s, R_hw @ self.a_ff_ned_m_s2

    def setpoint_message(self, time_s: float, target_system: int, target_component: int, yaw_rad: float,
                         yaw_rate_rad_s: float) -> Any:
        """SET_POSITION_TARGET_LOCAL_NED with velocity and acceleration in H (MAV_FRAME_BODY_OFFSET_NED, as the
        companion's velocity setpoints: rotated by the companion's yaw, so its world frame need not be the bridge's)
        and a yaw rate. ``firmware_bridge.geometric_tracker.decode_trajectory_setpoint`` reads it back."""
        v_h, a_h = self.in_h(yaw_rad)
        return mavlink.MAVLink_set_position_target_local_ned_message(
            int(max(time_s, 0.0) * 1e3) & 0xFFFFFFFF, target_system, target_component,
            mavlink.MAV_FRAME_BODY_OFFSET_NED, TYPE_MASK_VELOCITY_ACCEL_YAW_RATE, 0.0, 0.0, 0.0,
            float(v_h[0]), float(v_h[1]), float(v_h[2]), float(a_h[0]), float(a_h[1]), float(a_h[2]), 0.0,
            float(yaw_rate_rad_s))


def feed_forward_after_safety(a_ff_h_m_s2: ArrayLike | None, constrained: bool,
                              v_repulsion_h_m_s: ArrayLike) -> Vec3 | None:
    """The acceleration feed-forward to send with the safety layer's velocity (H, m/s^2), or None.

    a_d belongs to the trajectory's velocity: once the safety layer changed that velocity (a constraint acted:
    an obstacle's closing-speed law, the safe distance, an unknown sector, the vertical limits, the speed
    limit; or the repulsion added to it), the feed-forward would push on toward what the layer is avoiding,
    so the vehicle gets the constrained velocity alone."""
    if a_ff_h_m_s2 is None or constrained:
        return None
    if float(np.linalg.norm(np.asarray(v_repulsion_h_m_s, dtype=float))) > 1e-9:
        return None
    a = np.asarray(a_ff_h_m_s2, dtype=float).reshape(3)
    return a.copy() if bool(np.all(np.isfinite(a))) else None


def position_loop(sample: TrajectorySample, p_est_ned_m: ArrayLike, gains: FollowGains | None = None,
                  yaw_rad: float | None = None) -> FollowCommand:
    """One step: the desired flat output and the estimated position -> velocity reference + acceleration."""
    g = gains or FollowGains()
    p = np.asarray(p_est_ned_m, dtype=float)
    e_x = p - sample.p_m
    correction = -g.k_p_1_s * e_x
    n = float(np.linalg.norm(correction))
    if n > g.max_correction_m_s:
        correction *= g.max_correction_m_s / n
    return FollowCommand(sample.t_s, sample.v_m_s + correction, sample.a_m_s2.copy(), e_x, sample.p_m.copy(),
                         yaw_rad)


class TrajectoryFollower:
    """A trajectory flown from ``start_s`` (the caller's clock), offset so it starts where the vehicle is or at
    its own first waypoint (``relative``)."""

    def __init__(self, trajectory: MinSnapTrajectory, start_s: float, gains: FollowGains | None = None,
                 origin_ned_m: ArrayLike | None = None, yaw_rad: float | None = None) -> None:
        self.trajectory = trajectory
        self.start_s = float(start_s)
        self.gains = gains or FollowGains()
        self.offset_ned_m = np.zeros(3) if origin_ned_m is None else \
            np.asarray(origin_ned_m, dtype=float) - trajectory.sample(0.0).p_m
        self.yaw_rad = yaw_rad

    def done(self, now_s: float) -> bool:
        return now_s - self.start_s >= self.trajectory.duration_s

    def sample(self, now_s: float) -> TrajectorySample:
        s = self.trajectory.sample(now_s - self.start_s)
        return TrajectorySample(s.t_s, s.p_m + self.offset_ned_m, s.v_m_s, s.a_m_s2, s.j_m_s3)

    def step(self, now_s: float, p_est_ned_m: ArrayLike) -> FollowCommand:
        if not np.all(np.isfinite(np.asarray(p_est_ned_m, dtype=float))):
            raise ValueError("position estimate is not finite")
        if not math.isfinite(now_s):
            raise ValueError("time is not finite")
        return position_loop(self.sample(now_s), p_est_ned_m, self.gains, self.yaw_rad)

"""The velocity tracker: PID on the velocity error in H with gravity compensation (pure, step-based).

Paper 000 section III: "a simple PID controller with gravity compensation computing the required
thrust, roll and pitch angles that are needed to accelerate as requested ... the integral term is
computed simply integrating the error of the velocity. Yaw rate is tracked in a similar fashion
using the yaw torque command." The MK FlightCtrl closes the attitude and yaw-rate loops on board, so
the tracker outputs roll, pitch, yaw rate and collective thrust (an :class:`AttitudeCommand`).

Frames: H is the horizontal frame (NED, x along the heading, z down, paper 000 section II), so a
velocity in H does not depend on roll and pitch. Thrust acts along -z of the body frame Q (FRD):

    a_h = g e3 - (T / m) R_hq e3 + d / m            (translational dynamics in H, yaw-aligned)

The desired acceleration ``a_des = kp e + ki int(e) - kd dv/dt`` (e = v_ref - v_est) is turned into
the force ``f = m (a_des - g e3)``; its direction gives roll and pitch exactly (no small-angle
approximation) and the thrust magnitude uses the hover compensation ``m (g - a_z) / (cos phi cos theta)``
with the *measured* roll and pitch (as paper 003's geometric controller projects the desired force on
the current body axis, eq. (4)).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from quadlink.frames import GRAVITY_M_S2


@dataclass(frozen=True)
class TrackerGains:
    """Gains and limits of the tracker (the bridge exposes them as MAVLink parameters)."""

    kp_xy_1_s: float = 2.0  # horizontal: m/s^2 of acceleration per m/s of velocity error
    ki_xy_1_s2: float = 0.6
    kd_xy_s: float = 0.05  # on the (filtered) measured acceleration, not on the reference
    kp_z_1_s: float = 3.0
    ki_z_1_s2: float = 1.0
    kd_z_s: float = 0.0
    integral_max_xy_m_s2: float = 2.0  # anti-windup clamp of the integral term (acceleration units)
    integral_max_z_m_s2: float = 3.0
    max_tilt_rad: float = math.radians(25.0)
    max_speed_xy_m_s: float = 3.0
    max_climb_m_s: float = 1.5  # upwards (NED -z)
    max_descent_m_s: float = 1.0
    max_yaw_rate_rad_s: float = math.radians(90.0)
    max_accel_down_m_s2: float = 0.6 * GRAVITY_M_S2  # never command (near) free fall
    thrust_min_fraction: float = 0.05
    thrust_max_fraction: float = 0.95
    derivative_cutoff_hz: float = 10.0


@dataclass(frozen=True)
class AttitudeCommand:
    """Output of one tracker step, for the board's attitude loop."""

    roll_rad: float
    pitch_rad: float
    yaw_rate_rad_s: float
    thrust_fraction: float  # collective thrust / max total thrust, 0..1
    a_des_h_m_s2: tuple[float, float, float] = (0.0, 0.0, 0.0)  # diagnostics
    saturated: bool = False


@dataclass
class _TrackerState:
    integral_h_m_s2: np.ndarray = field(default_factory=lambda: np.zeros(3))
    v_prev_h: np.ndarray | None = None
    accel_filt_h: np.ndarray = field(default_factory=lambda: np.zeros(3))


class VelocityTracker:
    """PID velocity tracker with gravity compensation, stepped at the command rate (100 Hz)."""

    def __init__(self, mass_kg: float, max_total_thrust_n: float, gains: TrackerGains | None = None) -> None:
        if mass_kg <= 0 or max_total_thrust_n <= mass_kg * GRAVITY_M_S2:
            raise ValueError("the vehicle needs mass > 0 and max thrust above its weight")
        self.mass_kg = mass_kg
        self.max_total_thrust_n = max_total_thrust_n
        self.gains = gains or TrackerGains()
        self._s = _TrackerState()

    @property
    def hover_thrust_fraction(self) -> float:
        return self.mass_kg * GRAVITY_M_S2 / self.max_total_thrust_n

    @property
    def integral_h_m_s2(self) -> np.ndarray:
        return self._s.integral_h_m_s2.copy()

    def set_gains(self, gains: TrackerGains) -> None:
        self.gains = gains

    def reset(self) -> None:
        """Forget the integral and the derivative history (on the ground, on mode changes to idle)."""
        self._s = _TrackerState()

    def clamp_reference(self, v_ref_h: np.ndarray, yaw_rate_ref_rad_s: float) -> tuple[np.ndarray, float]:
        """The reference as the tracker will follow it (speed, climb, descent and yaw-rate limits)."""
        g = self.gains
        v = np.array(v_ref_h, dtype=float)
        speed = math.hypot(v[0], v[1])
        if speed > g.max_speed_xy_m_s:
            v[:2] *= g.max_speed_xy_m_s / speed
        v[2] = min(max(v[2], -g.max_climb_m_s), g.max_descent_m_s)
        yaw_rate = min(max(float(yaw_rate_ref_rad_s), -g.max_yaw_rate_rad_s), g.max_yaw_rate_rad_s)
        return v, yaw_rate

    def update(self, dt_s: float, v_ref_h: np.ndarray, yaw_rate_ref_rad_s: float, v_est_h: np.ndarray,
               roll_rad: float, pitch_rad: float) -> AttitudeCommand:
        """One step: velocity reference and estimate in H (m/s, NED) -> attitude/thrust command."""
        g = self.gains
        s = self._s
        dt_s = min(max(float(dt_s), 1e-4), 0.1)  # a stalled clock must not blow the integral up
        v_ref, yaw_rate = self.clamp_reference(v_ref_h, yaw_rate_ref_rad_s)
        v_est = np.asarray(v_est_h, dtype=float)
        if not np.all(np.isfinite(v_est)):
            v_est = np.zeros(3)
        err = v_ref - v_est

        # derivative on the measurement (no kick on reference steps), first-order low-pass
        if s.v_prev_h is not None:
            accel_raw = (v_est - s.v_prev_h) / dt_s
            alpha = dt_s / (dt_s + 1.0 / (2.0 * math.pi * g.derivative_cutoff_hz))
            s.accel_filt_h = s.accel_filt_h + alpha * (accel_raw - s.accel_filt_h)
        s.v_prev_h = v_est.copy()

        kp = np.array([g.kp_xy_1_s, g.kp_xy_1_s, g.kp_z_1_s])
        ki = np.array([g.ki_xy_1_s2, g.ki_xy_1_s2, g.ki_z_1_s2])
        kd = np.array([g.kd_xy_s, g.kd_xy_s, g.kd_z_s])
        a_unsat = kp * err + s.integral_h_m_s2 - kd * s.accel_filt_h
        a_des, saturated = self._limit_acceleration(a_unsat)

        # integral on the velocity error (paper 000 sec. III), conditional integration as anti-windup:
        # an axis does not integrate further into the direction its output is saturated in.
        step = ki * err * dt_s
        excess = a_unsat - a_des
        winding_up = (np.abs(excess) > 1e-9) & (np.sign(step) == np.sign(excess))
        step = np.where(winding_up, 0.0, step)
        integral = s.integral_h_m_s2 + step
        lim = np.array([g.integral_max_xy_m_s2, g.integral_max_xy_m_s2, g.integral_max_z_m_s2])
        s.integral_h_m_s2 = np.clip(integral, -lim, lim)

        roll_cmd, pitch_cmd = self.angles_from_acceleration(a_des)
        thrust = self.thrust_from_acceleration(a_des[2], roll_rad, pitch_rad)
        if thrust != self._clip_thrust(thrust):
            saturated = True
        return AttitudeCommand(roll_rad=roll_cmd, pitch_rad=pitch_cmd, yaw_rate_rad_s=yaw_rate,
                               thrust_fraction=self._clip_thrust(thrust),
                               a_des_h_m_s2=(float(a_des[0]), float(a_des[1]), float(a_des[2])),
                               saturated=saturated)

    def _limit_acceleration(self, a: np.ndarray) -> tuple[np.ndarray, bool]:
        """Vertical: no more than max_accel_down downwards, thrust headroom upwards; horizontal: tilt limit."""
        g = self.gains
        out = np.array(a, dtype=float)
        saturated = False
        a_up_max = self.max_total_thrust_n * g.thrust_max_fraction * math.cos(g.max_tilt_rad) / self.mass_kg \
            - GRAVITY_M_S2
        z = min(max(out[2], -a_up_max), g.max_accel_down_m_s2)
        saturated = saturated or bool(z != out[2])
        out[2] = z
        # the force direction must stay within max_tilt of the vertical: |a_xy| <= (g - a_z) tan(max_tilt)
        a_xy_max = (GRAVITY_M_S2 - out[2]) * math.tan(g.max_tilt_rad)
        norm_xy = math.hypot(out[0], out[1])
        if norm_xy > a_xy_max:
            out[:2] *= a_xy_max / norm_xy
            saturated = True
        return out, saturated

    def angles_from_acceleration(self, a_des_h: np.ndarray) -> tuple[float, float]:
        """Exact roll/pitch (ZYX, yaw-aligned) whose thrust axis points along m (a_des - g e3)."""
        f = np.asarray(a_des_h, dtype=float) - np.array([0.0, 0.0, GRAVITY_M_S2])  # per unit mass
        norm = float(np.linalg.norm(f))
        if norm < 1e-6:
            return 0.0, 0.0
        # body z axis b3 = -f/|f| = R_hq e3 = [sin(theta) cos(phi), -sin(phi), cos(theta) cos(phi)]
        roll = math.asin(min(max(f[1] / norm, -1.0), 1.0))
        pitch = math.atan2(-f[0], -f[2])
        return roll, pitch

    def thrust_from_acceleration(self, a_z_des_m_s2: float, roll_rad: float, pitch_rad: float) -> float:
        """Hover compensation: T = m (g - a_z) / (cos phi cos theta), as a fraction of the max thrust."""
        tilt_cos = math.cos(roll_rad) * math.cos(pitch_rad)
        tilt_cos = max(tilt_cos, math.cos(min(1.5 * self.gains.max_tilt_rad, math.radians(60.0))))
        return float(self.mass_kg * (GRAVITY_M_S2 - a_z_des_m_s2) / tilt_cos / self.max_total_thrust_n)

    def _clip_thrust(self, thrust: float) -> float:
        return min(max(thrust, self.gains.thrust_min_fraction), self.gains.thrust_max_fraction)

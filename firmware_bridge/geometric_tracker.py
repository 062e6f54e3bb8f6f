"""The geometric tracker on SE(3) (paper 003 eqs. 3-6, after Lee et al.): pure, step-based, beside the PID tracker.

Paper 003 frames: W is the inertial frame with e3 pointing *down* (its model ``m dv/dt = -tau R e3 + m g e3``,
eq. 1), which is quadlink's local NED; R = R_ned_q (body FRD -> NED). The errors are (eq. 6)

    e_x = x - x_d,        e_v = v - v_d,

and the thrust of eq. (4) is the desired force projected on the *measured* body z axis:

    f_des = -k_x e_x - k_v e_v - m g e3 + m a_d        (the force the rotors must produce, NED)
    tau   = -f_des . (R e3)                             (eq. 4; R is the estimated attitude)

(in NED the rotors push along -b3, so the hover force is -m g e3 and tau = m g; the z-up form of the
same law reads ``+ m g e3``.) The commanded attitude R_c = [b1c b2c b3c] comes from the desired force and the
heading b1d (Lee et al.): b3c = -f_des / |f_des|, b2c = b3c x b1d / |b3c x b1d|, b1c = b2c x b3c; the
commanded angular velocity Omega_c is the body rate of R_c (``hat(Omega_c) = R_c^T dR_c/dt``), here finite
differenced between steps and low-passed.

Who realises which term (the MK board closes the attitude loop, as on the real FlightCtrl):

=====================================================  ==========================================================
term                                                   where
=====================================================  ==========================================================
e_x, e_v, f_des, tau (eq. 4, 6) with a_d feed-forward  **bridge** (this module), 100 Hz; e_x only when a position
                                                       is given — otherwise the companion closes the position
                                                       loop, v_ref = v_d - k_p e_x, and the cascade is eq. (4)
                                                       with k_x = k_v k_p
R_c from f_des and b1d, Omega_c                        **bridge**: R_c goes to the board as ZYX roll/pitch at the
                                                       current heading (the thrust axis exactly, ``board_angles``)
                                                       and its heading through the yaw rate (Omega_c's z + P)
-k_R e_R (eq. 3, 5)                                    **board**: angle P loop (roll/pitch error -> rate setpoint);
                                                       heading: the bridge's P term on yaw -> the board's yaw-rate
-k_Omega e_Omega (eq. 3, 5)                            **board**: rate PID (roll, pitch), rate PI (yaw)
Omega x J Omega                                        **board**: gyroscopic feed-forward in its torque
-J (hat(Omega) R^T R_c Omega_c - R^T R_c dOmega_c/dt)  **not realised** for roll/pitch: the board's setpoint frame
                                                       carries no rate feed-forward (the yaw component of Omega_c
                                                       is sent as the yaw-rate setpoint). Omega_c is computed and
                                                       reported so a firmware frame extension can carry it.
=====================================================  ==========================================================

The angular errors e_R, e_Omega are therefore the board's, in Euler-angle form (equivalent to eq. 5 to first
order about the commanded attitude); the exponential stability of [23] holds for the inner loop only as far as the
board's loop is fast against the translational one (angle P 7 1/s vs k_x, k_v of 4 1/s^2, 3.2 1/s here).

Optionally (``drag_ff_1_s``, default 0: eq. (4) as published) a horizontal drag feed-forward (c / m) v_d adds the
force the trajectory's own speed costs against linear drag (SITL: c = 0.25 N s/m airframe + 0.02 * m g rotor drag);
it halves the oval's tracking error on the SITL.

Beyond eq. (4), as in the robust variant of [23] and in every flown implementation, an optional integral of the
composite error e_v + (k_x / k_v) e_x (``k_i``, clamped, conditional anti-windup; e_v alone in velocity-only mode)
absorbs a wrong mass or a steady push; it is zero at the equilibrium, so the hover behaviour is exactly eq. (4)'s.

Two entry points:

* :meth:`GeometricTracker.step` — the full tracker in local NED: :class:`TrackingState` (velocity, attitude,
  optional position) and :class:`TrajectoryTarget` (x_d optional, v_d, a_d, heading) -> :class:`GeometricCommand`.
* :meth:`GeometricTracker.update` — the same signature as :meth:`VelocityTracker.update` (velocity reference and
  estimate in H, yaw-rate reference, measured roll/pitch) plus an optional acceleration reference, returning the
  same :class:`AttitudeCommand`, so the autopilot can swap trackers by a parameter (``BRG_TRACKER``,
  :func:`make_tracker`). H is yaw-aligned, so the translational law is the same there; the heading is then the
  current one (b1d = x of H) and the yaw rate is the autopilot's (its heading hold), as with the PID tracker.

:func:`decode_trajectory_setpoint` maps a SET_POSITION_TARGET_LOCAL_NED with the velocity (and optionally
acceleration, position) bits, as PX4 accepts it, to a :class:`TrajectoryTarget`.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from firmware_bridge.velocity_tracker import AttitudeCommand, TrackerGains, VelocityTracker
from quadlink.errors import ProtocolError
from quadlink.frames import GRAVITY_M_S2, R_hq, Rz, wrap_pi
from quadlink.lie import so3_log
from quadlink.mavlink import mavlink
from quadlink.mavlink.param_service import ParamSpec
from quadlink.mavlink.setpoint_masks import (
    BODY_FRAMES,
    LOCAL_FRAMES,
    TM_POSITION,
    TM_YAW,
    TM_YAW_RATE,
    PartialTypeMask,
    mask_groups,
)

E3 = np.array([0.0, 0.0, 1.0])
Vec3 = NDArray[np.float64]
Mat3 = NDArray[np.float64]


@dataclass(frozen=True)
class GeometricGains:
    """Eq. (4)'s gains, per unit mass (the paper's k_x, k_v in N/m, N s/m are m times these)."""

    k_x_1_s2: float = 4.0  # m/s^2 per m of position error (used only when a position is given)
    k_v_1_s: float = 3.2  # m/s^2 per m/s of velocity error
    k_i_1_s2: float = 1.0  # m/s^2 per m of the integrated composite error (0: eq. (4) alone)
    integral_max_m_s2: float = 2.0  # clamp of the integral term, per axis
    integral_input_max_m_s: float = 0.3  # the integrated error is clipped to this per axis: a push or a large
    #   transient fills the integral at most k_i * 0.3 m/s^2 per second, so it cannot wind up into an overshoot
    drag_ff_1_s: float = 0.0  # horizontal drag feed-forward: (linear drag / m) * v_d (0: eq. (4) as published)
    k_yaw_1_s: float = 1.5  # heading error (rad) -> yaw rate (rad/s) added to Omega_c's z, world-frame mode
    omega_c_cutoff_hz: float = 5.0  # low-pass of the finite-differenced Omega_c
    max_omega_c_rad_s: float = 3.0  # clamp of Omega_c (a setpoint jump is not a rate)


@dataclass(frozen=True)
class TrackingState:
    """The estimated state (local NED; attitude R_ned_q body FRD -> NED, the measured one of eq. 4)."""

    v_ned_m_s: Vec3
    R_ned_q: Mat3
    p_ned_m: Vec3 | None = None  # None: velocity-only tracking (the companion closes the position loop)


@dataclass(frozen=True)
class TrajectoryTarget:
    """The desired flat output (local NED). ``yaw_rad`` gives b1d; else ``yaw_rate_rad_s`` turns it; else hold."""

    v_ned_m_s: Vec3
    a_ned_m_s2: Vec3 = field(default_factory=lambda: np.zeros(3))
    p_ned_m: Vec3 | None = None
    yaw_rad: float | None = None
    yaw_rate_rad_s: float | None = None

    def in_h(self, yaw_rad: float) -> tuple[Vec3, Vec3]:
        """Velocity and acceleration rotated into H (yaw-aligned) with the current yaw, for :meth:`update`."""
        R_hw = Rz(-yaw_rad)
        return R_hw @ np.asarray(self.v_ned_m_s, dtype=float), R_hw @ np.asarray(self.a_ned_m_s2, dtype=float)


@dataclass(frozen=True)
class GeometricCommand:
    """One step's output: the board's command and the geometric quantities behind it (diagnostics)."""

    attitude: AttitudeCommand  # roll/pitch from R_c, yaw rate, thrust fraction: what the board gets
    R_c: Mat3  # commanded attitude (body -> frame of the step: NED, or H in update())
    omega_c_q_rad_s: Vec3  # commanded body rates (finite differenced R_c, low-passed)
    f_des_n: Vec3  # desired force (eq. 4's bracket), same frame as R_c
    thrust_n: float  # tau of eq. (4) before the thrust-fraction clip
    e_x_m: Vec3 | None
    e_v_m_s: Vec3


def _cross(a: Vec3, b: Vec3) -> Vec3:
    """a x b for 3-vectors (numpy's general cross is ~10x slower on single vectors, and this runs at 100 Hz)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def attitude_from_force(f_des: ArrayLike, b1d: ArrayLike) -> Mat3:
    """R_c = [b1c b2c b3c]: b3c along -f_des (NED: the rotors push along -b3), b1c in the vertical plane of b1d.

    The heading enters as in the ZYX parametrisation the board's setpoint uses (R_c = Rz(psi_d) Ry(theta) Rx(phi)):
    with y_d = e3 x b1d (horizontal, right of the heading), b1c = y_d x b3c / |.|, b2c = b3c x b1c. Lee et al.
    project b1d on the plane normal to b3c instead; the two differ by a rotation about b3c of second order in the
    tilt, and the thrust direction (what eq. 4 needs) is the same.
    """
    f = np.asarray(f_des, dtype=float)
    norm = float(np.linalg.norm(f))
    b3c = E3.copy() if norm < 1e-9 else -f / norm
    h = np.asarray(b1d, dtype=float).copy()
    h[2] = 0.0
    if float(np.linalg.norm(h)) < 1e-9:
        h = np.array([1.0, 0.0, 0.0])
    y_d = _cross(E3, h / np.linalg.norm(h))
    b1c = _cross(y_d, b3c)
    n1 = float(np.linalg.norm(b1c))
    if n1 < 1e-6:  # thrust axis along y_d (a 90 deg roll): keep the heading's own direction
        b1c = _cross(_cross(b3c, h), b3c)
        n1 = float(np.linalg.norm(b1c))
    b1c /= n1
    b2c = _cross(b3c, b1c)
    return np.column_stack([b1c, b2c, b3c])


def board_angles(R_c: Mat3, yaw_rad: float) -> tuple[float, float]:
    """Roll and pitch (ZYX) that put the body z axis on R_c's at the vehicle's *current* heading ``yaw_rad``.

    The board applies its roll/pitch setpoint at its own yaw, so the thrust direction is realised exactly even
    while the heading still converges to R_c's (then these equal R_c's own ZYX roll and pitch).
    """
    b3_h = Rz(-yaw_rad) @ np.asarray(R_c, dtype=float)[:, 2]  # = Ry(pitch) Rx(roll) e3 = [s_th c_ph, -s_ph, c_th c_ph]
    roll = math.asin(min(max(-float(b3_h[1]), -1.0), 1.0))
    pitch = math.atan2(float(b3_h[0]), float(b3_h[2]))
    return roll, pitch


class TrackerLike(Protocol):
    """What the autopilot uses of a tracker (both trackers have it)."""

    gains: TrackerGains

    @property
    def hover_thrust_fraction(self) -> float: ...

    def set_gains(self, gains: TrackerGains) -> None: ...

    def reset(self) -> None: ...

    def update(self, dt_s: float, v_ref_h: np.ndarray, yaw_rate_ref_rad_s: float, v_est_h: np.ndarray,
               roll_rad: float, pitch_rad: float) -> AttitudeCommand: ...


class GeometricTracker:
    """Eq. (4) with R_c from (f_des, b1d), stepped at the command rate (100 Hz).

    ``limits`` are the PID tracker's :class:`TrackerGains` (tilt, speed, climb, yaw-rate and thrust limits; its
    PID gains are unused), so the autopilot's ``tracker.gains`` / ``set_gains`` work with either tracker.
    """

    def __init__(self, mass_kg: float, max_total_thrust_n: float, limits: TrackerGains | None = None,
                 gains: GeometricGains | None = None) -> None:
        if mass_kg <= 0 or max_total_thrust_n <= mass_kg * GRAVITY_M_S2:
            raise ValueError("the vehicle needs mass > 0 and max thrust above its weight")
        self.mass_kg = mass_kg
        self.max_total_thrust_n = max_total_thrust_n
        self.gains = limits or TrackerGains()
        self._limits = VelocityTracker(mass_kg, max_total_thrust_n, self.gains)  # its limit math, not its PID
        self.geometric = gains or GeometricGains()
        self._integral = np.zeros(3)
        self._R_c_prev: Mat3 | None = None
        self._omega_c = np.zeros(3)
        self._yaw_d: float | None = None
        self.last: GeometricCommand | None = None

    @property
    def hover_thrust_fraction(self) -> float:
        return self.mass_kg * GRAVITY_M_S2 / self.max_total_thrust_n

    @property
    def integral_m_s2(self) -> Vec3:
        return self._integral.copy()

    def set_gains(self, gains: TrackerGains) -> None:
        """The limits (the autopilot passes the PID tracker's parameter set)."""
        self.gains = gains
        self._limits.set_gains(gains)

    def set_geometric_gains(self, gains: GeometricGains) -> None:
        self.geometric = gains

    def reset(self) -> None:
        """Forget the integral, the Omega_c history and the heading (on the ground, on mode changes)."""
        self._integral = np.zeros(3)
        self._R_c_prev = None
        self._omega_c = np.zeros(3)
        self._yaw_d = None
        self.last = None

    # ------------------------------------------------------------------ the law
    def _limit_acceleration(self, a: Vec3) -> tuple[Vec3, bool]:
        """Keep the desired force inside the tilt cone and the thrust range: the PID tracker's limits, one
        implementation (|f_xy| / |f_z| <= tan(max tilt), no near free fall, thrust headroom upwards)."""
        return self._limits._limit_acceleration(a)

    def _core(self, dt_s: float, p_est: Vec3 | None, v_est: Vec3, R: Mat3, x_d: Vec3 | None, v_d: Vec3,
              a_d: Vec3, b1d: Vec3) -> tuple[GeometricCommand, bool]:
        k = self.geometric
        e_v = v_est - v_d  # eq. (6)
        e_x = None if (p_est is None or x_d is None) else p_est - x_d
        a_fb = -k.k_v_1_s * e_v + a_d + k.drag_ff_1_s * np.array([v_d[0], v_d[1], 0.0])
        if e_x is not None:
            a_fb = a_fb - k.k_x_1_s2 * e_x
        a_unsat = a_fb + self._integral
        a_cmd, saturated = self._limit_acceleration(a_unsat)
        # integral of the composite error e_v + (k_x / k_v) e_x (robust variant of [23]): at rest it integrates the
        # position error, in velocity-only mode the velocity error (the companion's e_x is inside v_ref then);
        # conditional integration: not further into a saturation
        composite = e_v if e_x is None or k.k_v_1_s <= 0.0 else e_v + (k.k_x_1_s2 / k.k_v_1_s) * e_x
        composite = np.clip(composite, -k.integral_input_max_m_s, k.integral_input_max_m_s)  # a push is not a bias
        step = -k.k_i_1_s2 * composite * dt_s
        excess = a_unsat - a_cmd
        winding_up = (np.abs(excess) > 1e-9) & (np.sign(step) == np.sign(excess))
        self._integral = np.clip(self._integral + np.where(winding_up, 0.0, step),
                                 -k.integral_max_m_s2, k.integral_max_m_s2)

        f_des = self.mass_kg * (a_cmd - GRAVITY_M_S2 * E3)  # eq. (4)'s bracket: -k_x e_x - k_v e_v - m g e3 + m a_d
        thrust_n = float(-f_des @ (R @ E3))  # eq. (4): projected on the measured body z
        R_c = attitude_from_force(f_des, b1d)

        if self._R_c_prev is not None:  # hat(Omega_c) = R_c^T dR_c/dt, over one step
            raw = so3_log(self._R_c_prev.T @ R_c) / dt_s
            raw = np.clip(raw, -k.max_omega_c_rad_s, k.max_omega_c_rad_s)
            alpha = dt_s / (dt_s + 1.0 / (2.0 * math.pi * k.omega_c_cutoff_hz))
            self._omega_c = self._omega_c + alpha * (raw - self._omega_c)
        self._R_c_prev = R_c

        fraction = thrust_n / self.max_total_thrust_n
        clipped = min(max(fraction, self.gains.thrust_min_fraction), self.gains.thrust_max_fraction)
        saturated = saturated or clipped != fraction
        roll_c, pitch_c = board_angles(R_c, math.atan2(R[1, 0], R[0, 0]))
        cmd = AttitudeCommand(roll_rad=roll_c, pitch_rad=pitch_c, yaw_rate_rad_s=0.0, thrust_fraction=clipped,
                              a_des_h_m_s2=(float(a_cmd[0]), float(a_cmd[1]), float(a_cmd[2])), saturated=saturated)
        return GeometricCommand(cmd, R_c, self._omega_c.copy(), f_des, thrust_n, e_x, e_v), saturated

    def _yaw_rate_limit(self, yaw_rate_rad_s: float) -> float:
        m = self.gains.max_yaw_rate_rad_s
        return min(max(float(yaw_rate_rad_s), -m), m)

    def step(self, dt_s: float, target: TrajectoryTarget, state: TrackingState) -> GeometricCommand:
        """One step in local NED: the full tracker (position error when both positions are given)."""
        dt_s = min(max(float(dt_s), 1e-4), 0.1)
        R = np.asarray(state.R_ned_q, dtype=float)
        v_est = np.asarray(state.v_ned_m_s, dtype=float)
        if not np.all(np.isfinite(v_est)):
            v_est = np.zeros(3)
        yaw = math.atan2(R[1, 0], R[0, 0])
        if target.yaw_rad is not None:
            self._yaw_d = wrap_pi(target.yaw_rad)
            yaw_rate_ff = 0.0
        else:
            yaw_rate_ff = 0.0 if target.yaw_rate_rad_s is None else self._yaw_rate_limit(target.yaw_rate_rad_s)
            self._yaw_d = wrap_pi((yaw if self._yaw_d is None else self._yaw_d) + yaw_rate_ff * dt_s)
        b1d = np.array([math.cos(self._yaw_d), math.sin(self._yaw_d), 0.0])
        p_est = None if state.p_ned_m is None else np.asarray(state.p_ned_m, dtype=float)
        x_d = None if target.p_ned_m is None else np.asarray(target.p_ned_m, dtype=float)
        out, _ = self._core(dt_s, p_est, v_est, R, x_d, np.asarray(target.v_ned_m_s, dtype=float),
                            np.asarray(target.a_ned_m_s2, dtype=float), b1d)
        # the board tracks a body yaw rate: Omega_c's z (the heading's own motion) + a P term on the heading error
        yaw_c = math.atan2(out.R_c[1, 0], out.R_c[0, 0])
        yaw_rate = self._yaw_rate_limit(out.omega_c_q_rad_s[2] + self.geometric.k_yaw_1_s * wrap_pi(yaw_c - yaw))
        cmd = out.attitude
        out = GeometricCommand(AttitudeCommand(cmd.roll_rad, cmd.pitch_rad, yaw_rate, cmd.thrust_fraction,
                                               cmd.a_des_h_m_s2, cmd.saturated),
                               out.R_c, out.omega_c_q_rad_s, out.f_des_n, out.thrust_n, out.e_x_m, out.e_v_m_s)
        self.last = out
        return out

    def update(self, dt_s: float, v_ref_h: np.ndarray, yaw_rate_ref_rad_s: float, v_est_h: np.ndarray,
               roll_rad: float, pitch_rad: float, a_ref_h: np.ndarray | None = None) -> AttitudeCommand:
        """Drop-in for :meth:`VelocityTracker.update`: velocity-only eq. (4) in H with acceleration feed-forward.

        The reference is clamped like the PID tracker's (speed, climb, descent, yaw rate); the heading is the
        current one (b1d = x of H) and the yaw rate passes through (the autopilot's heading hold adds to it).
        """
        dt_s = min(max(float(dt_s), 1e-4), 0.1)
        v_ref, yaw_rate = self._limits.clamp_reference(v_ref_h, yaw_rate_ref_rad_s)
        v_est = np.asarray(v_est_h, dtype=float)
        if not np.all(np.isfinite(v_est)):
            v_est = np.zeros(3)
        a_d = np.zeros(3) if a_ref_h is None else np.asarray(a_ref_h, dtype=float)
        if not np.all(np.isfinite(a_d)):
            a_d = np.zeros(3)
        out, _ = self._core(dt_s, None, v_est, R_hq(roll_rad, pitch_rad), None, v_ref, a_d,
                            np.array([1.0, 0.0, 0.0]))
        cmd = out.attitude
        cmd = AttitudeCommand(cmd.roll_rad, cmd.pitch_rad, yaw_rate, cmd.thrust_fraction, cmd.a_des_h_m_s2,
                              cmd.saturated)
        self.last = GeometricCommand(cmd, out.R_c, out.omega_c_q_rad_s, out.f_des_n, out.thrust_n, None,
                                     out.e_v_m_s)
        return cmd


# ---------------------------------------------------------------------- selection by parameter
class TrackerKind(enum.IntEnum):
    """``BRG_TRACKER``: which tracker flies velocity (and acceleration) setpoints."""

    PID_VELOCITY = 0
    GEOMETRIC = 1


#: Parameters to append to ``firmware_bridge.params.PARAM_SPECS`` to select and tune the geometric tracker.
GEOMETRIC_PARAM_SPECS: tuple[ParamSpec, ...] = (
    # REAL32 like every bridge parameter (PX4's and ArduPilot's encodings agree on it): 0.0 or 1.0
    ParamSpec("BRG_TRACKER", 0.0, 0.0, 1.0, "enum", "velocity tracker: 0 PID (paper 000), 1 geometric (paper 003)"),
    ParamSpec("BRG_GEO_KX", 4.0, 0.0, 20.0, "(m/s^2)/m", "geometric tracker: position gain k_x/m"),
    ParamSpec("BRG_GEO_KV", 3.2, 0.0, 20.0, "(m/s^2)/(m/s)", "geometric tracker: velocity gain k_v/m"),
    ParamSpec("BRG_GEO_KI", 1.0, 0.0, 10.0, "(m/s^2)/m", "geometric tracker: composite-error integral gain"),
    ParamSpec("BRG_GEO_I_MAX", 2.0, 0.0, 10.0, "m/s^2", "geometric tracker: integral clamp"),
    ParamSpec("BRG_GEO_DRAG", 0.0, 0.0, 5.0, "1/s", "geometric tracker: horizontal drag feed-forward (drag/m) on v_d"),
)
assert all(len(p.name) <= 16 for p in GEOMETRIC_PARAM_SPECS)


def geometric_gains_from_params(values: Mapping[str, float]) -> GeometricGains:
    """The gains from parameter values (``ParamTable.values`` or any name -> value mapping; defaults if absent)."""
    d = {p.name: p.default for p in GEOMETRIC_PARAM_SPECS}
    d.update({k: float(v) for k, v in values.items() if k in d})
    return GeometricGains(k_x_1_s2=d["BRG_GEO_KX"], k_v_1_s=d["BRG_GEO_KV"], k_i_1_s2=d["BRG_GEO_KI"],
                          integral_max_m_s2=d["BRG_GEO_I_MAX"], drag_ff_1_s=d["BRG_GEO_DRAG"])


def make_tracker(kind: int | TrackerKind, mass_kg: float, max_total_thrust_n: float, limits: TrackerGains,
                 geometric: GeometricGains | None = None) -> VelocityTracker | GeometricTracker:
    """The tracker ``BRG_TRACKER`` selects; both have ``update(dt, v_ref_h, yaw_rate, v_est_h, roll, pitch)``."""
    try:
        k = TrackerKind(int(kind))
    except ValueError as exc:
        raise ValueError(f"BRG_TRACKER {kind}: 0 (PID velocity) or 1 (geometric)") from exc
    if k == TrackerKind.GEOMETRIC:
        return GeometricTracker(mass_kg, max_total_thrust_n, limits, geometric)
    return VelocityTracker(mass_kg, max_total_thrust_n, limits)


# ---------------------------------------------------------------------- SET_POSITION_TARGET_LOCAL_NED
# type_mask bits (MAVLink POSITION_TARGET_TYPEMASK, from the dialect): a set bit means "ignore this field"
#: the masks a trajectory streamer sends (position + velocity + acceleration, with yaw or with yaw rate)
TM_PVA_YAW = TM_YAW_RATE
TM_VA_YAW = TM_POSITION | TM_YAW_RATE


class SetpointRejected(ProtocolError):
    """A SET_POSITION_TARGET_LOCAL_NED the tracker cannot fly (mask, frame or values)."""


class PositionTargetLike(Protocol):
    """The fields of a decoded SET_POSITION_TARGET_LOCAL_NED (pymavlink's message has them)."""

    type_mask: int
    coordinate_frame: int
    x: float
    y: float
    z: float
    vx: float
    vy: float
    vz: float
    afx: float
    afy: float
    afz: float
    yaw: float
    yaw_rate: float


def decode_trajectory_setpoint(msg: PositionTargetLike, yaw_rad: float) -> TrajectoryTarget:
    """SET_POSITION_TARGET_LOCAL_NED with velocity (+ acceleration, + position) bits -> a local-NED target.

    As PX4 takes it: velocity required here (the bridge flies velocity); acceleration (``afx..afz``, force bit clear)
    is the feed-forward a_d; a position (MAV_FRAME_LOCAL_NED only: the odometry's frame) adds e_x. Body frames
    (BODY_NED, BODY_OFFSET_NED, BODY_FRD) carry velocity and acceleration in the yaw-aligned body frame H, rotated
    into NED with the current yaw (``yaw_rad``), as PX4's receiver and ArduCopter do. ``yaw`` gives b1d; ``yaw_rate``
    (when its bit is clear) turns it instead. Raises :class:`SetpointRejected`.
    """
    tm = int(msg.type_mask)
    frame = int(msg.coordinate_frame)
    if frame not in BODY_FRAMES + LOCAL_FRAMES:
        raise SetpointRejected(f"frame {frame}: local NED/FRD or body NED/FRD only")
    try:
        groups = mask_groups(tm)
    except PartialTypeMask as exc:   # PX4 does not fly a partial group either
        raise SetpointRejected(str(exc)) from exc
    if groups.force:
        raise SetpointRejected(f"type_mask {tm}: force setpoints are not supported")
    if not groups.velocity:
        raise SetpointRejected(f"type_mask {tm}: the tracker needs a velocity")
    has_accel, has_pos = groups.acceleration, groups.position
    if has_pos and frame != mavlink.MAV_FRAME_LOCAL_NED:
        raise SetpointRejected(f"frame {frame}: positions only in MAV_FRAME_LOCAL_NED")
    v = np.array([msg.vx, msg.vy, msg.vz], dtype=float)
    a = np.array([msg.afx, msg.afy, msg.afz], dtype=float) if has_accel else np.zeros(3)
    p = np.array([msg.x, msg.y, msg.z], dtype=float) if has_pos else None
    if not (np.all(np.isfinite(v)) and np.all(np.isfinite(a)) and (p is None or np.all(np.isfinite(p)))):
        raise SetpointRejected("non-finite position, velocity or acceleration")
    if frame in BODY_FRAMES:
        R_wh = Rz(yaw_rad)
        v, a = R_wh @ v, R_wh @ a
    yaw_rate = None if tm & TM_YAW_RATE else float(msg.yaw_rate)
    yaw = None if (tm & TM_YAW or yaw_rate is not None) else float(msg.yaw)
    if yaw_rate is not None and not math.isfinite(yaw_rate):
        yaw_rate = 0.0
    if yaw is not None and not math.isfinite(yaw):
        yaw = None
    return TrajectoryTarget(v_ned_m_s=v, a_ned_m_s2=a, p_ned_m=p, yaw_rad=yaw, yaw_rate_rad_s=yaw_rate)

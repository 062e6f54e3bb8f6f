"""The motion arbiter: every source of motion becomes one command for the reference pipeline (issue 14).

Pure: no clock, no I/O; time is an argument (the daemon passes its monotonic wall clock: link loss is a
wall-time phenomenon). The daemon feeds it what arrives on the ground-station endpoint and asks it, at
camera rate, for the :class:`MotionCommand` that :func:`companion.reference.reference_velocity` turns into
the reference (eq. 7 repulsion, the safe-distance projection, the closing-speed law, the stale/unknown
sector rules, the vertical limits and the speed limits apply to every source alike). Nothing a ground
station sends moves the vehicle any other way: scripted setpoints are not routed to the autopilot.

Sources
  * **Operator** — MANUAL_CONTROL (the haptic client, QGroundControl's virtual joystick): the handle
    position of eqs. (2)-(3) (x forward along alpha, y yaw rate, z climb with 500 = none).
  * **Script** — SET_POSITION_TARGET_LOCAL_NED as MAVSDK's offboard plugin and pymavlink scripts send it:
    velocity (type_mask 0x5C7 = 1479, MAV_FRAME_BODY_NED, with yaw rate: ``set_velocity_body``; 0x9C7 =
    2503, MAV_FRAME_LOCAL_NED, with absolute yaw: ``set_velocity_ned``), also BODY_OFFSET_NED, BODY_FRD
    and LOCAL_OFFSET_NED. Body frames are yaw-aligned (H), as PX4 and ArduCopter read them; with the
    pan-scan on, a body-frame velocity is taken relative to the centre of the yaw oscillation (the
    alpha of eq. 6 does the same for the operator), so a script flying "forward" flies straight.
    Local frames are the odometry's local NED (the LOCAL_POSITION_NED the companion publishes).
    **Position targets** (0xDF8 = 3576 position + yaw, 2552 with yaw ignored, and position + velocity)
    become a bounded velocity toward the target, ``v = clamp(k_p (p_target - p) + v_ff, v_max)``, under the
    same constraints (offset frames are resolved against the position at receipt, as ArduPilot does).
    **Trajectory setpoints** (issue 19; PX4 style, local frames: position + velocity + acceleration, 2048 with
    yaw, 1024 with yaw rate; or velocity + acceleration): the companion closes the position loop on its
    odometry, ``v_ref = v_d - k_p e_x`` (:func:`companion.trajectory_follow.position_loop`), and carries a_d as
    the acceleration feed-forward (:attr:`MotionCommand.a_ff_h_m_s2`), which the daemon sends only when the
    safety layer left the velocity untouched. Force setpoints, an acceleration without a velocity, body-frame
    accelerations and partial masks are refused (:class:`Refusal`: STATUSTEXT).
    An absolute yaw becomes a yaw rate ``k_yaw wrap(yaw_target - yaw)`` (bounded).

Priority and liveness
  * The operator overrides a script while the handle is out of the dead-band (any axis).
  * A script is followed while *offboard is engaged*: by DO_SET_MODE OFFBOARD (MAVSDK's
    ``offboard.start()``), or — for scripts that never switch modes — by its first setpoint. DO_SET_MODE
    to any other mode (MAVSDK's ``offboard.stop()`` asks for HOLD) disengages it.
  * A source silent for its timeout is dropped. A script silent for ``script_timeout_s`` (PX4's
    COM_OF_LOSS_T semantics, default 1 s) disengages offboard (PX4 leaves OFFBOARD on loss) and the
    vehicle holds; it re-engages with DO_SET_MODE OFFBOARD (or, for a script that never switched modes,
    with its next setpoint). No live source at all -> HOLD (zero command; repulsion still acts).
  * The ground-station link is alive while it sends anything that shows a live peer: HEARTBEAT,
    MANUAL_CONTROL, setpoints (``link_timeout_s``, longer than the 1 Hz heartbeat period).
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from companion.operator_input import OperatorInput, operator_from_manual_control
from companion.trajectory_follow import FollowGains, position_loop
from quadlink.frames import Rz, wrap_pi
from quadlink.mavlink import mavlink
from quadlink.mavlink.setpoint_masks import (
    BODY_FRAMES,
    TM_FORCE,
    TM_YAW,
    TM_YAW_RATE,
    PartialTypeMask,
    mask_groups,
)
from quadlink.trajectory import TrajectorySample

LOCAL_FRAMES = (mavlink.MAV_FRAME_LOCAL_NED, mavlink.MAV_FRAME_LOCAL_OFFSET_NED)
OFFSET_FRAMES = (mavlink.MAV_FRAME_LOCAL_OFFSET_NED, mavlink.MAV_FRAME_BODY_OFFSET_NED, mavlink.MAV_FRAME_BODY_FRD)


class Source(enum.IntEnum):
    NONE = 0
    OPERATOR = 1
    SCRIPT = 2


@dataclass(frozen=True)
class ArbiterParams:
    """Timeouts (s), the operator's dead-band, and the script's limits and gains."""

    operator_timeout_s: float = 0.5      # MANUAL_CONTROL silent this long: the operator is gone
    script_timeout_s: float = 1.0        # PX4 COM_OF_LOSS_T: offboard setpoints silent this long -> hold
    link_timeout_s: float = 3.0          # nothing from the ground station this long: link lost
    deadband: float = 0.03               # operator handle dead-band (normalised), as the reference's
    script_max_speed_m_s: float = 1.0    # scripted velocities are clamped to this (then the reference's limits)
    script_max_yaw_rate_rad_s: float = 1.0
    yaw_gain_per_s: float = 1.5          # absolute yaw target -> yaw rate
    position_gain_per_s: float = 1.0     # position target -> velocity
    position_max_speed_m_s: float = 0.5
    trajectory_gain_per_s: float = 1.25  # trajectory (p, v, a) setpoint: k_p of v_ref = v_d - k_p e_x (issue 19)
    trajectory_max_correction_m_s: float = 1.0   # |k_p e_x| clamped to this (a far x_d is not a sprint)
    trajectory_max_accel_m_s2: float = 3.0       # |a_d| feed-forward clamped to this


@dataclass(frozen=True)
class Setpoint:
    """One SET_POSITION_TARGET_LOCAL_NED's content (SI, the message's frame)."""

    frame: int
    type_mask: int
    position_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    velocity_m_s: tuple[float, float, float] = (0.0, 0.0, 0.0)
    yaw_rad: float = 0.0
    yaw_rate_rad_s: float = 0.0
    acceleration_m_s2: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class Pose:
    """What the arbiter needs of the vehicle's state: odometry position (local NED), yaw (NED, rad), and
    the pan-scan's current yaw offset (eq. 5) so that body-frame commands are relative to its centre."""

    position_ned_m: tuple[float, float, float] | None
    yaw_rad: float | None
    scan_yaw_offset_rad: float = 0.0


@dataclass(frozen=True)
class ScriptTarget:
    """A script's accepted setpoint, resolved: velocity in a frame, or a position in local NED."""

    body_velocity_m_s: tuple[float, float, float] | None    # yaw-aligned body (H, centre of the pan-scan)
    local_velocity_m_s: tuple[float, float, float] | None   # odometry local NED
    position_ned_m: tuple[float, float, float] | None       # absolute target, odometry local NED
    yaw_rad: float | None
    yaw_rate_rad_s: float | None
    accel_ned_m_s2: tuple[float, float, float] | None = None   # trajectory feed-forward a_d, local NED


@dataclass(frozen=True)
class Refusal:
    """A setpoint the arbiter does not follow, with the reason for the STATUSTEXT."""

    text: str


@dataclass(frozen=True)
class MotionCommand:
    """The arbiter's decision for the reference pipeline.

    ``source`` OPERATOR: ``operator`` is the handle (eqs. 2-3). SCRIPT: ``v_h_m_s`` (H, NED, m/s) and
    ``yaw_rate_rad_s`` replace eqs. (2)-(3); ``a_ff_h_m_s2`` (H, m/s^2) is a trajectory's acceleration
    feed-forward (None for plain velocity/position scripts). NONE: hold (zero command). ``hold`` is True when
    no live source commands motion (the ground station may still be connected)."""

    source: Source
    operator: OperatorInput | None = None
    v_h_m_s: NDArray[np.float64] | None = None
    yaw_rate_rad_s: float = 0.0
    hold: bool = True
    reason: str = ""
    a_ff_h_m_s2: NDArray[np.float64] | None = None


def _finite(*values: float) -> bool:
    return all(math.isfinite(v) for v in values)


def parse_setpoint(sp: Setpoint, pose: Pose) -> ScriptTarget | Refusal:
    """Validate a setpoint and resolve it (offset positions against ``pose``); a :class:`Refusal` if it is
    not one the companion follows."""
    tm = sp.type_mask
    if sp.frame not in BODY_FRAMES + LOCAL_FRAMES:
        return Refusal(f"setpoint frame {sp.frame} not supported (local or body NED)")
    if tm & TM_FORCE:
        return Refusal("force setpoints not supported (velocity, position or a trajectory)")
    try:
        groups = mask_groups(tm)
    except PartialTypeMask:
        return Refusal(f"partial setpoint (type_mask {tm}): give all of x, y, z or none, likewise v and a")
    pos_given, vel_given, acc_given = groups.position, groups.velocity, groups.acceleration
    if acc_given and (not vel_given or sp.frame not in LOCAL_FRAMES):
        return Refusal("acceleration setpoints only as a trajectory: with velocity, in a local frame")
    if acc_given and not _finite(*sp.acceleration_m_s2):
        return Refusal("setpoint with NaN or infinite values")
    if not pos_given and not vel_given:
        if tm & TM_YAW and tm & TM_YAW_RATE:
            return Refusal(f"empty setpoint (type_mask {tm})")
    if (pos_given and not _finite(*sp.position_m)) or (vel_given and not _finite(*sp.velocity_m_s)):
        return Refusal("setpoint with NaN or infinite values")
    yaw_rate = None if tm & TM_YAW_RATE or not math.isfinite(sp.yaw_rate_rad_s) else float(sp.yaw_rate_rad_s)
    yaw = None if tm & TM_YAW or yaw_rate is not None or not math.isfinite(sp.yaw_rad) else float(sp.yaw_rad)
    body = sp.frame in BODY_FRAMES
    velocity = tuple(float(v) for v in sp.velocity_m_s) if vel_given else (0.0, 0.0, 0.0)
    position = None
    if pos_given:
        if pose.position_ned_m is None or pose.yaw_rad is None:
            return Refusal("position setpoint refused: no position estimate")
        target = np.asarray(sp.position_m, dtype=float)
        if body:                                   # yaw-aligned offset from the vehicle
            c, s = math.cos(pose.yaw_rad), math.sin(pose.yaw_rad)
            target = np.asarray(pose.position_ned_m) + np.array([c * target[0] - s * target[1],
                                                                 s * target[0] + c * target[1], target[2]])
        elif sp.frame == mavlink.MAV_FRAME_LOCAL_OFFSET_NED:
            target = np.asarray(pose.position_ned_m) + target
        position = (float(target[0]), float(target[1]), float(target[2]))
        if body and vel_given:   # feed-forward velocity of a body position target: rotate into local NED
            c, s = math.cos(pose.yaw_rad), math.sin(pose.yaw_rad)
            velocity = (c * velocity[0] - s * velocity[1], s * velocity[0] + c * velocity[1], velocity[2])
            body = False
    accel = tuple(float(a) for a in sp.acceleration_m_s2) if acc_given else None
    if position is not None:
        return ScriptTarget(None, velocity, position, yaw, yaw_rate, accel)  # type: ignore[arg-type]
    if body:
        return ScriptTarget(velocity, None, None, yaw, yaw_rate)  # type: ignore[arg-type]
    return ScriptTarget(None, velocity, None, yaw, yaw_rate, accel)  # type: ignore[arg-type]


def script_velocity_h(target: ScriptTarget, pose: Pose, params: ArbiterParams) -> tuple[NDArray[np.float64], float]:
    """A script target as a velocity in H (NED, m/s) and a yaw rate (rad/s, NED), clamped to the script
    limits. Needs the yaw for local frames and the position for position targets (zero otherwise)."""
    v_h, yaw_rate, _ = script_command_h(target, pose, params)
    return v_h, yaw_rate


def _trajectory_velocity_ned(target: ScriptTarget, pose: Pose, params: ArbiterParams) -> NDArray[np.float64]:
    """A trajectory setpoint's velocity reference in local NED: v_d - k_p e_x with a position and an estimate
    (:func:`companion.trajectory_follow.position_loop`, the correction clamped), else v_d."""
    v_d = np.asarray(target.local_velocity_m_s or (0.0, 0.0, 0.0), dtype=float)
    if target.position_ned_m is None or pose.position_ned_m is None:
        return v_d
    assert target.accel_ned_m_s2 is not None
    sample = TrajectorySample(0.0, np.asarray(target.position_ned_m, dtype=float), v_d,
                              np.asarray(target.accel_ned_m_s2, dtype=float), np.zeros(3))
    gains = FollowGains(params.trajectory_gain_per_s, params.trajectory_max_correction_m_s)
    return position_loop(sample, pose.position_ned_m, gains).v_ref_ned_m_s


def script_command_h(target: ScriptTarget, pose: Pose, params: ArbiterParams
                     ) -> tuple[NDArray[np.float64], float, NDArray[np.float64] | None]:
    """:func:`script_velocity_h` plus a trajectory's acceleration feed-forward in H (m/s^2; None for other
    scripts, and when the yaw is unknown)."""
    v_h = np.zeros(3)
    a_h: NDArray[np.float64] | None = None
    if target.accel_ned_m_s2 is not None:
        if pose.yaw_rad is not None:
            R_hw = Rz(-pose.yaw_rad)   # local NED -> H
            v_h = R_hw @ _trajectory_velocity_ned(target, pose, params)
            a_h = R_hw @ np.asarray(target.accel_ned_m_s2, dtype=float)
            n = float(np.linalg.norm(a_h))
            if n > params.trajectory_max_accel_m_s2:
                a_h *= params.trajectory_max_accel_m_s2 / n
    elif target.body_velocity_m_s is not None:
        # relative to the centre of the pan-scan's swing: H is rotated by the offset psi_bar_s (eq. 5)
        c, s = math.cos(pose.scan_yaw_offset_rad), math.sin(pose.scan_yaw_offset_rad)
        b = target.body_velocity_m_s
        v_h = np.array([c * b[0] + s * b[1], -s * b[0] + c * b[1], b[2]])
    elif pose.yaw_rad is not None:
        v_ned = np.zeros(3) if target.local_velocity_m_s is None else np.asarray(target.local_velocity_m_s, dtype=float)
        if target.position_ned_m is not None and pose.position_ned_m is not None:
            err = np.asarray(target.position_ned_m) - np.asarray(pose.position_ned_m)
            v_p = params.position_gain_per_s * err
            n = float(np.linalg.norm(v_p))
            if n > params.position_max_speed_m_s:
                v_p *= params.position_max_speed_m_s / n
            v_ned = v_ned + v_p
        c, s = math.cos(pose.yaw_rad), math.sin(pose.yaw_rad)
        v_h = np.array([c * v_ned[0] + s * v_ned[1], -s * v_ned[0] + c * v_ned[1], v_ned[2]])   # Rz(yaw)^T
    speed = float(np.linalg.norm(v_h))
    if speed > params.script_max_speed_m_s:
        v_h *= params.script_max_speed_m_s / speed
    if target.yaw_rate_rad_s is not None:
        yaw_rate = target.yaw_rate_rad_s
    elif target.yaw_rad is not None and pose.yaw_rad is not None:
        yaw_rate = params.yaw_gain_per_s * wrap_pi(target.yaw_rad - pose.yaw_rad)
    else:
        yaw_rate = 0.0
    lim = params.script_max_yaw_rate_rad_s
    return v_h, min(max(yaw_rate, -lim), lim), a_h


class Arbiter:
    """The sources' latest inputs and the offboard engagement; all times are arguments."""

    def __init__(self, params: ArbiterParams) -> None:
        self.params = params
        self._operator: OperatorInput = OperatorInput()
        self._operator_s: float | None = None
        self._script: ScriptTarget | None = None
        self._script_s: float | None = None
        self._link_s: float | None = None
        self.offboard_engaged = False
        self._mode_switched = False   # the script's tool switches modes (MAVSDK): re-engage only by mode
        self._hold_asked = False      # the ground station switched to a hold mode: its silence is deliberate
        self.events: list[str] = []   # transitions since the last :meth:`take_events` (for STATUSTEXT)

    # --- inputs
    def on_manual_control(self, now_s: float, x: int, y: int, z: int) -> None:
        self._operator = operator_from_manual_control(x, y, z, self.params.deadband)
        self._operator_s = now_s
        self._link_s = now_s
        self._hold_asked = False

    def on_heartbeat(self, now_s: float) -> None:
        self._link_s = now_s

    def on_setpoint(self, now_s: float, sp: Setpoint, pose: Pose) -> Refusal | None:
        self._link_s = now_s
        parsed = parse_setpoint(sp, pose)
        if isinstance(parsed, Refusal):
            return parsed
        self._script, self._script_s = parsed, now_s
        self._hold_asked = False
        if not self.offboard_engaged and not self._mode_switched:
            self.offboard_engaged = True
            self.events.append("offboard engaged by the setpoint stream")
        return None

    def on_set_mode(self, now_s: float, offboard: bool) -> bool:
        """DO_SET_MODE / SET_MODE from the ground station: OFFBOARD engages the script (accepted only with a
        fresh setpoint stream, as PX4 requires), anything else disengages it. Accepted?"""
        self._link_s = now_s
        self._mode_switched = True
        if offboard:
            if not self._script_fresh(now_s):
                self.events.append("offboard refused: no setpoint stream")
                return False
            if not self.offboard_engaged:
                self.events.append("offboard engaged")
            self.offboard_engaged = True
            return True
        if self.offboard_engaged:
            self.events.append("offboard stopped: hold")
        self.offboard_engaged = False
        self._hold_asked = True
        return True

    def take_events(self) -> list[str]:
        ev, self.events = self.events, []
        return ev

    # --- state
    def _script_fresh(self, now_s: float) -> bool:
        return self._script_s is not None and 0.0 <= now_s - self._script_s <= self.params.script_timeout_s

    @property
    def last_command_s(self) -> float | None:
        """When the newest accepted motion command (operator or script setpoint) arrived; None: never, or the
        ground station has since switched to a hold mode (MAVSDK's ``offboard.stop()``: its silence is meant)."""
        if self._hold_asked:
            return None
        stamps = [t for t in (self._operator_s, self._script_s) if t is not None]
        return max(stamps) if stamps else None

    def operator_alive(self, now_s: float) -> bool:
        return self._operator_s is not None and 0.0 <= now_s - self._operator_s <= self.params.operator_timeout_s

    def link_alive(self, now_s: float) -> bool:
        return self._link_s is not None and 0.0 <= now_s - self._link_s <= self.params.link_timeout_s

    def operator_active(self, now_s: float) -> bool:
        """The operator's handle is out of the dead-band (on a live stream): it overrides a script."""
        op = self._operator
        return self.operator_alive(now_s) and (op.qx != 0.0 or op.qy != 0.0 or op.qz != 0.0)

    def command(self, now_s: float, pose: Pose) -> MotionCommand:
        """The command now (call at camera rate; it also notices a lost script)."""
        if self.offboard_engaged and self._script_s is not None and not self._script_fresh(now_s):
            self.offboard_engaged = False
            self.events.append(f"offboard setpoints lost for {self.params.script_timeout_s:g} s: hold")
        script = self.offboard_engaged and self._script_fresh(now_s) and self._script is not None
        if self.operator_active(now_s) or (self.operator_alive(now_s) and not script):
            return MotionCommand(Source.OPERATOR, operator=self._operator, hold=False,
                                 reason="operator" + (" overrides the script" if script else ""))
        if script:
            assert self._script is not None
            v_h, yaw_rate, a_h = script_command_h(self._script, pose, self.params)
            return MotionCommand(Source.SCRIPT, v_h_m_s=v_h, yaw_rate_rad_s=yaw_rate, hold=False,
                                 reason="trajectory" if a_h is not None else "script", a_ff_h_m_s2=a_h)
        return MotionCommand(Source.NONE, hold=True, reason="no live source")

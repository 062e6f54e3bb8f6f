"""The bridge's one state machine: its state and the few helpers every service shares.

:class:`BridgeState` holds everything the autopilot knows (board, IMU, odometry, setpoints, mode, arming,
take-off, counters). The services are objects that each hold this one state (and the services they use), one
module each, none with sockets, threads or a wall clock (time is always ``now_s``):
:mod:`~firmware_bridge.commander` (arming, commands, mode requests, failsafes),
:mod:`~firmware_bridge.flight_control` (the 100 Hz closed loop, blind take-off, heading hold),
:mod:`~firmware_bridge.offboard` (setpoints and odometry -> H), :mod:`~firmware_bridge.telemetry`
(heartbeat, SYS_STATUS, streams), :mod:`~firmware_bridge.connect` (what ground stations ask on connect);
:class:`firmware_bridge.autopilot.Autopilot` builds them with the shared parameter service.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from firmware_bridge.attitude_filter import BridgeAttitude
from firmware_bridge.drag_velocity import DragVelocity
from firmware_bridge.geometric_tracker import GeometricTracker, TrackerKind, make_tracker
from firmware_bridge.modes import FlightMode, TakeoffPhase
from firmware_bridge.params import ParamTable
from firmware_bridge.streams import StreamScheduler
from firmware_bridge.velocity_tracker import AttitudeCommand, VelocityTracker
from firmware_bridge.vertical_estimator import VerticalEstimator
from quadlink.frames import GRAVITY_M_S2
from quadlink.mavlink import mavlink
from quadlink.mavlink.statustext import ChunkIds, statustext_messages
from quadlink.vehicle import VehicleConfig

log = logging.getLogger("firmware_bridge.autopilot")

MALFORMED_LOG_INTERVAL_S = 5.0  # bad input is counted always, logged at most this often


class BoardStatusLike(Protocol):
    """What the autopilot reads of ``quadlink.mk.messages.BoardStatus`` (kept free of the MK codec)."""

    @property
    def armed(self) -> bool: ...
    @property
    def flight_state(self) -> int: ...
    @property
    def failsafe(self) -> bool: ...
    @property
    def battery_mv(self) -> int: ...
    @property
    def error_flags(self) -> int: ...
    @property
    def imu_sample_count(self) -> int: ...


class NonFiniteCommand(ValueError):
    """A board command with a NaN or infinite field: a bug upstream, never sent to the board."""


@dataclass
class BlindDescent:
    """A landing flown as the blind descent (without odometry, or the level last part of any landing), from its
    start (``FlightControlService._blind_step``)."""
    start_s: float
    height0_m: float                # the estimated height then
    thrust_lp: float                # the descent's thrust, low-passed (DESCENT_THRUST_TAU_S) until the floor read,
                                    # then the thrust the hold holds
    floor_s: float | None = None    # when the baro-fused estimate first read the floor
    floor_still: bool = False       # since then, the board's baro climb rate has said the descent stopped
    seen_descending: bool = False   # the board's baro climb rate has read a descent under way (since the floor read)


@dataclass(frozen=True)
class BoardCommand:
    """What the board gets at 100 Hz (the daemon packs it into an MK ``AttitudeSetpoint``).

    Every field is finite: the constructor refuses NaN/inf (issue 16: no NaN ever reaches the board).
    """

    roll_rad: float
    pitch_rad: float
    yaw_rate_rad_s: float
    thrust: float  # fraction 0..1 of the max total thrust
    armed: bool

    def __post_init__(self) -> None:
        if not (math.isfinite(self.roll_rad) and math.isfinite(self.pitch_rad)
                and math.isfinite(self.yaw_rate_rad_s) and math.isfinite(self.thrust)):
            raise NonFiniteCommand(f"non-finite board command {self}")


@dataclass(frozen=True)
class Outbound:
    """A MAVLink message to send: to every endpoint (``link`` None) or back to one."""

    msg: Any
    link: int | None = None


@dataclass(frozen=True)
class VelocitySetpoint:
    """An accepted SET_POSITION_TARGET_LOCAL_NED (all present fields finite)."""

    v_h: tuple[float, float, float] | None  # already in H, or None when in local NED
    v_ned: tuple[float, float, float] | None
    yaw_rate_rad_s: float | None
    yaw_rad: float | None
    # PX4-style trajectory setpoints (issue 19): acceleration feed-forward a_d in the velocity's frame (H or
    # local NED; None = not given) and an optional position x_d (local NED, the odometry's frame)
    a_h: tuple[float, float, float] | None = None
    a_ned: tuple[float, float, float] | None = None
    p_ned: tuple[float, float, float] | None = None


@dataclass(frozen=True)
class AttitudeSetpoint:
    """An accepted SET_ATTITUDE_TARGET (all present fields finite)."""

    roll_rad: float
    pitch_rad: float
    yaw_rate_rad_s: float | None
    yaw_rad: float | None
    thrust: float | None


class BridgeState:
    """The autopilot's state (see the module docstring); services add behaviour, never state of their own.

    Its public fields are what the services share: each service's docstring names those it owns (writes).
    """

    def __init__(self, vehicle: VehicleConfig, params: ParamTable, sysid: int = 1, compid: int = 1,
                 unix_clock: Callable[[], float] | None = None) -> None:
        self.vehicle = vehicle
        self.params = params
        self.sysid, self.compid = sysid, compid
        self.unix_clock = unix_clock  # injected (time.time in the daemon); SYSTEM_TIME only
        self.mav = mavlink.MAVLink(None, sysid, compid)  # encoder only, no file
        # the PID velocity tracker always exists: take-off phase 1, the blind landing and the odometry-lost
        # descent fly on it whatever BRG_TRACKER says; ``tracker`` is the one BRG_TRACKER selects for the closed
        # loop (the same object when BRG_TRACKER = 0). A PARAM_SET of BRG_TRACKER takes effect on the ground only.
        self.pid_tracker = VelocityTracker(vehicle.mass_kg, vehicle.max_total_thrust_n, params.tracker_gains())
        self.tracker_kind = TrackerKind.PID_VELOCITY
        self._tracker_switch_noted = False
        self.tracker: VelocityTracker | GeometricTracker = self.pid_tracker
        self._select_tracker(int(params["BRG_TRACKER"]))
        self.filter = BridgeAttitude(tau_s=params["BRG_ATT_TAU"])
        self.mode = FlightMode.POSCTL
        self.armed_cmd = False
        self.in_air = False
        self.failsafe_reason: str | None = None
        self.events: list[tuple[int, str]] = []  # (MAV_SEVERITY, text), flushed by tick()/control_step()
        self.statustext_ids = ChunkIds()         # a text over 50 bytes goes out in chunks
        # board
        self.board_status: BoardStatusLike | None = None
        self.board_status_time_s: float | None = None
        self.board_version: str | None = None
        self.board_version_int = 0
        self.board_link_ok = False
        self.board_failsafe_reported = False
        self.arm_mismatch_since_s: float | None = None
        # IMU
        self.imu_time_s: float | None = None
        self.last_imu_time_usec = 0
        self.imu_samples = 0
        self.last_accel_q = np.array([0.0, 0.0, -GRAVITY_M_S2])
        self.last_gyro_q = np.zeros(3)
        # odometry
        self.odom_time_s: float | None = None
        self.v_h_odom = np.zeros(3)
        self.dv_h_imu = np.zeros(3)
        self.odom_z_m: float | None = None
        self.odom_ok = False
        # the velocity in H from the last odometry on, integrated from the IMU (leaky): with the odometry lost
        # in the air it brakes the slide (x, y) and paces the descent (z) (firmware_bridge.flight_control)
        self.v_h_dead_reckoned = np.zeros(3)
        # the velocity gate's reference: the IMU's prediction, pulled a share (BRG_ODOM_VGATE_K) toward each accepted
        # odometry velocity -- a ramp of odometry error cannot walk it along, as it walks the last accepted sample
        self.v_h_gate_ref = np.zeros(3)
        self.odom_lost_s: float | None = None   # when the odometry was lost in the air (None: not lost)
        self.low_thrust_since_s: float | None = None  # since when the thrust is under the touchdown test's (None: not)
        self.odom_reset_counter: int | None = None
        self.odom_p_ned_m: np.ndarray | None = None  # the odometry's position (its local frame), if finite
        self.hold_anchor_ned_m: np.ndarray | None = None  # where LAND or TAKEOFF began (x, y of the odometry)
        # the horizontal velocity the accelerometer's drag reading gives, learnt while the odometry is good
        self.drag = DragVelocity()
        self.drag_told = False   # the STATUSTEXT when the fit is first trusted
        # the odometry's horizontal velocity through the drag's low-pass (every sample in the air, used or not), and
        # since when it has disagreed with the drag's by more than BRG_ODOM_DGATE (firmware_bridge.offboard)
        self.odom_v_h_lp: np.ndarray | None = None
        self.odom_lp_time_s: float | None = None
        self.drag_disagree_since_s: float | None = None
        self.drag_disagreement_max_m_s = 0.0   # the largest seen since the bridge started, across flights, as the
                                               # drag's fit lives (the status line; the gate's margin)
        # flight without odometry (take-off phase 1 and the landing after it): accelerometer-only vertical
        self.vertical = VerticalEstimator(vehicle.hover_thrust_fraction, params["MPC_Z_VEL_MAX_UP"],
                                          params["MPC_Z_VEL_MAX_DN"])
        self.baro_frames = 0   # the board's 'Z' frames received (0: a board without the barometer frame)
        self.blind = False  # in the air and no odometry acquired yet in this flight
        self.takeoff_phase: TakeoffPhase | None = None
        self.takeoff_start_s: float | None = None
        self.tko_ramp_start_s: float | None = None   # the open-loop climb's thrust ramp from idle (None: no ramp)
        self.tko_climbed_m = 0.0           # the take-off's climb, integrated from the velocity estimate
        self.tko_disagree_told = False
        self.hover_thrust_learned: float | None = None
        self.blind_descent: BlindDescent | None = None
        # setpoints
        self.setpoint_time_s: float | None = None
        self.vel_sp: VelocitySetpoint | None = None
        self.att_sp: AttitudeSetpoint | None = None
        # takeoff / landing
        self.height_m = 0.0  # above the take-off point, integrated or from odometry z
        self.z_ground_m: float | None = None
        self.takeoff_target_m = params["MIS_TAKEOFF_ALT"]
        self.touchdown_since_s: float | None = None
        self.fs_hover_until_s: float | None = None
        self.on_ground_armed_since_s: float | None = None
        self.last_command: AttitudeCommand | None = None
        self.last_board_command = BoardCommand(0.0, 0.0, 0.0, 0.0, False)
        # (roll, pitch) the board is commanded for level by the bridge's estimate: the board holds its own estimate,
        # off the true level by its errors; learnt in steady flight on odometry (flight_control), 0 on the ground
        self.level_trim_rad = np.zeros(2)
        self.control_time_s: float | None = None
        self.yaw_sp_rad: float | None = None
        # streams and counters
        self.streams = StreamScheduler()
        self.stream_interval_s = self.streams.interval_s  # the same dict: the scheduler's table
        self.counters: dict[str, int] = {"mavlink_bad": 0, "mk_bad": 0, "setpoint_rejected": 0,
                                         "odometry_rejected": 0, "odometry_low_quality": 0, "odometry_gated": 0,
                                         "odometry_drag_gated": 0,
                                         "odometry_vz_gated": 0, "commands": 0, "unsupported_commands": 0,
                                         "commands_refused": 0, "handler_errors": 0, "param_refused": 0}
        self._last_counter_report_s = -math.inf

    def _select_tracker(self, kind: int) -> None:
        """Build the tracker ``BRG_TRACKER`` selects (``make_tracker``); the PID tracker is reused for 0."""
        k = TrackerKind(int(kind))
        if k == TrackerKind.PID_VELOCITY:
            self.tracker = self.pid_tracker
        else:
            self.tracker = make_tracker(k, self.vehicle.mass_kg, self.vehicle.max_total_thrust_n,
                                        self.params.tracker_gains(), self.params.geometric_gains())
        self.tracker_kind = k

    def reset_trackers(self) -> None:
        self.pid_tracker.reset()
        if self.tracker is not self.pid_tracker:
            self.tracker.reset()

    def apply_tracker_selection(self) -> None:
        """Switch to the tracker ``BRG_TRACKER`` names, on the ground only (no handover in the air: the two
        trackers' integrals mean different things, so a switch waits for the landing; STATUSTEXT says so)."""
        wanted = TrackerKind(int(self.params["BRG_TRACKER"]))
        if wanted == self.tracker_kind:
            self._tracker_switch_noted = False
            return
        if self.in_air:
            if not self._tracker_switch_noted:
                self._tracker_switch_noted = True
                self.event(mavlink.MAV_SEVERITY_NOTICE, f"BRG_TRACKER {int(wanted)}: applied once landed")
            return
        self._select_tracker(int(wanted))
        self._tracker_switch_noted = False
        self.event(mavlink.MAV_SEVERITY_INFO, f"Tracker: {wanted.name.lower()}")

    def event(self, severity: int, text: str) -> None:
        log.log(logging.WARNING if severity <= mavlink.MAV_SEVERITY_WARNING else logging.INFO, "%s", text)
        self.events.append((severity, text))

    def flush_events(self) -> list[Outbound]:
        out = [Outbound(m) for sev, text in self.events
               for m in statustext_messages(sev, text, self.statustext_ids.next())]
        self.events.clear()
        return out

    def fresh(self, stamp_s: float | None, now_s: float, timeout_s: float) -> bool:
        return stamp_s is not None and now_s - stamp_s <= timeout_s

    @property
    def armed(self) -> bool:
        """Armed as reported on MAVLink: the board's word when it talks, else our request."""
        if self.board_link_ok and self.board_status is not None:
            return bool(self.board_status.armed)
        return self.armed_cmd

    def note_malformed(self, kind: str, now_s: float, detail: str = "") -> None:
        """Count bad input (``mavlink_bad`` or ``mk_bad``); log at most once every 5 s."""
        self.counters[kind] = self.counters.get(kind, 0) + 1
        if now_s - self._last_counter_report_s >= MALFORMED_LOG_INTERVAL_S:
            self._last_counter_report_s = now_s
            log.warning("malformed input: %s %s (counts: mavlink %d, mk %d)", kind, detail,
                        self.counters["mavlink_bad"], self.counters["mk_bad"])

    def for_us(self, msg: Any) -> bool:
        ts = getattr(msg, "target_system", 0)
        tc = getattr(msg, "target_component", 0)
        return ts in (0, self.sysid) and tc in (0, self.compid)

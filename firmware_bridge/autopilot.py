"""The MAVLink autopilot facade as a pure state machine (no sockets, no threads, no wall clock).

The daemon (:mod:`firmware_bridge.daemon`) feeds it decoded inputs with the current time ``now_s``
(board time: IMU sample k is at k * 2 ms; a wall-clock fallback only while the IMU stream is lost)
and sends what it returns:

* :meth:`Autopilot.on_imu` -> HIGHRES_IMU (one per sample), ATTITUDE / ATTITUDE_QUATERNION at their rate;
* :meth:`Autopilot.control_step` (every 5th IMU sample, 100 Hz) -> a :class:`BoardCommand` for the
  board's ``AttitudeSetpoint``;
* :meth:`Autopilot.on_board_status` / :meth:`Autopilot.on_board_version` -> board state;
* :meth:`Autopilot.handle_mavlink` -> replies (parameters, commands, TIMESYNC), addressed to the link
  the request came from;
* :meth:`Autopilot.tick` -> periodic messages (HEARTBEAT 1 Hz, SYS_STATUS, SYSTEM_TIME,
  EXTENDED_SYS_STATE), failsafe checks and STATUSTEXT events.

Modes use PX4's custom-mode numbering (``main << 16 | sub << 24``, px4_custom_mode.h) with
``MAV_AUTOPILOT_GENERIC`` in the heartbeat, so MAVSDK (which falls back to PX4's encoding for
generic autopilots) can switch to and confirm OFFBOARD. DO_SET_MODE also accepts ArduCopter's mode
numbers (what pymavlink/MAVProxy send for a generic quadrotor: ``mode LAND`` = 9, ``LOITER`` = 5,
``GUIDED`` = 4 -> OFFBOARD) wherever they do not collide with PX4's main modes (PX4 wins).

Velocity setpoints (SET_POSITION_TARGET_LOCAL_NED, type_mask 1479 velocity + yaw rate, 3527
velocity only, 2503 velocity + yaw): in MAV_FRAME_BODY_NED, BODY_OFFSET_NED and BODY_FRD the
velocity is taken in the yaw-aligned body frame H (rotated by yaw only), which is what PX4's
mavlink receiver and ArduCopter's GUIDED mode do with these frames; in MAV_FRAME_LOCAL_NED /
LOCAL_OFFSET_NED it is in the odometry's local NED frame and rotated into H with the yaw estimate.
"""

from __future__ import annotations

import enum
import logging
import math
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from firmware_bridge.attitude_filter import BridgeAttitude
from firmware_bridge.params import ParamTable
from firmware_bridge.velocity_tracker import AttitudeCommand, VelocityTracker
from firmware_bridge.vertical_estimator import VerticalEstimator
from quadlink import __version__
from quadlink.frames import GRAVITY_M_S2, R_from_quat_wxyz, R_hq, Rz, euler_from_R, quat_wxyz_from_euler, wrap_pi
from quadlink.mavlink import mavlink
from quadlink.mk.flags import BoardError, BoardFlightState
from quadlink.vehicle import VehicleConfig

log = logging.getLogger(__name__)

# PX4 custom modes (px4_custom_mode.h): main mode in bits 16..23, sub mode in bits 24..31
PX4_MAIN_ALTCTL, PX4_MAIN_POSCTL, PX4_MAIN_AUTO, PX4_MAIN_OFFBOARD = 2, 3, 4, 6
PX4_AUTO_TAKEOFF, PX4_AUTO_LOITER, PX4_AUTO_LAND = 2, 3, 6


class FlightMode(enum.Enum):
    """Bridge modes and their PX4 (main, sub) custom mode."""

    ALTCTL = (PX4_MAIN_ALTCTL, 0)  # hold (velocity zero), like POSCTL: no sticks here
    POSCTL = (PX4_MAIN_POSCTL, 0)
    OFFBOARD = (PX4_MAIN_OFFBOARD, 0)
    TAKEOFF = (PX4_MAIN_AUTO, PX4_AUTO_TAKEOFF)
    LOITER = (PX4_MAIN_AUTO, PX4_AUTO_LOITER)
    LAND = (PX4_MAIN_AUTO, PX4_AUTO_LAND)

    @property
    def custom_mode(self) -> int:
        main, sub = self.value
        return (main << 16) | (sub << 24)

    @classmethod
    def from_px4(cls, main: int, sub: int) -> FlightMode | None:
        for mode in cls:
            if mode.value == (main, sub):
                return mode
        return None


#: ArduCopter mode numbers (pymavlink's mode map for a generic quadrotor) -> bridge mode
ARDUCOPTER_MODES: dict[int, FlightMode] = {9: FlightMode.LAND, 5: FlightMode.LOITER, 16: FlightMode.POSCTL,
                                           4: FlightMode.OFFBOARD}

HOLD_MODES = (FlightMode.ALTCTL, FlightMode.POSCTL, FlightMode.LOITER)


class TakeoffPhase(enum.Enum):
    """Take-off phases (the camera sees the floor closer than its minimum range until ~0.3-0.5 m up)."""

    OPEN_LOOP = 1  # no odometry yet: level, heading hold, climb on the accelerometer's vertical estimate
    CLOSED_LOOP = 2  # odometry: the velocity tracker finishes the climb


# SET_POSITION_TARGET_LOCAL_NED type_mask bits (POSITION_TARGET_TYPEMASK)
TM_POSITION = 0x007
TM_VELOCITY = 0x038
TM_ACCEL = 0x1C0
TM_FORCE = 0x200
TM_YAW = 0x400
TM_YAW_RATE = 0x800
BODY_FRAMES = (mavlink.MAV_FRAME_BODY_NED, mavlink.MAV_FRAME_BODY_OFFSET_NED, mavlink.MAV_FRAME_BODY_FRD)
LOCAL_FRAMES = (mavlink.MAV_FRAME_LOCAL_NED, mavlink.MAV_FRAME_LOCAL_OFFSET_NED, mavlink.MAV_FRAME_LOCAL_FRD)
ODOM_WORLD_FRAMES = (mavlink.MAV_FRAME_LOCAL_NED, mavlink.MAV_FRAME_LOCAL_FRD)
ODOM_BODY_FRAMES = (mavlink.MAV_FRAME_BODY_FRD, mavlink.MAV_FRAME_BODY_NED)

# SET_ATTITUDE_TARGET type_mask bits (ATTITUDE_TARGET_TYPEMASK)
ATM_YAW_RATE = 0x04
ATM_THRUST = 0x40
ATM_ATTITUDE = 0x80

STREAM_DEFAULT_INTERVAL_S: dict[int, float] = {
    mavlink.MAVLINK_MSG_ID_HEARTBEAT: 1.0,
    mavlink.MAVLINK_MSG_ID_SYS_STATUS: 1.0,
    mavlink.MAVLINK_MSG_ID_SYSTEM_TIME: 1.0,
    mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 1.0,
    mavlink.MAVLINK_MSG_ID_ATTITUDE: 0.02,
    mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: -1.0,  # off unless requested
    mavlink.MAVLINK_MSG_ID_HIGHRES_IMU: 0.0,  # 0: every IMU sample
    mavlink.MAVLINK_MSG_ID_BATTERY_STATUS: -1.0,
}
IMU_STREAMS = (mavlink.MAVLINK_MSG_ID_HIGHRES_IMU, mavlink.MAVLINK_MSG_ID_ATTITUDE,
               mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION)

SENSORS_PRESENT = (mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO | mavlink.MAV_SYS_STATUS_SENSOR_3D_ACCEL
                   | mavlink.MAV_SYS_STATUS_SENSOR_VISION_POSITION | mavlink.MAV_SYS_STATUS_SENSOR_ANGULAR_RATE_CONTROL
                   | mavlink.MAV_SYS_STATUS_SENSOR_ATTITUDE_STABILIZATION
                   | mavlink.MAV_SYS_STATUS_SENSOR_Z_ALTITUDE_CONTROL
                   | mavlink.MAV_SYS_STATUS_SENSOR_XY_POSITION_CONTROL
                   | mavlink.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS | mavlink.MAV_SYS_STATUS_SENSOR_BATTERY)

CAPABILITIES = (mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2 | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
                | mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
                | mavlink.MAV_PROTOCOL_CAPABILITY_SET_ATTITUDE_TARGET
                | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE)

TOUCHDOWN_HOLD_S = 0.5
SETPOINT_FRESH_FOR_OFFBOARD_S = 0.5  # PX4 wants the stream running before the switch
IMU_PREDICTION_HORIZON_S = 0.3
MAX_HEADING_ERROR_RAD = 0.5
ODOM_LOST_VZ_LEAK_TAU_S = 3.0
HOVER_LEARN_TAU_S = 1.0  # low-pass of the thrust in the open-loop climb: the hover thrust actually needed
GROUND_CONTACT_ACCEL_M_S2 = 0.3  # below hover thrust, less vertical acceleration than this = the ground carries it
BLIND_DESCENT_EXTRA_S = 3.0  # the blind descent probes for the ground after height / rate + this


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


@dataclass(frozen=True)
class BoardCommand:
    """What the board gets at 100 Hz (the daemon packs it into an MK ``AttitudeSetpoint``)."""

    roll_rad: float
    pitch_rad: float
    yaw_rate_rad_s: float
    thrust: float  # fraction 0..1 of the max total thrust
    armed: bool


@dataclass(frozen=True)
class Outbound:
    """A MAVLink message to send: to every endpoint (``link`` None) or back to one."""

    msg: Any
    link: int | None = None


@dataclass(frozen=True)
class _VelocitySetpoint:
    v_h: tuple[float, float, float] | None  # already in H, or None when in local NED
    v_ned: tuple[float, float, float] | None
    yaw_rate_rad_s: float | None
    yaw_rad: float | None


@dataclass(frozen=True)
class _AttitudeSetpoint:
    roll_rad: float
    pitch_rad: float
    yaw_rate_rad_s: float | None
    yaw_rad: float | None
    thrust: float | None


class Autopilot:
    def __init__(self, vehicle: VehicleConfig, params: ParamTable, sysid: int = 1, compid: int = 1,
                 unix_clock: Any = None) -> None:
        self.vehicle = vehicle
        self.params = params
        self.sysid, self.compid = sysid, compid
        self._unix_clock = unix_clock  # injected (time.time in the daemon); SYSTEM_TIME only
        self.mav = mavlink.MAVLink(None, sysid, compid)  # encoder only, no file
        self.tracker = VelocityTracker(vehicle.mass_kg, vehicle.max_total_thrust_n, params.tracker_gains())
        self.filter = BridgeAttitude(tau_s=params["BRG_ATT_TAU"])
        self.mode = FlightMode.POSCTL
        self.armed_cmd = False
        self.in_air = False
        self.failsafe_reason: str | None = None
        self.events: list[tuple[int, str]] = []  # (MAV_SEVERITY, text), flushed by tick()/control_step()
        # board
        self.board_status: BoardStatusLike | None = None
        self.board_status_time_s: float | None = None
        self.board_version: str | None = None
        self.board_version_int = 0
        self.board_link_ok = False
        self._board_failsafe_reported = False
        self._arm_mismatch_since_s: float | None = None
        # IMU
        self.imu_time_s: float | None = None
        self.last_imu_time_usec = 0
        self.imu_samples = 0
        self._last_accel_q = np.array([0.0, 0.0, -GRAVITY_M_S2])
        self._last_gyro_q = np.zeros(3)
        # odometry
        self.odom_time_s: float | None = None
        self._v_h_odom = np.zeros(3)
        self._dv_h_imu = np.zeros(3)
        self._odom_z_m: float | None = None
        self.odom_ok = False
        self._vz_dead_reckoned = 0.0
        self._odom_reset_counter: int | None = None
        # flight without odometry (take-off phase 1 and the landing after it): accelerometer-only vertical
        self.vertical = VerticalEstimator(vehicle.hover_thrust_fraction, params["MPC_Z_VEL_MAX_UP"],
                                          params["MPC_Z_VEL_MAX_DN"])
        self.blind = False  # in the air and no odometry acquired yet in this flight
        self.takeoff_phase: TakeoffPhase | None = None
        self._takeoff_start_s: float | None = None
        self._hover_thrust_learned: float | None = None
        self._blind_descent: tuple[float, float] | None = None  # (start time, estimated height then)
        # setpoints
        self.setpoint_time_s: float | None = None
        self._vel_sp: _VelocitySetpoint | None = None
        self._att_sp: _AttitudeSetpoint | None = None
        # takeoff / landing
        self.height_m = 0.0  # above the take-off point, integrated or from odometry z
        self._z_ground_m: float | None = None
        self.takeoff_target_m = params["MIS_TAKEOFF_ALT"]
        self._touchdown_since_s: float | None = None
        self._fs_hover_until_s: float | None = None
        self._on_ground_armed_since_s: float | None = None
        self.last_command: AttitudeCommand | None = None
        self.last_board_command = BoardCommand(0.0, 0.0, 0.0, 0.0, False)
        self._control_time_s: float | None = None
        self._yaw_sp_rad: float | None = None
        # streams and counters
        self.stream_interval_s = dict(STREAM_DEFAULT_INTERVAL_S)
        self._stream_last_s: dict[int, float] = {}
        self.counters: dict[str, int] = {"mavlink_bad": 0, "mk_bad": 0, "setpoint_rejected": 0,
                                         "odometry_rejected": 0, "odometry_low_quality": 0, "commands": 0,
                                         "unsupported_commands": 0}
        self._last_counter_report_s = -math.inf

    # ------------------------------------------------------------------ helpers
    def _event(self, severity: int, text: str) -> None:
        log.log(logging.WARNING if severity <= mavlink.MAV_SEVERITY_WARNING else logging.INFO, "%s", text)
        self.events.append((severity, text[:50]))

    def _flush_events(self) -> list[Outbound]:
        out = [Outbound(self.mav.statustext_encode(sev, text.encode("ascii", "replace"))) for sev, text in self.events]
        self.events.clear()
        return out

    def _fresh(self, stamp_s: float | None, now_s: float, timeout_s: float) -> bool:
        return stamp_s is not None and now_s - stamp_s <= timeout_s

    @property
    def armed(self) -> bool:
        """Armed as reported on MAVLink: the board's word when it talks, else our request."""
        if self.board_link_ok and self.board_status is not None:
            return bool(self.board_status.armed)
        return self.armed_cmd

    def apply_params(self) -> None:
        self.tracker.set_gains(self.params.tracker_gains())
        self.filter.set_tau(self.params["BRG_ATT_TAU"])
        self.vertical.max_climb_m_s = self.params["MPC_Z_VEL_MAX_UP"]
        self.vertical.max_descent_m_s = self.params["MPC_Z_VEL_MAX_DN"]

    def set_mode(self, mode: FlightMode, now_s: float, reason: str = "") -> None:
        if mode == self.mode:
            return
        log.info("mode %s -> %s%s", self.mode.name, mode.name, f" ({reason})" if reason else "")
        self.mode = mode
        self._touchdown_since_s = None
        if mode == FlightMode.TAKEOFF:
            self._start_takeoff(now_s)

    def _start_takeoff(self, now_s: float) -> None:
        was_in_air, self.in_air = self.in_air, True
        if self.odom_ok:
            self.takeoff_phase = TakeoffPhase.CLOSED_LOOP
            if self._z_ground_m is None:
                self._z_ground_m = self._odom_z_m
            self._event(mavlink.MAV_SEVERITY_INFO, f"Takeoff to {self.takeoff_target_m:.1f} m")
            return
        # phase 1: the camera cannot see yet; climb level on the accelerometer until odometry arrives
        self.takeoff_phase = TakeoffPhase.OPEN_LOOP
        self.blind = True
        self._takeoff_start_s = now_s
        self._hover_thrust_learned = None
        self._blind_descent = None
        if not was_in_air:
            self.vertical.reset_ground()
        self._z_ground_m = None
        self.height_m = self.vertical.height_m
        self._event(mavlink.MAV_SEVERITY_INFO, f"Takeoff to {self.takeoff_target_m:.1f} m, open loop until odometry")

    def note_malformed(self, kind: str, now_s: float, detail: str = "") -> None:
        """Count bad input (``mavlink_bad`` or ``mk_bad``); log at most once every 5 s."""
        self.counters[kind] = self.counters.get(kind, 0) + 1
        if now_s - self._last_counter_report_s >= 5.0:
            self._last_counter_report_s = now_s
            log.warning("malformed input: %s %s (counts: mavlink %d, mk %d)", kind, detail,
                        self.counters["mavlink_bad"], self.counters["mk_bad"])

    # ------------------------------------------------------------------ board side
    def on_imu(self, now_s: float, time_usec: int, accel_q_m_s2: np.ndarray,
               gyro_q_rad_s: np.ndarray) -> list[Outbound]:
        """One IMU sample (SI, body FRD) at board time ``time_usec``; returns its telemetry."""
        dt = 0.0 if self.imu_time_s is None else now_s - self.imu_time_s
        if self.imu_time_s is None or dt < 0 or dt > 0.1:
            dt = 1.0 / self.vehicle.imu.rate_hz
        self.imu_time_s = now_s
        self.last_imu_time_usec = int(time_usec)
        self.imu_samples += 1
        self._last_accel_q = np.asarray(accel_q_m_s2, dtype=float)
        self._last_gyro_q = np.asarray(gyro_q_rad_s, dtype=float)
        est = self.filter.update(now_s, self._last_gyro_q, self._last_accel_q)
        # acceleration in H from the specific force: a_h = R_hq f_q + g e3
        a_h = R_hq(est.roll_rad, est.pitch_rad) @ self._last_accel_q + np.array([0.0, 0.0, GRAVITY_M_S2])
        if self.in_air:
            self._dv_h_imu += a_h * dt
            self._vz_dead_reckoned += a_h[2] * dt - self._vz_dead_reckoned * dt / ODOM_LOST_VZ_LEAK_TAU_S
        board = self.last_board_command
        self.vertical.update(dt, float(a_h[2]), board.thrust if board.armed else 0.0, on_ground=not self.in_air)
        out: list[Outbound] = []
        if self._stream_due(mavlink.MAVLINK_MSG_ID_HIGHRES_IMU, now_s):
            a, w = self._last_accel_q, self._last_gyro_q
            out.append(Outbound(self.mav.highres_imu_encode(
                int(time_usec), float(a[0]), float(a[1]), float(a[2]), float(w[0]), float(w[1]), float(w[2]),
                0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0x3F)))
        boot_ms = int(time_usec // 1000) & 0xFFFFFFFF
        if self._stream_due(mavlink.MAVLINK_MSG_ID_ATTITUDE, now_s):
            out.append(Outbound(self.mav.attitude_encode(boot_ms, est.roll_rad, est.pitch_rad, est.yaw_rad,
                                                         est.rollspeed_rad_s, est.pitchspeed_rad_s,
                                                         est.yawspeed_rad_s)))
        if self._stream_due(mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION, now_s):
            q = quat_wxyz_from_euler(est.roll_rad, est.pitch_rad, est.yaw_rad)  # [w, x, y, z], as MAVLink
            out.append(Outbound(self.mav.attitude_quaternion_encode(
                boot_ms, float(q[0]), float(q[1]), float(q[2]), float(q[3]), est.rollspeed_rad_s,
                est.pitchspeed_rad_s, est.yawspeed_rad_s)))
        return out

    def on_board_status(self, now_s: float, status: BoardStatusLike) -> list[Outbound]:
        prev = self.board_status
        self.board_status = status
        self.board_status_time_s = now_s
        if not self.board_link_ok:
            self.board_link_ok = True
            self._event(mavlink.MAV_SEVERITY_INFO, "Board link up")
        if status.failsafe and not self._board_failsafe_reported:
            self._board_failsafe_reported = True
            self._event(mavlink.MAV_SEVERITY_CRITICAL, f"Board failsafe (flags 0x{status.error_flags:x})")
        elif not status.failsafe:
            self._board_failsafe_reported = False
        if prev is not None and bool(prev.armed) != bool(status.armed):
            self._event(mavlink.MAV_SEVERITY_INFO, "Board armed" if status.armed else "Board disarmed")
        if status.flight_state == BoardFlightState.FLYING and self.armed_cmd:
            self.in_air = True
        return self._flush_events()

    def on_board_version(self, text: str, version_int: int = 0) -> None:
        self.board_version = text
        self.board_version_int = version_int
        log.info("board firmware: %s", text)

    # ------------------------------------------------------------------ 100 Hz control
    def v_est_h(self, now_s: float) -> np.ndarray:
        """Velocity in H: last odometry plus the IMU-integrated change since (short horizon)."""
        if self.odom_time_s is not None and now_s - self.odom_time_s <= IMU_PREDICTION_HORIZON_S:
            return self._v_h_odom + self._dv_h_imu
        return self._v_h_odom.copy()

    def control_step(self, now_s: float) -> BoardCommand:
        """The 100 Hz step: failsafes, mode logic, the velocity tracker; the board's next setpoint."""
        dt = 0.01 if self._control_time_s is None else min(max(now_s - self._control_time_s, 1e-3), 0.1)
        self._control_time_s = now_s
        self._check_links(now_s)
        self._update_height(dt)
        est = self.filter.estimate
        if not self.in_air or (not self.odom_ok and not self.blind) or \
                (self.mode == FlightMode.OFFBOARD and self._att_sp is not None):
            self._yaw_sp_rad = None  # heading hold only in velocity control (or the blind climb) in the air
        if not self.armed_cmd:
            self.in_air = False
            self.blind = False
            self.takeoff_phase = None
            self._blind_descent = None
            self.tracker.reset()
            self._on_ground_armed_since_s = None
            return self._board(BoardCommand(0.0, 0.0, 0.0, 0.0, False))
        if not self.in_air:
            # armed on the ground: motors at idle, level, nothing integrates (PX4's "landed" state)
            self.tracker.reset()
            self._dv_h_imu[:] = 0.0
            if self._on_ground_armed_since_s is None:
                self._on_ground_armed_since_s = now_s
            timeout = self.params["COM_DISARM_PRFLT"]
            if timeout > 0 and now_s - self._on_ground_armed_since_s > timeout:
                self._disarm(now_s, "Auto-disarm: no takeoff")
                return self._board(BoardCommand(0.0, 0.0, 0.0, 0.0, False))
            if self.mode == FlightMode.LAND:
                self._disarm(now_s, "Landed, disarming")
                return self._board(BoardCommand(0.0, 0.0, 0.0, 0.0, False))
            return self._board(BoardCommand(0.0, 0.0, 0.0, 0.0, True))
        self._on_ground_armed_since_s = None

        # ---- no odometry yet in this flight: take-off phase 1, or the landing that ends it
        if self.blind and not self.odom_ok and not (self.mode == FlightMode.OFFBOARD and self._att_sp is not None):
            return self._blind_step(now_s, dt, est)

        # ---- odometry lost in the air: level attitude hold and descend on the IMU's vertical speed
        if not self.odom_ok and not (self.mode == FlightMode.OFFBOARD and self._att_sp is not None):
            v_ref = np.array([0.0, 0.0, self.params["MPC_LAND_SPEED"]])
            v_est = np.array([0.0, 0.0, self._vz_dead_reckoned])
            cmd = self.tracker.update(dt, v_ref, 0.0, v_est, est.roll_rad, est.pitch_rad)
            cmd = AttitudeCommand(0.0, 0.0, 0.0, cmd.thrust_fraction, cmd.a_des_h_m_s2, cmd.saturated)
            self._detect_touchdown(now_s, cmd, abs(self._vz_dead_reckoned))
            return self._finish(cmd)

        if self.mode == FlightMode.OFFBOARD and self._att_sp is not None:
            return self._finish(self._attitude_command(self._att_sp, est))

        v_ref = np.zeros(3)
        yaw_rate = 0.0
        if self.mode == FlightMode.OFFBOARD and self._vel_sp is not None:
            v_ref, yaw_rate = self._velocity_reference(self._vel_sp, est.yaw_rad)
        elif self.mode == FlightMode.TAKEOFF:
            remaining = self.takeoff_target_m - self.height_m
            v_ref[2] = -min(self.params["MPC_TKO_SPEED"], max(1.0 * remaining, 0.1))
            if remaining <= 0.05:
                self._event(mavlink.MAV_SEVERITY_INFO, f"Takeoff complete at {self.height_m:.2f} m")
                self.takeoff_phase = None
                self.set_mode(FlightMode.LOITER, now_s, "takeoff complete")
                v_ref[2] = 0.0
        elif self.mode == FlightMode.LAND:
            v_ref[2] = self.params["MPC_LAND_SPEED"]
        elif self._fs_hover_until_s is not None and now_s >= self._fs_hover_until_s:
            self._fs_hover_until_s = None
            self._event(mavlink.MAV_SEVERITY_WARNING, "Failsafe: hover done, landing")
            self.set_mode(FlightMode.LAND, now_s, "failsafe")
        sp = self._vel_sp
        if self.mode == FlightMode.OFFBOARD and sp is not None and sp.yaw_rate_rad_s is None and sp.yaw_rad is not None:
            self._yaw_sp_rad = None  # an absolute yaw target is tracked in _velocity_reference
        else:
            yaw_rate = self._heading_hold(dt, yaw_rate, est.yaw_rad)
        v_est = self.v_est_h(now_s)
        cmd = self.tracker.update(dt, v_ref, yaw_rate, v_est, est.roll_rad, est.pitch_rad)
        if self.mode == FlightMode.LAND:
            self._detect_touchdown(now_s, cmd, abs(v_est[2]))
        return self._finish(cmd)

    def _blind_step(self, now_s: float, dt: float, est: Any) -> BoardCommand:
        """Flight before any odometry: level (roll = pitch = 0), heading hold on the gyro, vertical velocity
        tracked on the accelerometer-only estimate, thrust under a ceiling. TAKEOFF climbs at BRG_TKO_OL_SPD
        toward the take-off height (thrust ramped up to hover x (1 + BRG_TKO_THR_MRG) over BRG_TKO_RAMP_T)
        until odometry arrives, at most BRG_TKO_OL_ALT (estimated) or BRG_TKO_OL_T; then, or in any other
        mode, it descends at BRG_OL_LAND_SPD with the thrust capped at the hover thrust learnt in the climb
        (it can not climb on a drifting estimate). Once the estimate says ground (height 0, or the descent
        took BLIND_DESCENT_EXTRA_S longer than height / rate) the cap drops to BRG_FS_DESC_THR x hover: in the
        air the vehicle then accelerates downwards, on the ground the accelerometer shows nothing, which is
        the touchdown test that does not depend on the drifting velocity."""
        p = self.params
        hover_prior = self.tracker.hover_thrust_fraction
        margin = p["BRG_TKO_THR_MRG"]
        vz_est = self.vertical.vz_m_s
        elapsed = 0.0
        if self.mode == FlightMode.TAKEOFF:
            elapsed = now_s - (self._takeoff_start_s if self._takeoff_start_s is not None else now_s)
            height = self.vertical.height_m
            if height >= p["BRG_TKO_OL_ALT"] or elapsed >= p["BRG_TKO_OL_T"]:
                self._event(mavlink.MAV_SEVERITY_CRITICAL,
                            f"No odometry in takeoff ({elapsed:.1f}s, {height:.2f}m): land")
                self.failsafe_reason = "no odometry in takeoff"
                self.takeoff_phase = None
                self.set_mode(FlightMode.LAND, now_s, "no odometry in takeoff")
        elif self.mode != FlightMode.LAND:
            self._event(mavlink.MAV_SEVERITY_CRITICAL, "No odometry: landing")
            self.set_mode(FlightMode.LAND, now_s, "no odometry")
        if self.mode == FlightMode.TAKEOFF:
            remaining = self.takeoff_target_m - self.vertical.height_m
            vz_ref = -min(p["BRG_TKO_OL_SPD"], max(remaining, 0.0))  # slows into the target, then holds
            ceiling = hover_prior * (1.0 + margin)
            ramp_s = p["BRG_TKO_RAMP_T"]
            if ramp_s > 0:
                ceiling *= min(1.0, elapsed / ramp_s)
        probing = False
        if self.mode != FlightMode.TAKEOFF:
            vz_ref = p["BRG_OL_LAND_SPD"]
            if self._blind_descent is None:
                self._blind_descent = (now_s, self.vertical.height_m)
            start_s, height0 = self._blind_descent
            learned = self._hover_thrust_learned if self._hover_thrust_learned is not None else hover_prior
            ceiling = min(max(learned, hover_prior * (1.0 - margin)), hover_prior * (1.0 + margin))
            probing = self.vertical.height_m <= 0.0 or \
                now_s - start_s > height0 / vz_ref + BLIND_DESCENT_EXTRA_S
            if probing:
                ceiling *= p["BRG_FS_DESC_THR"]
        if self.vertical.estimate.pinned:
            self.tracker.reset()  # the ground carries the vehicle while the thrust ramps: nothing to integrate
        yaw_rate = self._heading_hold(dt, 0.0, est.yaw_rad)
        cmd = self.tracker.update(dt, np.array([0.0, 0.0, vz_ref]), yaw_rate, np.array([0.0, 0.0, vz_est]),
                                  est.roll_rad, est.pitch_rad)
        thrust = min(cmd.thrust_fraction, ceiling)
        cmd = AttitudeCommand(0.0, 0.0, cmd.yaw_rate_rad_s, thrust, cmd.a_des_h_m_s2,
                              cmd.saturated or thrust < cmd.thrust_fraction)
        if self.mode == FlightMode.TAKEOFF and not self.vertical.estimate.pinned:
            # what the climb needs, tilt-compensated: the descent's thrust ceiling
            level = thrust * math.cos(est.roll_rad) * math.cos(est.pitch_rad)
            if self._hover_thrust_learned is None:
                self._hover_thrust_learned = level
            self._hover_thrust_learned += (level - self._hover_thrust_learned) * dt / HOVER_LEARN_TAU_S
        if self.mode == FlightMode.LAND:
            ground = probing and thrust <= ceiling + 1e-6 and \
                abs(self.vertical.estimate.accel_z_m_s2) < GROUND_CONTACT_ACCEL_M_S2
            self._detect_touchdown(now_s, cmd, abs(vz_est), ground_contact=ground)
        return self._finish(cmd)

    def _heading_hold(self, dt: float, yaw_rate_ref: float, yaw_rad: float) -> float:
        """Yaw rate tracked through a heading setpoint (like PX4's yaw control): the setpoint integrates the
        reference rate, and the heading error (yaw anchored to the odometry) adds ``MC_YAW_P`` * error, so a
        zero yaw rate holds the heading instead of letting the board's rate loop drift."""
        if self._yaw_sp_rad is None:
            self._yaw_sp_rad = yaw_rad
        self._yaw_sp_rad = wrap_pi(self._yaw_sp_rad + yaw_rate_ref * dt)
        error = wrap_pi(self._yaw_sp_rad - yaw_rad)
        if abs(error) > MAX_HEADING_ERROR_RAD:  # do not wind up behind a saturated or blocked yaw
            self._yaw_sp_rad = wrap_pi(yaw_rad + math.copysign(MAX_HEADING_ERROR_RAD, error))
            error = math.copysign(MAX_HEADING_ERROR_RAD, error)
        return yaw_rate_ref + self.params["MC_YAW_P"] * error

    def _finish(self, cmd: AttitudeCommand) -> BoardCommand:
        self.last_command = cmd
        return self._board(BoardCommand(cmd.roll_rad, cmd.pitch_rad, cmd.yaw_rate_rad_s, cmd.thrust_fraction,
                                        self.armed_cmd))

    def _board(self, command: BoardCommand) -> BoardCommand:
        self.last_board_command = command
        return command

    def _velocity_reference(self, sp: _VelocitySetpoint, yaw_rad: float) -> tuple[np.ndarray, float]:
        if sp.v_h is not None:
            v_ref = np.array(sp.v_h)
        else:
            assert sp.v_ned is not None
            v_ref = Rz(-yaw_rad) @ np.array(sp.v_ned)  # local NED -> H: rotate by -yaw about z
        if sp.yaw_rate_rad_s is not None:
            yaw_rate = sp.yaw_rate_rad_s
        elif sp.yaw_rad is not None:
            yaw_rate = 2.0 * wrap_pi(sp.yaw_rad - yaw_rad)  # yaw tracked through the yaw-rate command
        else:
            yaw_rate = 0.0
        return v_ref, yaw_rate

    def _attitude_command(self, sp: _AttitudeSetpoint, est: Any) -> AttitudeCommand:
        g = self.tracker.gains
        roll = min(max(sp.roll_rad, -g.max_tilt_rad), g.max_tilt_rad)
        pitch = min(max(sp.pitch_rad, -g.max_tilt_rad), g.max_tilt_rad)
        if sp.yaw_rate_rad_s is not None:
            yaw_rate = sp.yaw_rate_rad_s
        elif sp.yaw_rad is not None:
            yaw_rate = 2.0 * wrap_pi(sp.yaw_rad - est.yaw_rad)
        else:
            yaw_rate = 0.0
        yaw_rate = min(max(yaw_rate, -g.max_yaw_rate_rad_s), g.max_yaw_rate_rad_s)
        thrust = self.tracker.hover_thrust_fraction if sp.thrust is None else sp.thrust
        thrust = min(max(thrust, 0.0), g.thrust_max_fraction)
        return AttitudeCommand(roll, pitch, yaw_rate, thrust)

    def _update_height(self, dt: float) -> None:
        if self.blind:
            self.height_m = self.vertical.height_m
        elif self._z_ground_m is not None and self._odom_z_m is not None:
            self.height_m = -(self._odom_z_m - self._z_ground_m)
        elif self.in_air:
            self.height_m -= float(self.v_est_h(self._control_time_s or 0.0)[2]) * dt
        else:
            self.height_m = 0.0

    def _detect_touchdown(self, now_s: float, cmd: AttitudeCommand, vz_abs_m_s: float,
                          ground_contact: bool = False) -> None:
        """Low vertical speed with low thrust (or the board saying landed), or ``ground_contact`` (thrust
        below hover without vertical acceleration, flight without odometry), held for LNDMC_TIME_S."""
        p = self.params
        board_landed = (self.board_link_ok and self.board_status is not None
                        and self.board_status.flight_state == BoardFlightState.LANDED)
        low_thrust = cmd.thrust_fraction < p["LNDMC_THR_MAX"] * self.tracker.hover_thrust_fraction
        if ground_contact or (vz_abs_m_s < p["LNDMC_Z_VEL_MAX"] and (low_thrust or board_landed)):
            if self._touchdown_since_s is None:
                self._touchdown_since_s = now_s
            elif now_s - self._touchdown_since_s >= p["LNDMC_TIME_S"]:
                self.in_air = False
                self._disarm(now_s, "Landed, disarming")
        else:
            self._touchdown_since_s = None

    def _disarm(self, now_s: float, why: str) -> None:
        if self.armed_cmd:
            self._event(mavlink.MAV_SEVERITY_INFO, why)
        self.armed_cmd = False
        self.in_air = False
        self.failsafe_reason = None
        self._fs_hover_until_s = None
        self._z_ground_m = None
        self.height_m = 0.0
        self.blind = False
        self.takeoff_phase = None
        self._blind_descent = None
        self.tracker.reset()

    def _odometry_ok_event(self) -> None:
        if self.in_air:
            self._event(mavlink.MAV_SEVERITY_INFO, "Odometry ok")
        else:  # on the ground odometry comes and goes (the camera sees the floor too close): the health bit says it
            log.info("odometry ok")

    def _check_links(self, now_s: float) -> None:
        p = self.params
        board_fresh = self._fresh(self.board_status_time_s, now_s, p["BRG_BOARD_LOSS_T"]) or \
            self._fresh(self.imu_time_s, now_s, p["BRG_BOARD_LOSS_T"])
        if self.board_link_ok and not board_fresh:
            self.board_link_ok = False
            self._event(mavlink.MAV_SEVERITY_CRITICAL, "Board link lost")
            self.failsafe_reason = "board link lost"
        odom_fresh = self._fresh(self.odom_time_s, now_s, p["BRG_ODOM_LOSS_T"])
        if self.odom_ok and not odom_fresh:
            self.odom_ok = False
            if self.in_air:
                self._event(mavlink.MAV_SEVERITY_CRITICAL, "Odometry lost: level hold, descending")
                self.failsafe_reason = "odometry lost"
                self._vz_dead_reckoned = float(self.v_est_h(now_s)[2])
                self.set_mode(FlightMode.LAND, now_s, "odometry lost")
            else:
                log.info("odometry lost (on the ground: nothing depends on it)")  # the health bit says it
        elif odom_fresh and not self.odom_ok:
            self.odom_ok = True
            self._odometry_ok_event()
        if self.mode == FlightMode.OFFBOARD and self.in_air and \
                not self._fresh(self.setpoint_time_s, now_s, p["COM_OF_LOSS_T"]):
            self.failsafe_reason = "offboard setpoints lost"
            self._event(mavlink.MAV_SEVERITY_CRITICAL,
                        f"Offboard lost >{p['COM_OF_LOSS_T']:.1f}s: hover, then land")
            self._fs_hover_until_s = now_s + p["BRG_FS_HOVER_T"]
            self.set_mode(FlightMode.LOITER, now_s, "offboard setpoints lost")
        # the board must follow our arm request within a second, else we stop asking
        if self.board_link_ok and self.board_status is not None and bool(self.board_status.armed) != self.armed_cmd:
            if self._arm_mismatch_since_s is None:
                self._arm_mismatch_since_s = now_s
            elif now_s - self._arm_mismatch_since_s > 1.0 and self.armed_cmd:
                self._event(mavlink.MAV_SEVERITY_CRITICAL, "Board did not arm: disarming")
                self._disarm(now_s, "Board did not arm")
                self._arm_mismatch_since_s = None
        else:
            self._arm_mismatch_since_s = None

    # ------------------------------------------------------------------ MAVLink side
    def tick(self, now_s: float) -> list[Outbound]:
        """Periodic telemetry (call at >= 50 Hz) and the STATUSTEXT events of the last steps."""
        out = self._flush_events()
        if self._stream_due(mavlink.MAVLINK_MSG_ID_HEARTBEAT, now_s):
            out.append(Outbound(self.heartbeat()))
        if self._stream_due(mavlink.MAVLINK_MSG_ID_SYS_STATUS, now_s):
            out.append(Outbound(self.sys_status(now_s)))
        if self._stream_due(mavlink.MAVLINK_MSG_ID_SYSTEM_TIME, now_s):
            out.append(Outbound(self.system_time(now_s)))
        if self._stream_due(mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE, now_s):
            out.append(Outbound(self.mav.extended_sys_state_encode(0, self.landed_state())))
        if self._stream_due(mavlink.MAVLINK_MSG_ID_BATTERY_STATUS, now_s):
            out.append(Outbound(self.battery_status()))
        return out

    def _stream_due(self, msg_id: int, now_s: float) -> bool:
        interval = self.stream_interval_s.get(msg_id, -1.0)
        if interval < 0:
            return False
        last = self._stream_last_s.get(msg_id)
        if last is not None and now_s - last < interval - 1e-6 and now_s >= last:
            return False
        # keep the phase (no drift) unless we fell far behind
        self._stream_last_s[msg_id] = now_s if last is None or now_s - last > 2 * interval or now_s < last \
            else last + interval
        return True

    def landed_state(self) -> int:
        if not self.in_air:
            return mavlink.MAV_LANDED_STATE_ON_GROUND
        if self.mode == FlightMode.TAKEOFF:
            return mavlink.MAV_LANDED_STATE_TAKEOFF
        if self.mode == FlightMode.LAND:
            return mavlink.MAV_LANDED_STATE_LANDING
        return mavlink.MAV_LANDED_STATE_IN_AIR

    def heartbeat(self) -> Any:
        base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        if self.armed:
            base |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        if self.failsafe_reason or not self.board_link_ok or \
                (self.board_status is not None and self.board_status.failsafe):
            status = mavlink.MAV_STATE_CRITICAL
        elif self.armed:
            status = mavlink.MAV_STATE_ACTIVE
        else:
            status = mavlink.MAV_STATE_STANDBY
        return self.mav.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_GENERIC, base,
                                         self.mode.custom_mode, status)

    def battery_fraction(self) -> float | None:
        if self.board_status is None:
            return None
        b = self.vehicle.battery
        cell_v = self.board_status.battery_mv / 1000.0 / b.cells
        return min(max((cell_v - b.empty_cell_v) / (b.full_cell_v - b.empty_cell_v), 0.0), 1.0)

    def sys_status(self, now_s: float) -> Any:
        flags = self.board_status.error_flags if self.board_status is not None else 0
        imu_ok = self._fresh(self.imu_time_s, now_s, self.params["BRG_BOARD_LOSS_T"]) \
            and not flags & BoardError.IMU_SATURATED
        board_ok = self.board_link_ok and self.board_status is not None and not self.board_status.failsafe \
            and not flags & BoardError.SETPOINT_TIMEOUT
        # No geofence here (not present, not enabled); its health bit means "not breached", as ArduPilot
        # reports it: left clear, MAVProxy's fence module announces a "fence breach" at connect.
        health = mavlink.MAV_SYS_STATUS_GEOFENCE
        if imu_ok:
            health |= mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO | mavlink.MAV_SYS_STATUS_SENSOR_3D_ACCEL
        if self.odom_ok:
            health |= mavlink.MAV_SYS_STATUS_SENSOR_VISION_POSITION | \
                mavlink.MAV_SYS_STATUS_SENSOR_XY_POSITION_CONTROL | mavlink.MAV_SYS_STATUS_SENSOR_Z_ALTITUDE_CONTROL
        if board_ok:
            health |= mavlink.MAV_SYS_STATUS_SENSOR_ANGULAR_RATE_CONTROL | \
                mavlink.MAV_SYS_STATUS_SENSOR_ATTITUDE_STABILIZATION | mavlink.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
        frac = self.battery_fraction()
        if frac is not None and frac > 0.05 and not flags & BoardError.BATTERY_LOW:
            health |= mavlink.MAV_SYS_STATUS_SENSOR_BATTERY
        voltage_mv = int(self.board_status.battery_mv) if self.board_status is not None else 0xFFFF
        remaining = int(round(frac * 100)) if frac is not None else -1
        c = self.counters
        errors = c["mavlink_bad"] + c["mk_bad"]
        return self.mav.sys_status_encode(SENSORS_PRESENT, SENSORS_PRESENT, health, 0, min(voltage_mv, 0xFFFF), -1,
                                          remaining, 0, min(errors, 0xFFFF), min(c["mavlink_bad"], 0xFFFF),
                                          min(c["mk_bad"], 0xFFFF), min(c["setpoint_rejected"], 0xFFFF),
                                          min(c["odometry_rejected"], 0xFFFF))

    def battery_status(self) -> Any:
        mv = int(self.board_status.battery_mv) if self.board_status is not None else 0xFFFF
        frac = self.battery_fraction()
        voltages = [min(mv, 0xFFFE)] + [0xFFFF] * 9
        return self.mav.battery_status_encode(0, mavlink.MAV_BATTERY_FUNCTION_ALL, mavlink.MAV_BATTERY_TYPE_LIPO,
                                              32767, voltages, -1, -1, -1,
                                              int(round(frac * 100)) if frac is not None else -1)

    def system_time(self, now_s: float) -> Any:
        unix_us = int(self._unix_clock() * 1e6) if self._unix_clock is not None else 0
        return self.mav.system_time_encode(unix_us, int(now_s * 1000) & 0xFFFFFFFF)

    def autopilot_version(self) -> Any:
        major, minor, patch = (int(x) for x in (__version__.split(".") + ["0", "0"])[:3])
        sw = (major << 24) | (minor << 16) | (patch << 8) | 0xFF  # FIRMWARE_VERSION_TYPE_OFFICIAL
        uid = (0x514C << 48) | (self.sysid << 8) | self.compid
        return self.mav.autopilot_version_encode(CAPABILITIES, sw, self.board_version_int, 0, 0,
                                                 [0] * 8, [0] * 8, [0] * 8, 0, 0, uid)

    def param_value(self, name: str) -> Any:
        return self.mav.param_value_encode(name.encode("ascii"), float(self.params[name]),
                                           mavlink.MAV_PARAM_TYPE_REAL32, len(self.params), self.params.index_of(name))

    def _for_us(self, msg: Any) -> bool:
        ts = getattr(msg, "target_system", 0)
        tc = getattr(msg, "target_component", 0)
        return ts in (0, self.sysid) and tc in (0, self.compid)

    def handle_mavlink(self, now_s: float, msg: Any, link: int = 0) -> list[Outbound]:
        """One received message; replies go back to ``link``, events to everyone."""
        mtype = msg.get_type()
        if mtype == "BAD_DATA":
            self.note_malformed("mavlink_bad", now_s, "bad MAVLink data")
            return []
        handler = self._handlers.get(mtype)
        if handler is None:
            return []
        try:
            out = handler(self, now_s, msg, link)
        except (ValueError, TypeError, OverflowError, KeyError, AttributeError) as exc:
            self.note_malformed("mavlink_bad", now_s, f"{mtype}: {exc}")
            return []
        return out + self._flush_events()

    def _on_heartbeat(self, now_s: float, msg: Any, link: int) -> list[Outbound]:
        return []

    def _on_param_request_list(self, now_s: float, msg: Any, link: int) -> list[Outbound]:
        if not self._for_us(msg):
            return []
        return [Outbound(self.param_value(name), link) for name in self.params.names()]

    def _on_param_request_read(self, now_s: float, msg: Any, link: int) -> list[Outbound]:
        if not self._for_us(msg):
            return []
        names = self.params.names()
        if msg.param_index >= 0:
            if msg.param_index >= len(names):
                return []
            name = names[msg.param_index]
        else:
            name = _param_name(msg.param_id)
            if name not in names:
                return []
        return [Outbound(self.param_value(name), link)]

    def _on_param_set(self, now_s: float, msg: Any, link: int) -> list[Outbound]:
        if not self._for_us(msg):
            return []
        name = _param_name(msg.param_id)
        stored = self.params.set(name, float(msg.param_value))
        if stored is None:
            self._event(mavlink.MAV_SEVERITY_WARNING, f"Unknown parameter {name}")
            return []
        log.info("parameter %s = %g", name, stored)
        self.apply_params()
        if name == "MIS_TAKEOFF_ALT" and self.mode != FlightMode.TAKEOFF:
            self.takeoff_target_m = stored
        # the echo goes to every endpoint so every GCS sees the change
        return [Outbound(self.param_value(name))]

    def _on_timesync(self, now_s: float, msg: Any, link: int) -> list[Outbound]:
        if msg.tc1 != 0:
            return []  # a reply to someone else's request
        # timesync v2: tc1 = our time in ns, ts1 echoed so the requester can match its request
        return [Outbound(self.mav.timesync_encode(int(now_s * 1e9), msg.ts1), link)]

    def _on_set_mode(self, now_s: float, msg: Any, link: int) -> list[Outbound]:
        if msg.target_system not in (0, self.sysid):
            return []
        main, sub = (msg.custom_mode >> 16) & 0xFF, (msg.custom_mode >> 24) & 0xFF
        mode = FlightMode.from_px4(main, sub)
        if mode is not None:
            self._request_mode(mode, now_s)
        return []

    def _on_command_long(self, now_s: float, msg: Any, link: int) -> list[Outbound]:
        if not self._for_us(msg):
            return []
        params = (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7)
        return self._command(now_s, msg, link, msg.command, params)

    def _on_command_int(self, now_s: float, msg: Any, link: int) -> list[Outbound]:
        if not self._for_us(msg):
            return []
        params = (msg.param1, msg.param2, msg.param3, msg.param4, float(msg.x), float(msg.y), msg.z)
        return self._command(now_s, msg, link, msg.command, params)

    def _command(self, now_s: float, msg: Any, link: int, command: int, p: tuple[float, ...]) -> list[Outbound]:
        self.counters["commands"] += 1
        result, extra = self.execute_command(now_s, command, p)
        ack = self.mav.command_ack_encode(command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent())
        return [Outbound(ack, link)] + [Outbound(m, link) for m in extra]

    def execute_command(self, now_s: float, command: int, p: tuple[float, ...]) -> tuple[int, list[Any]]:
        """A command's MAV_RESULT and the messages it produces (REQUEST_MESSAGE)."""
        ACCEPTED, DENIED = mavlink.MAV_RESULT_ACCEPTED, mavlink.MAV_RESULT_DENIED
        TEMP = mavlink.MAV_RESULT_TEMPORARILY_REJECTED
        if command == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
            force = _int_param(p[1]) == 21196  # MAVSDK sends NaN for unused params
            if _int_param(p[0]) == 1:
                if not self.board_link_ok:
                    self._event(mavlink.MAV_SEVERITY_CRITICAL, "Arming denied: no board link")
                    return TEMP, []
                if self.board_status is not None and self.board_status.failsafe and not force:
                    self._event(mavlink.MAV_SEVERITY_CRITICAL, "Arming denied: board failsafe")
                    return TEMP, []
                if not self.armed_cmd:
                    self.armed_cmd = True
                    self.in_air = False
                    self.blind = False
                    self.takeoff_phase = None
                    self._blind_descent = None
                    self._z_ground_m = self._odom_z_m if self.odom_ok else None
                    self.height_m = 0.0
                    if self.mode in (FlightMode.LAND, FlightMode.TAKEOFF):
                        self.set_mode(FlightMode.POSCTL, now_s, "armed on the ground")  # else LAND disarms at once
                    self._event(mavlink.MAV_SEVERITY_INFO, "Armed")
                return ACCEPTED, []
            if self.in_air and not force:
                self._event(mavlink.MAV_SEVERITY_WARNING, "Disarm denied: in air (force with 21196)")
                return DENIED, []
            self._disarm(now_s, "Disarmed")
            return ACCEPTED, []
        if command == mavlink.MAV_CMD_DO_SET_MODE:
            mode = self.decode_set_mode(p[0], p[1], p[2])
            if mode is None:
                return mavlink.MAV_RESULT_UNSUPPORTED, []
            return self._request_mode(mode, now_s), []
        if command == mavlink.MAV_CMD_NAV_TAKEOFF:
            height = p[6]
            if math.isfinite(height) and 0.2 <= height <= 50.0:
                self.takeoff_target_m = float(height)  # relative to the take-off point (no AMSL here)
            else:
                self.takeoff_target_m = self.params["MIS_TAKEOFF_ALT"]
            return self._request_mode(FlightMode.TAKEOFF, now_s), []
        if command == mavlink.MAV_CMD_NAV_LAND:
            return self._request_mode(FlightMode.LAND, now_s), []
        if command in (mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES):
            msg_id = _int_param(p[0], -1) if command == mavlink.MAV_CMD_REQUEST_MESSAGE else \
                mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION
            reply = self._message_by_id(msg_id, now_s)
            if reply is None:
                return mavlink.MAV_RESULT_UNSUPPORTED, []
            return ACCEPTED, [reply]
        if command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            msg_id, interval_us = _int_param(p[0], -1), (p[1] if math.isfinite(p[1]) else 0.0)
            if msg_id not in self.stream_interval_s:
                return mavlink.MAV_RESULT_UNSUPPORTED, []
            if interval_us < -0.5:
                self.stream_interval_s[msg_id] = -1.0
            elif interval_us < 0.5:
                self.stream_interval_s[msg_id] = STREAM_DEFAULT_INTERVAL_S[msg_id]
                if self.stream_interval_s[msg_id] < 0:
                    self.stream_interval_s[msg_id] = 1.0 if msg_id not in IMU_STREAMS else 0.02
            else:
                self.stream_interval_s[msg_id] = interval_us * 1e-6
            if msg_id == mavlink.MAVLINK_MSG_ID_HEARTBEAT and self.stream_interval_s[msg_id] < 0:
                self.stream_interval_s[msg_id] = 1.0  # never silence the heartbeat
            return ACCEPTED, []
        self.counters["unsupported_commands"] += 1
        log.info("unsupported command %d", command)
        return mavlink.MAV_RESULT_UNSUPPORTED, []

    @staticmethod
    def decode_set_mode(base_mode: float, custom_main: float, custom_sub: float) -> FlightMode | None:
        """DO_SET_MODE params -> mode: PX4's (main, sub) first, ArduCopter's numbers where unambiguous."""
        if not _int_param(base_mode) & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return None
        main, sub = _int_param(custom_main), _int_param(custom_sub)
        mode = FlightMode.from_px4(main, sub)
        if mode is not None:
            return mode
        if sub == 0 and main not in (PX4_MAIN_ALTCTL, PX4_MAIN_POSCTL, PX4_MAIN_OFFBOARD):
            return ARDUCOPTER_MODES.get(main)
        return None

    def _request_mode(self, mode: FlightMode, now_s: float) -> int:
        TEMP = mavlink.MAV_RESULT_TEMPORARILY_REJECTED
        if mode == FlightMode.OFFBOARD:
            if not self._fresh(self.setpoint_time_s, now_s, SETPOINT_FRESH_FOR_OFFBOARD_S) or \
                    (self._vel_sp is None and self._att_sp is None):
                self._event(mavlink.MAV_SEVERITY_WARNING, "Offboard denied: no setpoint stream")
                return TEMP
            if self._vel_sp is not None and not self.odom_ok:
                self._event(mavlink.MAV_SEVERITY_WARNING, "Offboard denied: no odometry")
                return TEMP
        if mode == FlightMode.TAKEOFF:
            if not self.armed_cmd:
                self._event(mavlink.MAV_SEVERITY_WARNING, "Takeoff denied: not armed")
                return TEMP
            if self.in_air and not self.odom_ok and not self.blind:
                self._event(mavlink.MAV_SEVERITY_WARNING, "Takeoff denied: odometry lost in the air")
                return TEMP
        if mode in HOLD_MODES and self.in_air and self.blind and not self.odom_ok:
            self._event(mavlink.MAV_SEVERITY_WARNING, f"{mode.name} denied: no odometry yet")
            return TEMP
        self.failsafe_reason = None if mode != FlightMode.LAND else self.failsafe_reason
        self._fs_hover_until_s = None
        if mode == self.mode and mode == FlightMode.TAKEOFF:
            return mavlink.MAV_RESULT_ACCEPTED
        self.set_mode(mode, now_s, "requested")
        return mavlink.MAV_RESULT_ACCEPTED

    def _message_by_id(self, msg_id: int, now_s: float) -> Any:
        if msg_id == mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            return self.autopilot_version()
        if msg_id == mavlink.MAVLINK_MSG_ID_HEARTBEAT:
            return self.heartbeat()
        if msg_id == mavlink.MAVLINK_MSG_ID_SYS_STATUS:
            return self.sys_status(now_s)
        if msg_id == mavlink.MAVLINK_MSG_ID_SYSTEM_TIME:
            return self.system_time(now_s)
        if msg_id == mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE:
            return self.mav.extended_sys_state_encode(0, self.landed_state())
        if msg_id == mavlink.MAVLINK_MSG_ID_BATTERY_STATUS:
            return self.battery_status()
        if msg_id == mavlink.MAVLINK_MSG_ID_ATTITUDE:
            e = self.filter.estimate
            return self.mav.attitude_encode(int(now_s * 1000) & 0xFFFFFFFF, e.roll_rad, e.pitch_rad, e.yaw_rad,
                                            e.rollspeed_rad_s, e.pitchspeed_rad_s, e.yawspeed_rad_s)
        return None

    def _on_set_position_target_local_ned(self, now_s: float, msg: Any, link: int) -> list[Outbound]:
        if not self._for_us(msg):
            return []
        tm = msg.type_mask
        velocity = (msg.vx, msg.vy, msg.vz)
        usable = (tm & TM_POSITION) == TM_POSITION and (tm & TM_ACCEL) == TM_ACCEL and not tm & TM_FORCE \
            and not tm & TM_VELOCITY and all(math.isfinite(v) for v in velocity)
        frame = msg.coordinate_frame
        if not usable or frame not in BODY_FRAMES + LOCAL_FRAMES:
            self.counters["setpoint_rejected"] += 1
            if self.counters["setpoint_rejected"] in (1, 10, 100, 1000):
                self._event(mavlink.MAV_SEVERITY_WARNING,
                            f"Setpoint rejected: mask {tm} frame {frame} (velocity only)")
            return []
        yaw_rate = None if tm & TM_YAW_RATE else float(msg.yaw_rate)
        yaw = None if tm & TM_YAW or yaw_rate is not None else float(msg.yaw)
        if yaw_rate is not None and not math.isfinite(yaw_rate):
            yaw_rate = 0.0
        if yaw is not None and not math.isfinite(yaw):
            yaw = None
        v = (float(velocity[0]), float(velocity[1]), float(velocity[2]))
        self._vel_sp = _VelocitySetpoint(v if frame in BODY_FRAMES else None,
                                         v if frame in LOCAL_FRAMES else None, yaw_rate, yaw)
        self._att_sp = None
        self.setpoint_time_s = now_s
        if self.mode == FlightMode.OFFBOARD and self.armed_cmd and not self.in_air and v[2] < -0.1:
            self.in_air = True  # a climb command from the ground takes off
            self._z_ground_m = self._odom_z_m
        return []

    def _on_set_attitude_target(self, now_s: float, msg: Any, link: int) -> list[Outbound]:
        if not self._for_us(msg):
            return []
        tm = msg.type_mask
        q = np.asarray(msg.q, dtype=float)
        if tm & ATM_ATTITUDE:
            roll = pitch = 0.0
            yaw = None
        else:
            if not np.all(np.isfinite(q)) or abs(np.linalg.norm(q) - 1.0) > 0.1:
                self.counters["setpoint_rejected"] += 1
                return []
            roll, pitch, yaw_q = euler_from_R(R_from_quat_wxyz(q / np.linalg.norm(q)))
            yaw = yaw_q
        yaw_rate = None if tm & ATM_YAW_RATE else float(msg.body_yaw_rate)
        if yaw_rate is not None:
            yaw = None
        thrust = None if tm & ATM_THRUST else float(msg.thrust)
        if thrust is not None and not math.isfinite(thrust):
            self.counters["setpoint_rejected"] += 1
            return []
        self._att_sp = _AttitudeSetpoint(float(roll), float(pitch), yaw_rate, yaw, thrust)
        self._vel_sp = None
        self.setpoint_time_s = now_s
        if self.mode == FlightMode.OFFBOARD and self.armed_cmd and not self.in_air and thrust is not None \
                and thrust > 0.5 * self.tracker.hover_thrust_fraction:
            self.in_air = True
        return []

    def _on_odometry(self, now_s: float, msg: Any, link: int) -> list[Outbound]:
        q = np.asarray(msg.q, dtype=float)
        v = np.array([msg.vx, msg.vy, msg.vz], dtype=float)
        if not np.all(np.isfinite(v)) or msg.frame_id not in ODOM_WORLD_FRAMES or \
                msg.child_frame_id not in ODOM_BODY_FRAMES + ODOM_WORLD_FRAMES:
            self.counters["odometry_rejected"] += 1
            if self.counters["odometry_rejected"] in (1, 10, 100, 1000):
                self._event(mavlink.MAV_SEVERITY_WARNING,
                            f"Odometry rejected: frames {msg.frame_id}/{msg.child_frame_id}")
            return []
        if getattr(msg, "quality", 0) < self.params["BRG_ODOM_QMIN"]:
            # the companion's "failed" (0; MAVLink's -1): not a velocity source, it simply does not refresh
            self.counters["odometry_low_quality"] += 1
            return []
        est = self.filter.estimate
        roll, pitch, yaw = est.roll_rad, est.pitch_rad, est.yaw_rad
        if np.all(np.isfinite(q)) and abs(np.linalg.norm(q) - 1.0) < 0.1:
            roll, pitch, yaw = euler_from_R(R_from_quat_wxyz(q / np.linalg.norm(q)))
            self.filter.set_yaw(yaw)  # anchor the heading to the companion's local frame
        if msg.child_frame_id in ODOM_BODY_FRAMES:
            v_h = R_hq(roll, pitch) @ v  # body FRD -> H (paper 000: H is yaw-aligned, level)
        else:
            v_h = Rz(-yaw) @ v  # local NED -> H
        self._v_h_odom = v_h
        self._dv_h_imu[:] = 0.0
        self._vz_dead_reckoned = float(v_h[2])
        z = float(msg.z) if math.isfinite(msg.z) else None
        reset = self._odom_reset_counter is not None and msg.reset_counter != self._odom_reset_counter
        self._odom_reset_counter = int(msg.reset_counter)
        if self.in_air and z is not None and (self.blind or reset or self._z_ground_m is None):
            # the odometry's frame began (or was reset) in the air: anchor it so the height stays continuous
            self._z_ground_m = z + self.height_m
        self._odom_z_m = z
        self.odom_time_s = now_s
        if not self.odom_ok:
            self.odom_ok = True
            self._odometry_ok_event()
        if self.blind and self.in_air:
            self.blind = False
            if self.mode == FlightMode.TAKEOFF:
                self.takeoff_phase = TakeoffPhase.CLOSED_LOOP
            self._event(mavlink.MAV_SEVERITY_INFO, f"Odometry at {self.height_m:.2f} m: closed loop")
        return []

    _handlers: dict[str, Any] = {
        "HEARTBEAT": _on_heartbeat,
        "PARAM_REQUEST_LIST": _on_param_request_list,
        "PARAM_REQUEST_READ": _on_param_request_read,
        "PARAM_SET": _on_param_set,
        "TIMESYNC": _on_timesync,
        "SET_MODE": _on_set_mode,
        "COMMAND_LONG": _on_command_long,
        "COMMAND_INT": _on_command_int,
        "SET_POSITION_TARGET_LOCAL_NED": _on_set_position_target_local_ned,
        "SET_ATTITUDE_TARGET": _on_set_attitude_target,
        "ODOMETRY": _on_odometry,
    }


def _int_param(value: float, default: int = 0) -> int:
    """A command parameter as an integer; NaN/inf (MAVLink's "unused") -> ``default``."""
    return int(round(value)) if math.isfinite(value) else default


def _param_name(raw: Any) -> str:
    if isinstance(raw, bytes):
        raw = raw.decode("ascii", "replace")
    return str(raw).split("\x00", 1)[0]

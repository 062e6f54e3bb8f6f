"""The MAVLink autopilot facade: one pure state machine (no sockets, no threads, no wall clock) made of
services, one module each, over one shared state.

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

Where things live:

==============================  ===================================================================
:mod:`firmware_bridge.state`    the state (:class:`~firmware_bridge.state.BridgeState`), BoardCommand, Outbound
:mod:`firmware_bridge.modes`    FlightMode from :mod:`quadlink.px4_modes`, ArduCopter numbers, DO_SET_MODE
:mod:`firmware_bridge.streams`  stream intervals, SET_MESSAGE_INTERVAL bounds
:mod:`firmware_bridge.telemetry`  HEARTBEAT, SYS_STATUS, the IMU streams, messages on request
:mod:`firmware_bridge.offboard`   setpoints, odometry and IMU -> velocity in H
:mod:`firmware_bridge.connect`  protocol version, REQUEST_MESSAGE, TIMESYNC, mission and FTP answers (ground stations)
:mod:`firmware_bridge.commander`  arming, commands, mode requests, failsafes
:mod:`firmware_bridge.flight_control`  the 100 Hz step, blind take-off, heading hold, touchdown
:mod:`quadlink.mavlink.param_service`  PARAM_* (shared with the companion), bounds in :mod:`firmware_bridge.params`
==============================  ===================================================================

Every service is an object holding the one :class:`~firmware_bridge.state.BridgeState` and, passed to its
constructor, the services it uses; the dependencies run one way (telemetry and offboard use no other service,
connect uses telemetry and the parameter service, the commander uses offboard and connect, flight control uses
the commander and offboard). :class:`Autopilot` builds them, routes each MAVLink message to its service and
applies parameter changes; its attributes (``mode``, ``armed_cmd``, ``counters``, ``tracker``...) are the
state's, read and written through :class:`_Shared`. One unexpected exception in one message's handler is caught,
counted (``handler_errors``) and logged at most every few seconds: it never ends the daemon's loop.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from typing import Any, Generic, TypeVar, overload

import numpy as np

from firmware_bridge.attitude_filter import BridgeAttitude
from firmware_bridge.commander import CommanderService
from firmware_bridge.connect import MISSION_MESSAGES, ConnectService
from firmware_bridge.flight_control import FlightControlService
from firmware_bridge.geometric_tracker import GeometricTracker
from firmware_bridge.modes import FlightMode, TakeoffPhase, decode_set_mode
from firmware_bridge.offboard import OffboardService
from firmware_bridge.params import ParamTable
from firmware_bridge.state import BoardCommand, BoardStatusLike, BridgeState, NonFiniteCommand, Outbound
from firmware_bridge.telemetry import CAPABILITIES, TelemetryService
from firmware_bridge.velocity_tracker import AttitudeCommand, VelocityTracker
from firmware_bridge.vertical_estimator import VerticalEstimator
from quadlink.mavlink import mavlink
from quadlink.mavlink.param_service import ParamService
from quadlink.vehicle import VehicleConfig

log = logging.getLogger(__name__)

__all__ = ["Autopilot", "BoardCommand", "CAPABILITIES", "FlightMode", "NonFiniteCommand", "Outbound",
           "TakeoffPhase"]

_Handler = Callable[[float, Any, int], list[Outbound]]
# a broken message (a field of the wrong type, a value out of a codec's range) is malformed input
_MALFORMED = (ValueError, TypeError, OverflowError, KeyError, AttributeError, IndexError)
_T = TypeVar("_T")


class _Shared(Generic[_T]):
    """An attribute of the facade that is the shared state's attribute of the same name (read and written)."""

    def __set_name__(self, owner: type, name: str) -> None:
        self.name = name

    @overload
    def __get__(self, obj: None, objtype: type | None = None) -> _Shared[_T]: ...
    @overload
    def __get__(self, obj: Autopilot, objtype: type | None = None) -> _T: ...

    def __get__(self, obj: Autopilot | None, objtype: type | None = None) -> _T | _Shared[_T]:
        return self if obj is None else getattr(obj.state, self.name)

    def __set__(self, obj: Autopilot, value: _T) -> None:
        setattr(obj.state, self.name, value)


class Autopilot:
    """The bridge's MAVLink autopilot (see the module docstring)."""

    # the state as the daemon, the tests and the tools read it
    params = _Shared[ParamTable]()
    mav = _Shared[mavlink.MAVLink]()
    mode = _Shared[FlightMode]()
    armed_cmd = _Shared[bool]()
    armed = _Shared[bool]()          # read only: the board's word when it talks (BridgeState.armed)
    in_air = _Shared[bool]()
    blind = _Shared[bool]()
    takeoff_phase = _Shared[TakeoffPhase | None]()
    takeoff_target_m = _Shared[float]()
    failsafe_reason = _Shared[str | None]()
    odom_ok = _Shared[bool]()
    board_link_ok = _Shared[bool]()
    board_status = _Shared[BoardStatusLike | None]()
    board_version = _Shared[str | None]()
    counters = _Shared[dict[str, int]]()
    stream_interval_s = _Shared[dict[int, float]]()
    tracker = _Shared[VelocityTracker | GeometricTracker]()
    pid_tracker = _Shared[VelocityTracker]()
    filter = _Shared[BridgeAttitude]()
    vertical = _Shared[VerticalEstimator]()
    last_command = _Shared[AttitudeCommand | None]()
    last_board_command = _Shared[BoardCommand]()

    def __init__(self, vehicle: VehicleConfig, params: ParamTable, sysid: int = 1, compid: int = 1,
                 unix_clock: Callable[[], float] | None = None) -> None:
        self.state = BridgeState(vehicle, params, sysid, compid, unix_clock)
        self.param_service = ParamService(params, self.state.mav, sysid, compid)
        self.telemetry = TelemetryService(self.state)
        self.offboard = OffboardService(self.state)
        self.connect = ConnectService(self.state, self.telemetry, self.param_service)
        self.commander = CommanderService(self.state, self.offboard, self.connect)
        self.flight_control = FlightControlService(self.state, self.commander, self.offboard)
        self._handlers: dict[str, _Handler] = {
            "HEARTBEAT": self.connect.on_heartbeat,
            "PARAM_REQUEST_LIST": self._on_param,
            "PARAM_REQUEST_READ": self._on_param,
            "PARAM_SET": self._on_param,
            "TIMESYNC": self.connect.on_timesync,
            "SET_MODE": self.commander.on_set_mode,
            "COMMAND_LONG": self.commander.on_command_long,
            "COMMAND_INT": self.commander.on_command_int,
            "SET_POSITION_TARGET_LOCAL_NED": self.offboard.on_set_position_target_local_ned,
            "SET_ATTITUDE_TARGET": self.offboard.on_set_attitude_target,
            "ODOMETRY": self.offboard.on_odometry,
            "FILE_TRANSFER_PROTOCOL": self.connect.on_ftp,
            **{name: self.connect.on_mission for name in MISSION_MESSAGES},
        }

    # ------------------------------------------------------------------ inputs (the daemon's calls)
    def on_imu(self, now_s: float, time_usec: int, accel_q_m_s2: np.ndarray,
               gyro_q_rad_s: np.ndarray) -> list[Outbound]:
        """One IMU sample (SI, body FRD) at board time ``time_usec``; returns its telemetry."""
        est = self.offboard.on_imu(now_s, time_usec, accel_q_m_s2, gyro_q_rad_s)
        return self.telemetry.imu_streams(now_s, int(time_usec), est)

    def control_step(self, now_s: float) -> BoardCommand:
        """The 100 Hz step (:meth:`FlightControlService.control_step`): the board's next setpoint."""
        return self.flight_control.control_step(now_s)

    def on_board_status(self, now_s: float, status: BoardStatusLike) -> list[Outbound]:
        return self.commander.on_board_status(now_s, status)

    def on_board_baro(self, altitude_m: float, valid: bool, climb_m_s: float = math.nan) -> None:
        """The board's barometric altitude and climb rate (``Z`` frame, m and m/s, + up): fused into the vertical
        estimate that the blind flight (no odometry, no companion) descends on; the climb rate says when a landing's
        descent has stopped below the floor the drifted altitude reads."""
        self.state.vertical.on_baro(altitude_m, valid, climb_m_s)
        self.state.baro_frames += 1

    def on_board_version(self, text: str, version_int: int = 0) -> None:
        self.commander.on_board_version(text, version_int)

    def tick(self, now_s: float) -> list[Outbound]:
        """Periodic telemetry (call at >= 50 Hz) and the STATUSTEXT events of the last steps."""
        return self.telemetry.tick(now_s)

    def note_malformed(self, kind: str, now_s: float, detail: str = "") -> None:
        """Count bad input (``mavlink_bad`` or ``mk_bad``); log at most once every 5 s."""
        self.state.note_malformed(kind, now_s, detail)

    def handle_mavlink(self, now_s: float, msg: Any, link: int = 0) -> list[Outbound]:
        """One received message; replies go back to ``link``, events to everyone. Never raises."""
        mtype = msg.get_type()
        if mtype == "BAD_DATA":
            self.state.note_malformed("mavlink_bad", now_s, "bad MAVLink data")
            return []
        handler = self._handlers.get(mtype)
        if handler is None:
            return []
        try:
            out = handler(now_s, msg, link)
        except _MALFORMED as exc:
            self.state.note_malformed("mavlink_bad", now_s, f"{mtype}: {exc}")
            return []
        except Exception as exc:  # noqa: BLE001 - one message's bug must not end the flight loop (issue 16)
            self.state.note_malformed("handler_errors", now_s, f"{mtype}: {type(exc).__name__}: {exc}")
            return []
        return out + self.state.flush_events()

    # ------------------------------------------------------------------ read-outs
    def heartbeat(self) -> Any:
        return self.telemetry.heartbeat()

    def sys_status(self, now_s: float) -> Any:
        return self.telemetry.sys_status(now_s)

    def landed_state(self) -> int:
        return self.telemetry.landed_state()

    def v_est_h(self, now_s: float) -> np.ndarray:
        """Velocity in H (:meth:`OffboardService.v_est_h`)."""
        return self.offboard.v_est_h(now_s)

    @staticmethod
    def decode_set_mode(base_mode: float, custom_main: float, custom_sub: float) -> FlightMode | None:
        """DO_SET_MODE params -> mode (:func:`firmware_bridge.modes.decode_set_mode`)."""
        return decode_set_mode(base_mode, custom_main, custom_sub)

    # ------------------------------------------------------------------ parameters (the shared service)
    def apply_params(self) -> None:
        s = self.state
        s.pid_tracker.set_gains(s.params.tracker_gains())
        s.tracker.set_gains(s.params.tracker_gains())
        if isinstance(s.tracker, GeometricTracker):
            s.tracker.set_geometric_gains(s.params.geometric_gains())
        s.apply_tracker_selection()
        s.filter.set_tau(s.params["BRG_ATT_TAU"])
        s.vertical.max_climb_m_s = s.params["MPC_Z_VEL_MAX_UP"]
        s.vertical.max_descent_m_s = s.params["MPC_Z_VEL_MAX_DN"]

    def param_value(self, name: str) -> Any:
        return self.param_service.param_value(name)

    def _on_param(self, now_s: float, msg: Any, link: int) -> list[Outbound]:
        s = self.state
        reply = self.param_service.handle(now_s, msg)
        for severity, text in reply.events:
            s.event(severity, text)
        if reply.refused:
            s.counters["param_refused"] += 1
        if reply.changed is not None:
            self.apply_params()
            if reply.changed == "MIS_TAKEOFF_ALT" and s.mode != FlightMode.TAKEOFF:
                s.takeoff_target_m = s.params["MIS_TAKEOFF_ALT"]
        return [Outbound(m, link) for m in reply.to_sender] + [Outbound(m) for m in reply.to_all]

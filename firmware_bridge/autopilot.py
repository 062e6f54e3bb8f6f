"""The MAVLink autopilot facade: one pure state machine (no sockets, no threads, no wall clock) composed of
services, one module each.

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
:mod:`firmware_bridge.telemetry`  HEARTBEAT, SYS_STATUS, the IMU streams
:mod:`firmware_bridge.offboard`   setpoints, odometry and IMU -> velocity in H
:mod:`firmware_bridge.commander`  arming, commands, mode requests, failsafes
:mod:`firmware_bridge.flight_control`  the 100 Hz step, blind take-off, heading hold, touchdown
:mod:`firmware_bridge.connect`  protocol version, REQUEST_MESSAGE, mission and FTP answers (ground stations)
:mod:`quadlink.mavlink.param_service`  PARAM_* (shared with the companion), bounds in :mod:`firmware_bridge.params`
==============================  ===================================================================

The services are mixins layered in dependency order (telemetry < offboard < commander < flight control < connect),
all over the one :class:`~firmware_bridge.state.BridgeState`; this class adds the MAVLink dispatch and
the parameter service. One unexpected exception in one message's handler is caught, counted
(``handler_errors``) and logged at most every few seconds: it never ends the daemon's loop.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

from firmware_bridge.connect import MISSION_MESSAGES, ConnectService
from firmware_bridge.geometric_tracker import GeometricTracker
from firmware_bridge.modes import FlightMode, TakeoffPhase
from firmware_bridge.params import ParamTable
from firmware_bridge.state import BoardCommand, NonFiniteCommand, Outbound
from firmware_bridge.telemetry import CAPABILITIES
from quadlink.mavlink.param_service import ParamService
from quadlink.vehicle import VehicleConfig

log = logging.getLogger(__name__)

__all__ = ["Autopilot", "BoardCommand", "CAPABILITIES", "FlightMode", "NonFiniteCommand", "Outbound",
           "TakeoffPhase"]

_Handler = Callable[["Autopilot", float, Any, int], list[Outbound]]
# a broken message (a field of the wrong type, a value out of a codec's range) is malformed input
_MALFORMED = (ValueError, TypeError, OverflowError, KeyError, AttributeError, IndexError)


class Autopilot(ConnectService):
    """The bridge's MAVLink autopilot (see the module docstring)."""

    def __init__(self, vehicle: VehicleConfig, params: ParamTable, sysid: int = 1, compid: int = 1,
                 unix_clock: Callable[[], float] | None = None) -> None:
        super().__init__(vehicle, params, sysid, compid, unix_clock)
        self.param_service = ParamService(params, self.mav, sysid, compid)

    def apply_params(self) -> None:
        self.pid_tracker.set_gains(self.params.tracker_gains())
        self.tracker.set_gains(self.params.tracker_gains())
        if isinstance(self.tracker, GeometricTracker):
            self.tracker.set_geometric_gains(self.params.geometric_gains())
        self.apply_tracker_selection()
        self.filter.set_tau(self.params["BRG_ATT_TAU"])
        self.vertical.max_climb_m_s = self.params["MPC_Z_VEL_MAX_UP"]
        self.vertical.max_descent_m_s = self.params["MPC_Z_VEL_MAX_DN"]

    def param_value(self, name: str) -> Any:
        return self.param_service.param_value(name)

    def handle_mavlink(self, now_s: float, msg: Any, link: int = 0) -> list[Outbound]:
        """One received message; replies go back to ``link``, events to everyone. Never raises."""
        mtype = msg.get_type()
        if mtype == "BAD_DATA":
            self.note_malformed("mavlink_bad", now_s, "bad MAVLink data")
            return []
        handler = self._handlers.get(mtype)
        if handler is None:
            return []
        try:
            out = handler(self, now_s, msg, link)
        except _MALFORMED as exc:
            self.note_malformed("mavlink_bad", now_s, f"{mtype}: {exc}")
            return []
        except Exception as exc:  # noqa: BLE001 - one message's bug must not end the flight loop (issue 16)
            self.note_malformed("handler_errors", now_s, f"{mtype}: {type(exc).__name__}: {exc}")
            return []
        return out + self.flush_events()

    def _on_param(self, now_s: float, msg: Any, link: int) -> list[Outbound]:
        reply = self.param_service.handle(now_s, msg)
        for severity, text in reply.events:
            self.event(severity, text)
        if reply.refused:
            self.counters["param_refused"] += 1
        if reply.changed is not None:
            self.apply_params()
            if reply.changed == "MIS_TAKEOFF_ALT" and self.mode != FlightMode.TAKEOFF:
                self.takeoff_target_m = self.params["MIS_TAKEOFF_ALT"]
        return [Outbound(m, link) for m in reply.to_sender] + [Outbound(m) for m in reply.to_all]

    _handlers: dict[str, _Handler] = {
        "HEARTBEAT": ConnectService._on_heartbeat,
        "PARAM_REQUEST_LIST": _on_param,
        "PARAM_REQUEST_READ": _on_param,
        "PARAM_SET": _on_param,
        "TIMESYNC": ConnectService._on_timesync,
        "SET_MODE": ConnectService._on_set_mode,
        "COMMAND_LONG": ConnectService._on_command_long,
        "COMMAND_INT": ConnectService._on_command_int,
        "SET_POSITION_TARGET_LOCAL_NED": ConnectService._on_set_position_target_local_ned,
        "SET_ATTITUDE_TARGET": ConnectService._on_set_attitude_target,
        "ODOMETRY": ConnectService._on_odometry,
        "FILE_TRANSFER_PROTOCOL": ConnectService._on_ftp,
        **{name: ConnectService._on_mission for name in MISSION_MESSAGES},
    }

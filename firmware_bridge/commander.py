"""Commander service: arming, commands, mode requests, link and setpoint failsafes (pure; time as argument).

COMMAND_LONG / COMMAND_INT are acked at once to the sender. MAVLink's NaN = "unused" convention is applied
per command, as PX4 does: ARM_DISARM needs param1 exactly 0 or 1 (NaN never means disarm) and param2 the
exact force magic; NAV_TAKEOFF's NaN height means "the parameter"; SET_MESSAGE_INTERVAL is bounded by
:mod:`firmware_bridge.streams`. The failsafes (board link, odometry, offboard setpoints) run in
:meth:`CommanderService._check_links`, called by the 100 Hz control step.
"""

from __future__ import annotations

import logging
import math
from typing import Any

from firmware_bridge.modes import HOLD_MODES, FlightMode, TakeoffPhase, decode_set_mode, int_param
from firmware_bridge.offboard import OffboardService
from firmware_bridge.state import BoardStatusLike, Outbound
from quadlink.mavlink import mavlink
from quadlink.mk.flags import BoardFlightState

log = logging.getLogger("firmware_bridge.autopilot")

SETPOINT_FRESH_FOR_OFFBOARD_S = 0.5  # PX4 wants the stream running before the switch
FORCE_ARM_DISARM_MAGIC = 21196.0  # ARM_DISARM param2: force (PX4, ArduPilot)
ARM_FOLLOW_TIMEOUT_S = 1.0  # the board must follow an arm request within this, else we stop asking
TAKEOFF_HEIGHT_RANGE_M = (0.2, 50.0)  # NAV_TAKEOFF param7 accepted as a height above the take-off point


class CommanderService(OffboardService):
    """Arming, commands, modes and failsafes over the shared :class:`BridgeState`."""

    def set_mode(self, mode: FlightMode, now_s: float, reason: str = "") -> None:
        if mode == self.mode:
            return
        log.info("mode %s -> %s%s", self.mode.name, mode.name, f" ({reason})" if reason else "")
        self.mode = mode
        self.touchdown_since_s = None
        if mode == FlightMode.TAKEOFF:
            self._start_takeoff(now_s)

    def _start_takeoff(self, now_s: float) -> None:
        was_in_air, self.in_air = self.in_air, True
        self.takeoff_start_s = now_s   # BRG_TKO_OL_T counts from here (a loss in the climb re-enters phase 1)
        self.tko_climbed_m = self.height_m if was_in_air else 0.0
        self.tko_disagree_told = False
        if self.odom_ok:
            self.takeoff_phase = TakeoffPhase.CLOSED_LOOP
            if self.z_ground_m is None:
                self.z_ground_m = self.odom_z_m
            self.event(mavlink.MAV_SEVERITY_INFO, f"Takeoff to {self.takeoff_target_m:.1f} m")
            return
        # phase 1: the camera cannot see yet; climb level on the accelerometer until odometry arrives
        self.takeoff_phase = TakeoffPhase.OPEN_LOOP
        self.blind = True
        self.hover_thrust_learned = None
        self.blind_descent = None
        if not was_in_air:
            self.vertical.reset_ground()
        self.z_ground_m = None
        self.height_m = self.vertical.height_m
        self.event(mavlink.MAV_SEVERITY_INFO, f"Takeoff to {self.takeoff_target_m:.1f} m, open loop until odometry")

    def on_board_status(self, now_s: float, status: BoardStatusLike) -> list[Outbound]:
        prev = self.board_status
        self.board_status = status
        self.board_status_time_s = now_s
        if not self.board_link_ok:
            self.board_link_ok = True
            self.event(mavlink.MAV_SEVERITY_INFO, "Board link up")
        if status.failsafe and not self.board_failsafe_reported:
            self.board_failsafe_reported = True
            self.event(mavlink.MAV_SEVERITY_CRITICAL, f"Board failsafe (flags 0x{status.error_flags:x})")
        elif not status.failsafe:
            self.board_failsafe_reported = False
        if prev is not None and bool(prev.armed) != bool(status.armed):
            self.event(mavlink.MAV_SEVERITY_INFO, "Board armed" if status.armed else "Board disarmed")
        if status.flight_state == BoardFlightState.FLYING and self.armed_cmd:
            self.in_air = True
        return self.flush_events()

    def on_board_version(self, text: str, version_int: int = 0) -> None:
        self.board_version = text
        self.board_version_int = version_int
        log.info("board firmware: %s", text)

    def _disarm(self, now_s: float, why: str) -> None:
        if self.armed_cmd:
            self.event(mavlink.MAV_SEVERITY_INFO, why)
        self.armed_cmd = False
        self.in_air = False
        self.failsafe_reason = None
        self.fs_hover_until_s = None
        self.z_ground_m = None
        self.height_m = 0.0
        self.blind = False
        self.takeoff_phase = None
        self.blind_descent = None
        self.reset_trackers()

    def _check_links(self, now_s: float) -> None:
        p = self.params
        board_fresh = self.fresh(self.board_status_time_s, now_s, p["BRG_BOARD_LOSS_T"]) or \
            self.fresh(self.imu_time_s, now_s, p["BRG_BOARD_LOSS_T"])
        if self.board_link_ok and not board_fresh:
            self.board_link_ok = False
            self.event(mavlink.MAV_SEVERITY_CRITICAL, "Board link lost")
            self.failsafe_reason = "board link lost"
        odom_fresh = self.fresh(self.odom_time_s, now_s, p["BRG_ODOM_LOSS_T"])
        if self.odom_ok and not odom_fresh:
            self.odom_ok = False
            if self.in_air and self.mode == FlightMode.TAKEOFF and self.height_m < p["BRG_TKO_OL_ALT"]:
                # low in the climb the camera may lose the floor (too near, too fast): as if it had never
                # seen it, climb open loop until odometry returns, within BRG_TKO_OL_ALT / BRG_TKO_OL_T
                self.event(mavlink.MAV_SEVERITY_WARNING,
                            f"Odometry lost at {self.height_m:.2f} m in takeoff: open loop until odometry")
                stale_s = now_s - self.odom_time_s if self.odom_time_s is not None else 0.0
                self.height_m -= self.vz_dead_reckoned * max(stale_s, 0.0)  # the climb since the last odometry
                self.vertical.align(self.height_m, self.vz_dead_reckoned)
                self.takeoff_phase = TakeoffPhase.OPEN_LOOP
                self.blind = True
            elif self.in_air:
                self.event(mavlink.MAV_SEVERITY_CRITICAL, "Odometry lost: level hold, descending")
                self.failsafe_reason = "odometry lost"
                self.vz_dead_reckoned = float(self.v_est_h(now_s)[2])
                self.set_mode(FlightMode.LAND, now_s, "odometry lost")
            else:
                log.info("odometry lost (on the ground: nothing depends on it)")  # the health bit says it
        elif odom_fresh and not self.odom_ok:
            self.odom_ok = True
            self._odometry_ok_event()
        if self.mode == FlightMode.OFFBOARD and self.in_air and \
                not self.fresh(self.setpoint_time_s, now_s, p["COM_OF_LOSS_T"]):
            self.failsafe_reason = "offboard setpoints lost"
            self.event(mavlink.MAV_SEVERITY_CRITICAL,
                        f"Offboard lost >{p['COM_OF_LOSS_T']:.1f}s: hover, then land")
            self.fs_hover_until_s = now_s + p["BRG_FS_HOVER_T"]
            self.set_mode(FlightMode.LOITER, now_s, "offboard setpoints lost")
        # the board must follow our arm request within a second, else we stop asking
        if self.board_link_ok and self.board_status is not None and bool(self.board_status.armed) != self.armed_cmd:
            if self.arm_mismatch_since_s is None:
                self.arm_mismatch_since_s = now_s
            elif now_s - self.arm_mismatch_since_s > ARM_FOLLOW_TIMEOUT_S and self.armed_cmd:
                self.event(mavlink.MAV_SEVERITY_CRITICAL, "Board did not arm: disarming")
                self._disarm(now_s, "Board did not arm")
                self.arm_mismatch_since_s = None
        else:
            self.arm_mismatch_since_s = None

    def _on_set_mode(self, now_s: float, msg: Any, link: int) -> list[Outbound]:
        if msg.target_system not in (0, self.sysid):
            return []
        mode = FlightMode.from_custom_mode(msg.custom_mode)
        if mode is not None:
            self._request_mode(mode, now_s)
        return []

    def _on_command_long(self, now_s: float, msg: Any, link: int) -> list[Outbound]:
        if not self.for_us(msg):
            return []
        params = (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7)
        return self._command(now_s, msg, link, msg.command, params)

    def _on_command_int(self, now_s: float, msg: Any, link: int) -> list[Outbound]:
        if not self.for_us(msg):
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
            # param1 must be exactly 0 or 1: NaN is MAVLink's "unused", never "disarm" (issue 16)
            if p[0] not in (0.0, 1.0):
                self.counters["commands_refused"] += 1
                self.event(mavlink.MAV_SEVERITY_WARNING, f"Arm/disarm refused: param1 {p[0]!r}")
                return DENIED, []
            force = p[1] == FORCE_ARM_DISARM_MAGIC  # NaN (MAVSDK's unused) is not the magic number
            if p[0] == 1.0:
                if not self.board_link_ok:
                    self.event(mavlink.MAV_SEVERITY_CRITICAL, "Arming denied: no board link")
                    return TEMP, []
                if self.board_status is not None and self.board_status.failsafe and not force:
                    self.event(mavlink.MAV_SEVERITY_CRITICAL, "Arming denied: board failsafe")
                    return TEMP, []
                if not self.armed_cmd:
                    self.armed_cmd = True
                    self.in_air = False
                    self.blind = False
                    self.takeoff_phase = None
                    self.blind_descent = None
                    self.z_ground_m = self.odom_z_m if self.odom_ok else None
                    self.height_m = 0.0
                    if self.mode in (FlightMode.LAND, FlightMode.TAKEOFF):
                        self.set_mode(FlightMode.POSCTL, now_s, "armed on the ground")  # else LAND disarms at once
                    self.event(mavlink.MAV_SEVERITY_INFO, "Armed")
                return ACCEPTED, []
            if self.in_air and not force:
                self.event(mavlink.MAV_SEVERITY_WARNING, "Disarm denied: in air (force with 21196)")
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
            if math.isfinite(height) and TAKEOFF_HEIGHT_RANGE_M[0] <= height <= TAKEOFF_HEIGHT_RANGE_M[1]:
                self.takeoff_target_m = float(height)  # relative to the take-off point (no AMSL here)
            else:
                self.takeoff_target_m = self.params["MIS_TAKEOFF_ALT"]
            return self._request_mode(FlightMode.TAKEOFF, now_s), []
        if command == mavlink.MAV_CMD_NAV_LAND:
            return self._request_mode(FlightMode.LAND, now_s), []
        if command in (mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES):
            msg_id = int_param(p[0], -1) if command == mavlink.MAV_CMD_REQUEST_MESSAGE else \
                mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION
            reply = self._message_by_id(msg_id, now_s)
            if reply is None:
                return mavlink.MAV_RESULT_UNSUPPORTED, []
            return ACCEPTED, [reply]
        if command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            result = self.streams.set_interval(p[0], p[1])
            if result == mavlink.MAV_RESULT_DENIED:
                self.counters["commands_refused"] += 1
                self.event(mavlink.MAV_SEVERITY_WARNING, f"Message interval refused: {p[0]!r} {p[1]!r} us")
            return result, []
        self.counters["unsupported_commands"] += 1
        log.info("unsupported command %d", command)
        return mavlink.MAV_RESULT_UNSUPPORTED, []

    @staticmethod
    def decode_set_mode(base_mode: float, custom_main: float, custom_sub: float) -> FlightMode | None:
        """DO_SET_MODE params -> mode (:func:`firmware_bridge.modes.decode_set_mode`)."""
        return decode_set_mode(base_mode, custom_main, custom_sub)

    def _request_mode(self, mode: FlightMode, now_s: float) -> int:
        TEMP = mavlink.MAV_RESULT_TEMPORARILY_REJECTED
        if mode == FlightMode.OFFBOARD:
            if not self.fresh(self.setpoint_time_s, now_s, SETPOINT_FRESH_FOR_OFFBOARD_S) or \
                    (self.vel_sp is None and self.att_sp is None):
                self.event(mavlink.MAV_SEVERITY_WARNING, "Offboard denied: no setpoint stream")
                return TEMP
            if self.vel_sp is not None and not self.odom_ok:
                self.event(mavlink.MAV_SEVERITY_WARNING, "Offboard denied: no odometry")
                return TEMP
        if mode == FlightMode.TAKEOFF:
            if not self.armed_cmd:
                self.event(mavlink.MAV_SEVERITY_WARNING, "Takeoff denied: not armed")
                return TEMP
            if self.in_air and not self.odom_ok and not self.blind:
                self.event(mavlink.MAV_SEVERITY_WARNING, "Takeoff denied: odometry lost in the air")
                return TEMP
        if mode in HOLD_MODES and self.in_air and self.blind and not self.odom_ok:
            self.event(mavlink.MAV_SEVERITY_WARNING, f"{mode.name} denied: no odometry yet")
            return TEMP
        self.failsafe_reason = None if mode != FlightMode.LAND else self.failsafe_reason
        self.fs_hover_until_s = None
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

    def _on_timesync(self, now_s: float, msg: Any, link: int) -> list[Outbound]:
        if msg.tc1 != 0:
            return []  # a reply to someone else's request
        # timesync v2: tc1 = our time in ns, ts1 echoed so the requester can match its request
        return [Outbound(self.mav.timesync_encode(int(now_s * 1e9), msg.ts1), link)]

    def _on_heartbeat(self, now_s: float, msg: Any, link: int) -> list[Outbound]:
        return []

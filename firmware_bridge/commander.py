"""Commander service: arming, commands, mode requests, link and setpoint failsafes (pure; time as argument).

COMMAND_LONG / COMMAND_INT are acked at once to the sender. MAVLink's NaN = "unused" convention is applied
per command, as PX4 does: ARM_DISARM needs param1 exactly 0 or 1 (NaN never means disarm) and param2 the
exact force magic; NAV_TAKEOFF's NaN height means "the parameter"; SET_MESSAGE_INTERVAL is bounded by
:mod:`firmware_bridge.streams`. The failsafes (board link, odometry, offboard setpoints) run in
:meth:`CommanderService.check_links`, called by the 100 Hz control step. The requests a ground station makes on
connect (REQUEST_MESSAGE, protocol version, capabilities) are answered by :mod:`~firmware_bridge.connect`.
"""

from __future__ import annotations

import logging
import math
from typing import Any

from firmware_bridge.connect import ConnectService
from firmware_bridge.modes import HOLD_MODES, FlightMode, TakeoffPhase, decode_set_mode
from firmware_bridge.offboard import IMU_PREDICTION_HORIZON_S, OffboardService
from firmware_bridge.state import BoardStatusLike, BridgeState, Outbound
from quadlink.mavlink import mavlink
from quadlink.mavlink.command_params import COMMAND_PARAMS, CommandParamError, read_params
from quadlink.mk.flags import BoardFlightState

log = logging.getLogger("firmware_bridge.autopilot")

SETPOINT_FRESH_FOR_OFFBOARD_S = 0.5  # PX4 wants the stream running before the switch
FORCE_ARM_DISARM_MAGIC = 21196.0  # ARM_DISARM param2: force (PX4, ArduPilot)
ARM_FOLLOW_TIMEOUT_S = 1.0  # the board must follow an arm request within this, else we stop asking
TAKEOFF_HEIGHT_RANGE_M = (0.2, 50.0)  # NAV_TAKEOFF param7 accepted as a height above the take-off point


class CommanderService:
    """Arming, commands, modes and failsafes over the shared :class:`~firmware_bridge.state.BridgeState`: owns the
    mode, arming, the take-off start and the board, odometry and setpoint-stream failsafes. Uses the offboard
    service's velocity estimate and the connect service's answers to informational requests."""

    def __init__(self, state: BridgeState, offboard: OffboardService, connect: ConnectService) -> None:
        self.state = state
        self.offboard = offboard
        self.connect = connect

    def set_mode(self, mode: FlightMode, now_s: float, reason: str = "") -> None:
        s = self.state
        if mode == s.mode:
            return
        log.info("mode %s -> %s%s", s.mode.name, mode.name, f" ({reason})" if reason else "")
        s.mode = mode
        s.touchdown_since_s = None
        s.hold_anchor_ned_m = None   # a LAND or a TAKEOFF holds where it begins (firmware_bridge.flight_control)
        if mode == FlightMode.TAKEOFF:
            self._start_takeoff(now_s)

    def _start_takeoff(self, now_s: float) -> None:
        s = self.state
        was_in_air, s.in_air = s.in_air, True
        s.takeoff_start_s = now_s   # BRG_TKO_OL_T counts from here (a loss in the climb re-enters phase 1)
        s.tko_ramp_start_s = None if was_in_air else now_s
        s.tko_climbed_m = s.height_m if was_in_air else 0.0
        s.tko_disagree_told = False
        if s.odom_ok and s.fresh(s.odom_time_s, now_s, IMU_PREDICTION_HORIZON_S):
            s.takeoff_phase = TakeoffPhase.CLOSED_LOOP
            if s.z_ground_m is None:
                s.z_ground_m = s.odom_z_m
            s.event(mavlink.MAV_SEVERITY_INFO, f"Takeoff to {s.takeoff_target_m:.1f} m")
            return
        # phase 1: the camera cannot see yet; climb level on the accelerometer until odometry arrives (odometry
        # not yet timed out but older than the IMU's prediction horizon counts as none: see check_links)
        s.odom_ok = False
        s.takeoff_phase = TakeoffPhase.OPEN_LOOP
        s.blind = True
        s.hover_thrust_learned = None
        s.blind_descent = None
        if not was_in_air:
            s.vertical.reset_ground()
        else:
            # on the ground the anchor taken at arming (from odometry valid there) is kept: odometry that only
            # paused and comes back in the same frame gives the height from the ground it measured, not the
            # accelerometer's climb until then (CI: 0.04 m climbed at 0.20 m up, and the take-off ended 0.21 m
            # above its height). A frame reset, or a height TKO_REANCHOR_M from the climb, re-anchors it to the
            # climb (firmware_bridge.offboard.on_odometry); quadlink's companion counts a reset whenever its odometry
            # is good again after failing, so only a stream that paused (a link gap) keeps the ground anchor
            s.z_ground_m = None
        s.height_m = s.vertical.height_m
        s.event(mavlink.MAV_SEVERITY_INFO, f"Takeoff to {s.takeoff_target_m:.1f} m, open loop until odometry")

    def on_board_status(self, now_s: float, status: BoardStatusLike) -> list[Outbound]:
        s = self.state
        prev = s.board_status
        s.board_status = status
        s.board_status_time_s = now_s
        if not s.board_link_ok:
            s.board_link_ok = True
            s.event(mavlink.MAV_SEVERITY_INFO, "Board link up")
        if status.failsafe and not s.board_failsafe_reported:
            s.board_failsafe_reported = True
            s.event(mavlink.MAV_SEVERITY_CRITICAL, f"Board failsafe (flags 0x{status.error_flags:x})")
        elif not status.failsafe:
            s.board_failsafe_reported = False
        if prev is not None and bool(prev.armed) != bool(status.armed):
            s.event(mavlink.MAV_SEVERITY_INFO, "Board armed" if status.armed else "Board disarmed")
        if status.flight_state == BoardFlightState.FLYING and s.armed_cmd:
            s.in_air = True
        return s.flush_events()

    def on_board_version(self, text: str, version_int: int = 0) -> None:
        self.state.board_version = text
        self.state.board_version_int = version_int
        log.info("board firmware: %s", text)

    def disarm(self, now_s: float, why: str) -> None:
        s = self.state
        if s.armed_cmd:
            s.event(mavlink.MAV_SEVERITY_INFO, why)
        s.armed_cmd = False
        s.in_air = False
        s.failsafe_reason = None
        s.fs_hover_until_s = None
        s.z_ground_m = None
        s.height_m = 0.0
        s.blind = False
        s.takeoff_phase = None
        s.blind_descent = None
        s.level_trim_rad[:] = 0.0
        s.reset_trackers()

    def check_links(self, now_s: float) -> None:
        """The failsafes: board link, odometry, offboard setpoint stream, the board following an arm request."""
        s = self.state
        p = s.params
        board_fresh = s.fresh(s.board_status_time_s, now_s, p["BRG_BOARD_LOSS_T"]) or \
            s.fresh(s.imu_time_s, now_s, p["BRG_BOARD_LOSS_T"])
        if s.board_link_ok and not board_fresh:
            s.board_link_ok = False
            s.event(mavlink.MAV_SEVERITY_CRITICAL, "Board link lost")
            s.failsafe_reason = "board link lost"
        odom_fresh = s.fresh(s.odom_time_s, now_s, p["BRG_ODOM_LOSS_T"])
        low_in_climb = s.in_air and s.mode == FlightMode.TAKEOFF and s.height_m < p["BRG_TKO_OL_ALT"]
        if low_in_climb:
            # the climb's tracker flies the odometry's velocity, and past the IMU's prediction horizon that velocity
            # is frozen: with BRG_ODOM_LOSS_T at 2 s, a take-off begun on odometry that had just stopped wound its
            # integral up on a vehicle it thought still, and climbed 0.33 m past its height at 0.8 m/s (a RealSense
            # SITL flight in CI). Low in the climb, odometry that old is lost: the open-loop climb measures it.
            odom_fresh = odom_fresh and s.fresh(s.odom_time_s, now_s, IMU_PREDICTION_HORIZON_S)
        if s.odom_ok and not odom_fresh:
            s.odom_ok = False
            if low_in_climb:
                # low in the climb the camera may lose the floor (too near, too fast): as if it had never
                # seen it, climb open loop until odometry returns, within BRG_TKO_OL_ALT / BRG_TKO_OL_T
                s.event(mavlink.MAV_SEVERITY_WARNING,
                        f"Odometry lost at {s.height_m:.2f} m in takeoff: open loop until odometry")
                stale_s = now_s - s.odom_time_s if s.odom_time_s is not None else 0.0
                vz = float(s.v_h_dead_reckoned[2])
                s.height_m -= vz * max(stale_s, 0.0)  # the climb since the last odometry
                if not s.vertical.estimate.baro_fused:
                    # on the barometer the estimate is the better one: aligned to an odometry the vertical gate had
                    # refused, it took the phantom's descent and the climb ran on to 1 m/s (a unit test's point mass)
                    s.vertical.align(s.height_m, vz)
                s.takeoff_phase = TakeoffPhase.OPEN_LOOP
                s.blind = True
                # the thrust is up already: ramping it again from idle dropped a vehicle 5 cm up back on its gear
                s.tko_ramp_start_s = None
            elif s.in_air:
                s.event(mavlink.MAV_SEVERITY_CRITICAL, "Odometry lost: level hold, descending"
                        + (" on the baro" if s.vertical.estimate.baro_fused else ""))
                s.failsafe_reason = "odometry lost"
                vz = float(self.offboard.v_est_h(now_s)[2])
                s.v_h_dead_reckoned[2] = vz
                # after the brake, the descent is the blind one (firmware_bridge.flight_control._blind_step):
                # thrust capped at the hover thrust, a probe, and the touchdown on ground contact. The leaky
                # dead reckoning alone read an accelerometer bias of 0.2 m/s^2 as 0.6 m/s of descent, and the
                # level descent on it climbed (a campaign flight, 2.4 m to 0.10 m of the ceiling); on the barometer
                # the estimate is the better one and is kept
                if not s.vertical.estimate.baro_fused:
                    s.vertical.align(s.height_m, vz)
                s.blind = True
                s.blind_descent = None
                s.odom_lost_s = now_s
                self.set_mode(FlightMode.LAND, now_s, "odometry lost")
            else:
                log.info("odometry lost (on the ground: nothing depends on it)")  # the health bit says it
        elif odom_fresh and not s.odom_ok:
            s.odom_ok = True
            s.odom_lost_s = None
            self.offboard.odometry_ok_event()
        if s.mode == FlightMode.OFFBOARD and s.in_air and \
                not s.fresh(s.setpoint_time_s, now_s, p["COM_OF_LOSS_T"]):
            s.failsafe_reason = "offboard setpoints lost"
            s.event(mavlink.MAV_SEVERITY_CRITICAL, f"Offboard lost >{p['COM_OF_LOSS_T']:.1f}s: hover, then land")
            s.fs_hover_until_s = now_s + p["BRG_FS_HOVER_T"]
            self.set_mode(FlightMode.LOITER, now_s, "offboard setpoints lost")
        # the board must follow our arm request within a second, else we stop asking
        if s.board_link_ok and s.board_status is not None and bool(s.board_status.armed) != s.armed_cmd:
            if s.arm_mismatch_since_s is None:
                s.arm_mismatch_since_s = now_s
            elif now_s - s.arm_mismatch_since_s > ARM_FOLLOW_TIMEOUT_S and s.armed_cmd:
                s.event(mavlink.MAV_SEVERITY_CRITICAL, "Board did not arm: disarming")
                self.disarm(now_s, "Board did not arm")
                s.arm_mismatch_since_s = None
        else:
            s.arm_mismatch_since_s = None

    def on_set_mode(self, now_s: float, msg: Any, link: int) -> list[Outbound]:
        if msg.target_system not in (0, self.state.sysid):
            return []
        mode = FlightMode.from_custom_mode(msg.custom_mode)
        if mode is not None:
            self._request_mode(mode, now_s)
        return []

    def on_command_long(self, now_s: float, msg: Any, link: int) -> list[Outbound]:
        if not self.state.for_us(msg):
            return []
        params = (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7)
        return self._command(now_s, msg, link, msg.command, params)

    def on_command_int(self, now_s: float, msg: Any, link: int) -> list[Outbound]:
        if not self.state.for_us(msg):
            return []
        params = (msg.param1, msg.param2, msg.param3, msg.param4, float(msg.x), float(msg.y), msg.z)
        return self._command(now_s, msg, link, msg.command, params)

    def _command(self, now_s: float, msg: Any, link: int, command: int, p: tuple[float, ...]) -> list[Outbound]:
        self.state.counters["commands"] += 1
        result, extra = self.execute_command(now_s, command, p)
        ack = self.state.mav.command_ack_encode(command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent())
        return [Outbound(ack, link)] + [Outbound(m, link) for m in extra]

    def execute_command(self, now_s: float, command: int, p: tuple[float, ...]) -> tuple[int, list[Any]]:
        """A command's MAV_RESULT and the messages it produces (the informational ones: the connect service's)."""
        answered = self.connect.answer_request(now_s, command, p)
        if answered is not None:
            return answered
        s = self.state
        ACCEPTED, DENIED = mavlink.MAV_RESULT_ACCEPTED, mavlink.MAV_RESULT_DENIED
        TEMP = mavlink.MAV_RESULT_TEMPORARILY_REJECTED
        if command in COMMAND_PARAMS:
            # the one table of MAVLink's NaN = "unused" per command (quadlink.mavlink.command_params): ARM_DISARM's
            # param1 must be exactly 0 or 1, NaN is never "disarm" (issue 16)
            try:
                p = read_params(command, p)
            except CommandParamError as exc:
                s.counters["commands_refused"] += 1
                s.event(mavlink.MAV_SEVERITY_WARNING, f"Command {command} refused: {exc}")
                return DENIED, []
        if command == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
            force = p[1] == FORCE_ARM_DISARM_MAGIC  # NaN (MAVSDK's unused) is not the magic number
            if p[0] == 1.0:
                if not s.board_link_ok:
                    s.event(mavlink.MAV_SEVERITY_CRITICAL, "Arming denied: no board link")
                    return TEMP, []
                if s.board_status is not None and s.board_status.failsafe and not force:
                    s.event(mavlink.MAV_SEVERITY_CRITICAL, "Arming denied: board failsafe")
                    return TEMP, []
                if not s.armed_cmd:
                    s.armed_cmd = True
                    s.in_air = False
                    s.blind = False
                    s.takeoff_phase = None
                    s.blind_descent = None
                    s.z_ground_m = s.odom_z_m if s.odom_ok else None
                    s.height_m = 0.0
                    if s.mode in (FlightMode.LAND, FlightMode.TAKEOFF):
                        self.set_mode(FlightMode.POSCTL, now_s, "armed on the ground")  # else LAND disarms at once
                    s.event(mavlink.MAV_SEVERITY_INFO, "Armed")
                return ACCEPTED, []
            if s.in_air and not force:
                s.event(mavlink.MAV_SEVERITY_WARNING, "Disarm denied: in air (force with 21196)")
                return DENIED, []
            self.disarm(now_s, "Disarmed")
            return ACCEPTED, []
        if command == mavlink.MAV_CMD_DO_SET_MODE:
            mode = decode_set_mode(p[0], p[1], p[2])
            if mode is None:
                return mavlink.MAV_RESULT_UNSUPPORTED, []
            return self._request_mode(mode, now_s), []
        if command == mavlink.MAV_CMD_NAV_TAKEOFF:
            height = p[6]
            if math.isfinite(height) and TAKEOFF_HEIGHT_RANGE_M[0] <= height <= TAKEOFF_HEIGHT_RANGE_M[1]:
                s.takeoff_target_m = float(height)  # relative to the take-off point (no AMSL here)
            else:
                s.takeoff_target_m = s.params["MIS_TAKEOFF_ALT"]
            return self._request_mode(FlightMode.TAKEOFF, now_s), []
        if command == mavlink.MAV_CMD_NAV_LAND:
            return self._request_mode(FlightMode.LAND, now_s), []
        if command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            result = s.streams.set_interval(p[0], p[1])
            if result == mavlink.MAV_RESULT_DENIED:
                s.counters["commands_refused"] += 1
                s.event(mavlink.MAV_SEVERITY_WARNING, f"Message interval refused: {p[0]!r} {p[1]!r} us")
            return result, []
        s.counters["unsupported_commands"] += 1
        log.info("unsupported command %d", command)
        return mavlink.MAV_RESULT_UNSUPPORTED, []

    def _request_mode(self, mode: FlightMode, now_s: float) -> int:
        s = self.state
        TEMP = mavlink.MAV_RESULT_TEMPORARILY_REJECTED
        if mode == FlightMode.OFFBOARD:
            if not s.fresh(s.setpoint_time_s, now_s, SETPOINT_FRESH_FOR_OFFBOARD_S) or \
                    (s.vel_sp is None and s.att_sp is None):
                s.event(mavlink.MAV_SEVERITY_WARNING, "Offboard denied: no setpoint stream")
                return TEMP
            if s.vel_sp is not None and not s.odom_ok:
                s.event(mavlink.MAV_SEVERITY_WARNING, "Offboard denied: no odometry")
                return TEMP
        if mode == FlightMode.TAKEOFF:
            if not s.armed_cmd:
                s.event(mavlink.MAV_SEVERITY_WARNING, "Takeoff denied: not armed")
                return TEMP
            if s.in_air and not s.odom_ok and not s.blind:
                s.event(mavlink.MAV_SEVERITY_WARNING, "Takeoff denied: odometry lost in the air")
                return TEMP
        if mode in HOLD_MODES and s.in_air and s.blind and not s.odom_ok:
            s.event(mavlink.MAV_SEVERITY_WARNING, f"{mode.name} denied: no odometry yet")
            return TEMP
        s.failsafe_reason = None if mode != FlightMode.LAND else s.failsafe_reason
        s.fs_hover_until_s = None
        if mode == s.mode and mode == FlightMode.TAKEOFF:
            return mavlink.MAV_RESULT_ACCEPTED
        self.set_mode(mode, now_s, "requested")
        return mavlink.MAV_RESULT_ACCEPTED

"""Telemetry service: HEARTBEAT, SYS_STATUS, SYSTEM_TIME, EXTENDED_SYS_STATE, BATTERY_STATUS,
AUTOPILOT_VERSION and the per-IMU-sample streams, scheduled by :class:`firmware_bridge.streams.StreamScheduler`
(pure; time as argument).

HEARTBEAT reports ``MAV_AUTOPILOT_PX4`` with PX4's custom mode (:mod:`firmware_bridge.modes`; why PX4 and what
that promises: firmware_bridge/README.md "Identity"). SYS_STATUS claims only what the vehicle has — gyro,
accelerometer, the attitude filter (AHRS), vision odometry (the companion), rate/attitude/altitude/position
control, motor outputs, battery and the pre-arm check; no GPS, magnetometer or barometer (the FlightCtrl's
pressure sensor serves its own failsafe descent and never reaches the bridge). Present = enabled, and health is
honest: gyro/accel/AHRS only with a fresh, unsaturated IMU; vision/position control only with fresh odometry;
rate/attitude control and motors only with a board link and no setpoint timeout or failsafe; the pre-arm check
when arming would be accepted.
"""

from __future__ import annotations

import math
from typing import Any

from firmware_bridge.attitude_filter import AttitudeEstimate
from firmware_bridge.modes import FlightMode
from firmware_bridge.state import BridgeState, Outbound
from quadlink import __version__
from quadlink.frames import quat_wxyz_from_euler
from quadlink.mavlink import mavlink
from quadlink.mk.flags import BoardError

SENSORS_PRESENT = (mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO | mavlink.MAV_SYS_STATUS_SENSOR_3D_ACCEL
                   | mavlink.MAV_SYS_STATUS_SENSOR_VISION_POSITION | mavlink.MAV_SYS_STATUS_SENSOR_ANGULAR_RATE_CONTROL
                   | mavlink.MAV_SYS_STATUS_SENSOR_ATTITUDE_STABILIZATION
                   | mavlink.MAV_SYS_STATUS_SENSOR_Z_ALTITUDE_CONTROL
                   | mavlink.MAV_SYS_STATUS_SENSOR_XY_POSITION_CONTROL
                   | mavlink.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS | mavlink.MAV_SYS_STATUS_SENSOR_BATTERY
                   | mavlink.MAV_SYS_STATUS_AHRS | mavlink.MAV_SYS_STATUS_PREARM_CHECK)

# PARAM_ENCODE_BYTEWISE: integer parameters travel as their bytes (quadlink.mavlink.param_service); the bridge's
# are all REAL32, for which bytewise and C-cast encodings coincide
CAPABILITIES = (mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2 | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
                | mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
                | mavlink.MAV_PROTOCOL_CAPABILITY_SET_ATTITUDE_TARGET
                | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE)
# No mission, fence, rally or FTP bits: the vehicle flies none of them and serves no files. The mission protocol
# and FTP are still answered at once for the clients that ask anyway (firmware_bridge.connect).
#: the heartbeat's autopilot: PX4's custom modes, named by QGroundControl's PX4 plugin, MAVProxy and MAVSDK
AUTOPILOT_IDENTITY = mavlink.MAV_AUTOPILOT_PX4
BATTERY_HEALTHY_FRACTION = 0.05  # SYS_STATUS battery health bit above this remaining fraction
VERSION_UID_PREFIX = 0x514C  # "QL" in AUTOPILOT_VERSION.uid


def encode_sw_version(major: int, minor: int, patch: int, version_type: int = 0) -> int:
    """AUTOPILOT_VERSION's ``*_sw_version`` word: major, minor, patch, FIRMWARE_VERSION_TYPE from the top byte."""
    return int.from_bytes(bytes([version_type & 0xFF, patch & 0xFF, minor & 0xFF, major & 0xFF]), "little")


class TelemetryService:
    """Periodic and on-request telemetry. Reads the shared :class:`~firmware_bridge.state.BridgeState`; of it,
    changes only the stream schedule (what is due) and the event queue it flushes."""

    def __init__(self, state: BridgeState) -> None:
        self.state = state

    def imu_streams(self, now_s: float, time_usec: int, est: AttitudeEstimate) -> list[Outbound]:
        """HIGHRES_IMU / ATTITUDE / ATTITUDE_QUATERNION for one IMU sample, at their stream rates."""
        s = self.state
        out: list[Outbound] = []
        if s.streams.due(mavlink.MAVLINK_MSG_ID_HIGHRES_IMU, now_s):
            a, w = s.last_accel_q, s.last_gyro_q
            out.append(Outbound(s.mav.highres_imu_encode(
                int(time_usec), float(a[0]), float(a[1]), float(a[2]), float(w[0]), float(w[1]), float(w[2]),
                0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0x3F)))
        boot_ms = int(time_usec // 1000) & 0xFFFFFFFF
        if s.streams.due(mavlink.MAVLINK_MSG_ID_ATTITUDE, now_s):
            out.append(Outbound(s.mav.attitude_encode(boot_ms, est.roll_rad, est.pitch_rad, est.yaw_rad,
                                                      est.rollspeed_rad_s, est.pitchspeed_rad_s,
                                                      est.yawspeed_rad_s)))
        if s.streams.due(mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION, now_s):
            q = quat_wxyz_from_euler(est.roll_rad, est.pitch_rad, est.yaw_rad)  # [w, x, y, z], as MAVLink
            out.append(Outbound(s.mav.attitude_quaternion_encode(
                boot_ms, float(q[0]), float(q[1]), float(q[2]), float(q[3]), est.rollspeed_rad_s,
                est.pitchspeed_rad_s, est.yawspeed_rad_s)))
        return out

    def tick(self, now_s: float) -> list[Outbound]:
        """Periodic telemetry (call at >= 50 Hz) and the STATUSTEXT events of the last steps."""
        s = self.state
        out = s.flush_events()
        if s.streams.due(mavlink.MAVLINK_MSG_ID_HEARTBEAT, now_s):
            out.append(Outbound(self.heartbeat()))
        if s.streams.due(mavlink.MAVLINK_MSG_ID_SYS_STATUS, now_s):
            out.append(Outbound(self.sys_status(now_s)))
        if s.streams.due(mavlink.MAVLINK_MSG_ID_SYSTEM_TIME, now_s):
            out.append(Outbound(self.system_time(now_s)))
        if s.streams.due(mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE, now_s):
            out.append(Outbound(s.mav.extended_sys_state_encode(0, self.landed_state())))
        if s.streams.due(mavlink.MAVLINK_MSG_ID_BATTERY_STATUS, now_s):
            out.append(Outbound(self.battery_status()))
        if s.vertical.estimate.baro_fused and s.streams.due(mavlink.MAVLINK_MSG_ID_ALTITUDE, now_s):
            out.append(Outbound(self.altitude(now_s)))
        return out

    def altitude(self, now_s: float) -> Any:
        """ALTITUDE: the barometer-fused height above where the vehicle last stood (the take-off spot,
        :mod:`firmware_bridge.vertical_estimator`; in the air its baro reference follows the odometry's height,
        ``BRG_BARO_REF_T``) as ``altitude_local`` and ``altitude_relative``, NaN without a fresh baro reading; as
        ``altitude_monotonic`` the board's own barometric altitude, never re-referenced (MAVLink's recommended value:
        the uncorrected baro altitude since the power-up); AMSL, terrain and bottom clearance unknown (NaN). The
        companion keeps its ceiling from the highest of its odometry's height, the fused height and the board's since
        the take-off (altitude_monotonic less its value on the ground), so a slowly drifting odometry, which the
        fused height follows, is still checked by a barometer that does not."""
        s = self.state
        fused = s.vertical.estimate.baro_fused
        h = s.vertical.height_m if fused else math.nan
        raw = s.vertical.baro_altitude_m
        monotonic = raw if fused and raw is not None else math.nan
        nan = math.nan
        return s.mav.altitude_encode(int(now_s * 1e6), monotonic, nan, h, h, nan, nan)

    def landed_state(self) -> int:
        if not self.state.in_air:
            return mavlink.MAV_LANDED_STATE_ON_GROUND
        if self.state.mode == FlightMode.TAKEOFF:
            return mavlink.MAV_LANDED_STATE_TAKEOFF
        if self.state.mode == FlightMode.LAND:
            return mavlink.MAV_LANDED_STATE_LANDING
        return mavlink.MAV_LANDED_STATE_IN_AIR

    def heartbeat(self) -> Any:
        s = self.state
        base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        if s.armed:
            base |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        if s.failsafe_reason or not s.board_link_ok or (s.board_status is not None and s.board_status.failsafe):
            status = mavlink.MAV_STATE_CRITICAL
        elif s.armed:
            status = mavlink.MAV_STATE_ACTIVE
        else:
            status = mavlink.MAV_STATE_STANDBY
        return s.mav.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, AUTOPILOT_IDENTITY, base, s.mode.custom_mode, status)

    def battery_fraction(self) -> float | None:
        status = self.state.board_status
        if status is None:
            return None
        b = self.state.vehicle.battery
        cell_v = status.battery_mv / 1000.0 / b.cells
        return min(max((cell_v - b.empty_cell_v) / (b.full_cell_v - b.empty_cell_v), 0.0), 1.0)

    def sys_status(self, now_s: float) -> Any:
        s = self.state
        flags = s.board_status.error_flags if s.board_status is not None else 0
        imu_ok = s.fresh(s.imu_time_s, now_s, s.params["BRG_BOARD_LOSS_T"]) and not flags & BoardError.IMU_SATURATED
        board_ok = s.board_link_ok and s.board_status is not None and not s.board_status.failsafe \
            and not flags & BoardError.SETPOINT_TIMEOUT
        # No geofence here (not present, not enabled); its health bit means "not breached", as ArduPilot
        # reports it: left clear, MAVProxy's fence module announces a "fence breach" at connect.
        health = mavlink.MAV_SYS_STATUS_GEOFENCE
        if imu_ok:
            health |= mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO | mavlink.MAV_SYS_STATUS_SENSOR_3D_ACCEL | \
                mavlink.MAV_SYS_STATUS_AHRS
        if s.board_link_ok and not (s.board_status is not None and s.board_status.failsafe):
            health |= mavlink.MAV_SYS_STATUS_PREARM_CHECK   # the conditions the arm command checks
        if s.odom_ok:
            health |= mavlink.MAV_SYS_STATUS_SENSOR_VISION_POSITION | \
                mavlink.MAV_SYS_STATUS_SENSOR_XY_POSITION_CONTROL | mavlink.MAV_SYS_STATUS_SENSOR_Z_ALTITUDE_CONTROL
        if board_ok:
            health |= mavlink.MAV_SYS_STATUS_SENSOR_ANGULAR_RATE_CONTROL | \
                mavlink.MAV_SYS_STATUS_SENSOR_ATTITUDE_STABILIZATION | mavlink.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
        frac = self.battery_fraction()
        if frac is not None and frac > BATTERY_HEALTHY_FRACTION and not flags & BoardError.BATTERY_LOW:
            health |= mavlink.MAV_SYS_STATUS_SENSOR_BATTERY
        voltage_mv = int(s.board_status.battery_mv) if s.board_status is not None else 0xFFFF
        remaining = int(round(frac * 100)) if frac is not None else -1
        c = s.counters
        errors = c["mavlink_bad"] + c["mk_bad"]
        return s.mav.sys_status_encode(SENSORS_PRESENT, SENSORS_PRESENT, health, 0, min(voltage_mv, 0xFFFF), -1,
                                       remaining, 0, min(errors, 0xFFFF), min(c["mavlink_bad"], 0xFFFF),
                                       min(c["mk_bad"], 0xFFFF), min(c["setpoint_rejected"], 0xFFFF),
                                       min(c["odometry_rejected"], 0xFFFF))

    def battery_status(self) -> Any:
        s = self.state
        mv = int(s.board_status.battery_mv) if s.board_status is not None else 0xFFFF
        frac = self.battery_fraction()
        voltages = [min(mv, 0xFFFE)] + [0xFFFF] * 9
        return s.mav.battery_status_encode(0, mavlink.MAV_BATTERY_FUNCTION_ALL, mavlink.MAV_BATTERY_TYPE_LIPO,
                                           32767, voltages, -1, -1, -1,
                                           int(round(frac * 100)) if frac is not None else -1)

    def system_time(self, now_s: float) -> Any:
        unix_clock = self.state.unix_clock
        unix_us = int(unix_clock() * 1e6) if unix_clock is not None else 0
        return self.state.mav.system_time_encode(unix_us, int(now_s * 1000) & 0xFFFFFFFF)

    def autopilot_version(self) -> Any:
        s = self.state
        major, minor, patch = (int(x) for x in (__version__.split(".") + ["0", "0"])[:3])
        sw = encode_sw_version(major, minor, patch, mavlink.FIRMWARE_VERSION_TYPE_OFFICIAL)
        uid = (VERSION_UID_PREFIX << 48) | (s.sysid << 8) | s.compid
        return s.mav.autopilot_version_encode(CAPABILITIES, sw, s.board_version_int, 0, 0,
                                              [0] * 8, [0] * 8, [0] * 8, 0, 0, uid)

    def message_by_id(self, msg_id: int, now_s: float) -> Any:
        """The telemetry message ``msg_id``, on request (REQUEST_MESSAGE); None if it is not one of these."""
        if msg_id == mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            return self.autopilot_version()
        if msg_id == mavlink.MAVLINK_MSG_ID_HEARTBEAT:
            return self.heartbeat()
        if msg_id == mavlink.MAVLINK_MSG_ID_SYS_STATUS:
            return self.sys_status(now_s)
        if msg_id == mavlink.MAVLINK_MSG_ID_SYSTEM_TIME:
            return self.system_time(now_s)
        if msg_id == mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE:
            return self.state.mav.extended_sys_state_encode(0, self.landed_state())
        if msg_id == mavlink.MAVLINK_MSG_ID_BATTERY_STATUS:
            return self.battery_status()
        if msg_id == mavlink.MAVLINK_MSG_ID_ALTITUDE:
            return self.altitude(now_s)
        if msg_id == mavlink.MAVLINK_MSG_ID_ATTITUDE:
            e = self.state.filter.estimate
            return self.state.mav.attitude_encode(int(now_s * 1000) & 0xFFFFFFFF, e.roll_rad, e.pitch_rad,
                                                  e.yaw_rad, e.rollspeed_rad_s, e.pitchspeed_rad_s, e.yawspeed_rad_s)
        return None

"""Connect service: what QGroundControl, MAVSDK and MAVProxy ask a vehicle on connect, answered honestly (pure).

* MAV_CMD_REQUEST_PROTOCOL_VERSION and MAV_CMD_REQUEST_MESSAGE(PROTOCOL_VERSION) -> COMMAND_ACK ACCEPTED and
  PROTOCOL_VERSION (MAVLink 2 only; :func:`quadlink.mavlink.gcs_services.protocol_version_message`);
* MAV_CMD_REQUEST_MESSAGE for every message this bridge produces (:data:`REQUESTABLE`), ACCEPTED and the
  message; anything else (component information and metadata, home position, available modes, cameras,
  gimbals...) UNSUPPORTED, so a client gives up at once instead of retrying;
* the mission protocol for mission, fence and rally: empty lists, uploads refused, clears acknowledged
  (:func:`quadlink.mavlink.gcs_services.handle_mission`): the vehicle has no absolute position;
* MAVLink FTP: a prompt NAK for every request (:func:`quadlink.mavlink.gcs_services.handle_ftp`), so clients
  fall back to the parameter protocol at once.

The table of requests and answers is in firmware_bridge/README.md ("Ground stations").
"""

from __future__ import annotations

from typing import Any

from firmware_bridge.flight_control import FlightControlService
from firmware_bridge.modes import int_param
from firmware_bridge.state import Outbound
from quadlink.frames import quat_wxyz_from_euler
from quadlink.mavlink import gcs_services, mavlink
from quadlink.mavlink.param_service import ParamService

#: what MAV_CMD_REQUEST_MESSAGE answers (message id -> name); everything the bridge sends but command acks,
#: STATUSTEXT and TIMESYNC (replies of their own protocols)
REQUESTABLE: dict[int, str] = {
    mavlink.MAVLINK_MSG_ID_HEARTBEAT: "HEARTBEAT",
    mavlink.MAVLINK_MSG_ID_SYS_STATUS: "SYS_STATUS",
    mavlink.MAVLINK_MSG_ID_SYSTEM_TIME: "SYSTEM_TIME",
    mavlink.MAVLINK_MSG_ID_PARAM_VALUE: "PARAM_VALUE",
    mavlink.MAVLINK_MSG_ID_ATTITUDE: "ATTITUDE",
    mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: "ATTITUDE_QUATERNION",
    mavlink.MAVLINK_MSG_ID_HIGHRES_IMU: "HIGHRES_IMU",
    mavlink.MAVLINK_MSG_ID_BATTERY_STATUS: "BATTERY_STATUS",
    mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION: "AUTOPILOT_VERSION",
    mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: "EXTENDED_SYS_STATE",
    mavlink.MAVLINK_MSG_ID_PROTOCOL_VERSION: "PROTOCOL_VERSION",
}

MISSION_MESSAGES = ("MISSION_REQUEST_LIST", "MISSION_COUNT", "MISSION_CLEAR_ALL", "MISSION_REQUEST_INT",
                    "MISSION_REQUEST", "MISSION_ITEM_INT", "MISSION_ITEM")


class ConnectService(FlightControlService):
    """Protocol version, REQUEST_MESSAGE, mission and FTP answers over the shared state."""

    param_service: ParamService   # built by the facade (firmware_bridge.autopilot)

    def execute_command(self, now_s: float, command: int, p: tuple[float, ...]) -> tuple[int, list[Any]]:
        if command == mavlink.MAV_CMD_REQUEST_PROTOCOL_VERSION:
            return mavlink.MAV_RESULT_ACCEPTED, [gcs_services.protocol_version_message()]
        if command == mavlink.MAV_CMD_REQUEST_MESSAGE:
            reply = self.requested_message(int_param(p[0], -1), p, now_s)
            if reply is None:
                self.counters["unsupported_commands"] += 1
                return mavlink.MAV_RESULT_UNSUPPORTED, []
            return mavlink.MAV_RESULT_ACCEPTED, [reply]
        return super().execute_command(now_s, command, p)

    def requested_message(self, msg_id: int, p: tuple[float, ...], now_s: float) -> Any:
        """The message MAV_CMD_REQUEST_MESSAGE asks for (params ``p``), None if this bridge does not produce it."""
        if msg_id == mavlink.MAVLINK_MSG_ID_PROTOCOL_VERSION:
            return gcs_services.protocol_version_message()
        if msg_id == mavlink.MAVLINK_MSG_ID_PARAM_VALUE:   # param2: the parameter's index
            names = self.params.names()
            index = int_param(p[1], -1)
            return self.param_service.param_value(names[index]) if 0 <= index < len(names) else None
        if msg_id == mavlink.MAVLINK_MSG_ID_HIGHRES_IMU:
            a, w = self.last_accel_q, self.last_gyro_q
            return self.mav.highres_imu_encode(int(self.last_imu_time_usec), float(a[0]), float(a[1]), float(a[2]),
                                               float(w[0]), float(w[1]), float(w[2]), 0.0, 0.0, 0.0, 0.0, 0.0, 0.0,
                                               0.0, 0x3F)
        if msg_id == mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION:
            e = self.filter.estimate
            q = quat_wxyz_from_euler(e.roll_rad, e.pitch_rad, e.yaw_rad)   # [w, x, y, z], as MAVLink
            return self.mav.attitude_quaternion_encode(int(now_s * 1000) & 0xFFFFFFFF, float(q[0]), float(q[1]),
                                                       float(q[2]), float(q[3]), e.rollspeed_rad_s,
                                                       e.pitchspeed_rad_s, e.yawspeed_rad_s)
        return self._message_by_id(msg_id, now_s)

    def _on_mission(self, now_s: float, msg: Any, link: int) -> list[Outbound]:
        if not self.for_us(msg):
            return []
        return [Outbound(m, link) for m in gcs_services.handle_mission(msg)]

    def _on_ftp(self, now_s: float, msg: Any, link: int) -> list[Outbound]:
        return [Outbound(m, link) for m in gcs_services.handle_ftp(msg, self.sysid, self.compid)]

"""Connect service: what QGroundControl, MAVSDK and MAVProxy ask a vehicle on connect, answered honestly (pure).

* MAV_CMD_REQUEST_PROTOCOL_VERSION and MAV_CMD_REQUEST_MESSAGE(PROTOCOL_VERSION) -> COMMAND_ACK ACCEPTED and
  PROTOCOL_VERSION (MAVLink 2 only; :func:`quadlink.mavlink.gcs_services.protocol_version_message`);
* MAV_CMD_REQUEST_MESSAGE for every message this bridge produces (:data:`REQUESTABLE`), ACCEPTED and the
  message; anything else (component information and metadata, home position, available modes, cameras,
  gimbals...) UNSUPPORTED, so a client gives up at once instead of retrying;
* the mission protocol for mission, fence and rally: empty lists, uploads refused, clears acknowledged
  (:func:`quadlink.mavlink.gcs_services.handle_mission`): the vehicle has no absolute position;
* MAVLink FTP: a prompt NAK for every request (:func:`quadlink.mavlink.gcs_services.handle_ftp`), so clients
  fall back to the parameter protocol at once;
* MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES -> AUTOPILOT_VERSION, and TIMESYNC (v2) requests -> the board time.

The commander (:mod:`firmware_bridge.commander`) acks the commands; :meth:`ConnectService.answer_request` gives
it the result and the reply.

The table of requests and answers is in firmware_bridge/README.md ("Ground stations").
"""

from __future__ import annotations

from typing import Any

from firmware_bridge.modes import int_param
from firmware_bridge.state import BridgeState, Outbound
from firmware_bridge.telemetry import TelemetryService
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
    mavlink.MAVLINK_MSG_ID_ALTITUDE: "ALTITUDE",
    mavlink.MAVLINK_MSG_ID_PROTOCOL_VERSION: "PROTOCOL_VERSION",
}

MISSION_MESSAGES = ("MISSION_REQUEST_LIST", "MISSION_COUNT", "MISSION_CLEAR_ALL", "MISSION_REQUEST_INT",
                    "MISSION_REQUEST", "MISSION_ITEM_INT", "MISSION_ITEM")


class ConnectService:
    """Protocol version, REQUEST_MESSAGE, TIMESYNC, mission and FTP answers: reads the shared
    :class:`~firmware_bridge.state.BridgeState` (changes only its counters), the messages from the telemetry
    service, PARAM_VALUE from the shared parameter service."""

    def __init__(self, state: BridgeState, telemetry: TelemetryService, param_service: ParamService) -> None:
        self.state = state
        self.telemetry = telemetry
        self.param_service = param_service

    def answer_request(self, now_s: float, command: int, p: tuple[float, ...]) -> tuple[int, list[Any]] | None:
        """An informational command's MAV_RESULT and reply (the commander acks it); None for any other command."""
        if command == mavlink.MAV_CMD_REQUEST_PROTOCOL_VERSION:
            return mavlink.MAV_RESULT_ACCEPTED, [gcs_services.protocol_version_message()]
        if command == mavlink.MAV_CMD_REQUEST_MESSAGE:
            reply = self.requested_message(int_param(p[0], -1), p, now_s)
            if reply is None:
                self.state.counters["unsupported_commands"] += 1
                return mavlink.MAV_RESULT_UNSUPPORTED, []
            return mavlink.MAV_RESULT_ACCEPTED, [reply]
        if command == mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            return mavlink.MAV_RESULT_ACCEPTED, [self.telemetry.autopilot_version()]
        return None

    def requested_message(self, msg_id: int, p: tuple[float, ...], now_s: float) -> Any:
        """The message MAV_CMD_REQUEST_MESSAGE asks for (params ``p``), None if this bridge does not produce it."""
        s = self.state
        if msg_id == mavlink.MAVLINK_MSG_ID_PROTOCOL_VERSION:
            return gcs_services.protocol_version_message()
        if msg_id == mavlink.MAVLINK_MSG_ID_PARAM_VALUE:   # param2: the parameter's index
            names = s.params.names()
            index = int_param(p[1], -1)
            return self.param_service.param_value(names[index]) if 0 <= index < len(names) else None
        if msg_id == mavlink.MAVLINK_MSG_ID_HIGHRES_IMU:
            a, w = s.last_accel_q, s.last_gyro_q
            return s.mav.highres_imu_encode(int(s.last_imu_time_usec), float(a[0]), float(a[1]), float(a[2]),
                                            float(w[0]), float(w[1]), float(w[2]), 0.0, 0.0, 0.0, 0.0, 0.0, 0.0,
                                            0.0, 0x3F)
        if msg_id == mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION:
            e = s.filter.estimate
            q = quat_wxyz_from_euler(e.roll_rad, e.pitch_rad, e.yaw_rad)   # [w, x, y, z], as MAVLink
            return s.mav.attitude_quaternion_encode(int(now_s * 1000) & 0xFFFFFFFF, float(q[0]), float(q[1]),
                                                    float(q[2]), float(q[3]), e.rollspeed_rad_s,
                                                    e.pitchspeed_rad_s, e.yawspeed_rad_s)
        return self.telemetry.message_by_id(msg_id, now_s)

    def on_mission(self, now_s: float, msg: Any, link: int) -> list[Outbound]:
        if not self.state.for_us(msg):
            return []
        return [Outbound(m, link) for m in gcs_services.handle_mission(msg)]

    def on_ftp(self, now_s: float, msg: Any, link: int) -> list[Outbound]:
        return [Outbound(m, link) for m in gcs_services.handle_ftp(msg, self.state.sysid, self.state.compid)]

    def on_timesync(self, now_s: float, msg: Any, link: int) -> list[Outbound]:
        if msg.tc1 != 0:
            return []  # a reply to someone else's request
        # timesync v2: tc1 = our time in ns, ts1 echoed so the requester can match its request
        return [Outbound(self.state.mav.timesync_encode(int(now_s * 1e9), msg.ts1), link)]

    def on_heartbeat(self, now_s: float, msg: Any, link: int) -> list[Outbound]:
        """Nothing to answer (a received HEARTBEAT only flushes the pending events, as every handled message)."""
        return []

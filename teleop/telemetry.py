"""What the ground station knows about the vehicle, from the MAVLink it receives. Pure: messages and
their arrival time in, a frozen :class:`Telemetry` snapshot out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

from quadlink.ids import COMPANION_COMPONENT_ID
from quadlink.mavlink import mavlink

_MODE_PREFIX = "QUADLINK_TELEOP_MODE_"
# TELEOP_FEEDBACK.mode -> name, from the dialect's QUADLINK_TELEOP_MODE (idle, takeoff, teleop, hold, land)
MODE_NAMES = {value: entry.name[len(_MODE_PREFIX):].lower()
              for value, entry in mavlink.enums["QUADLINK_TELEOP_MODE"].items()
              if entry.name.startswith(_MODE_PREFIX) and not entry.name.endswith("_ENUM_END")}
FLAG_PAN_SCAN_ON = mavlink.QUADLINK_TELEOP_FLAGS_PAN_SCAN_ON
FLAG_ODOMETRY_OK = mavlink.QUADLINK_TELEOP_FLAGS_ODOMETRY_OK
FLAG_GCS_LINK_OK = mavlink.QUADLINK_TELEOP_FLAGS_GCS_LINK_OK
FLAG_OBSTACLES_FRESH = mavlink.QUADLINK_TELEOP_FLAGS_OBSTACLES_FRESH


@dataclass(frozen=True)
class Feedback:
    """TELEOP_FEEDBACK (H frame, NED, SI), with the ground-station receive time."""

    t_recv_s: float
    time_usec: int
    v_h_m_s: tuple[float, float, float]
    v_cmd_h_m_s: tuple[float, float, float]
    v_rep_h_m_s: tuple[float, float, float]
    alpha_rad: float
    pan_scan_yaw_rate_rad_s: float
    yaw_rate_cmd_rad_s: float
    gyro_yaw_rate_rad_s: float
    obstacle_h_m: tuple[float, float, float]
    obstacle_distance_m: float | None
    mode: int
    flags: int

    @property
    def pan_scan_on(self) -> bool:
        return bool(self.flags & FLAG_PAN_SCAN_ON)


@dataclass(frozen=True)
class Telemetry:
    autopilot_heartbeat_t_s: float | None = None
    companion_heartbeat_t_s: float | None = None
    armed: bool = False
    roll_rad: float = 0.0
    pitch_rad: float = 0.0
    yaw_rad: float = 0.0
    battery_v: float | None = None
    battery_remaining_pct: int | None = None
    obstacle_distance_min_m: float | None = None     # from OBSTACLE_DISTANCE
    feedback: Feedback | None = None
    last_statustext: str = ""
    statustext_t_s: float | None = None


def _finite(x: float, default: float = 0.0) -> float:
    return float(x) if math.isfinite(x) else default


def apply_message(tel: Telemetry, msg: Any, t_s: float, autopilot: tuple[int, int] = (1, 1),
                  companion_component: int = COMPANION_COMPONENT_ID) -> Telemetry:
    """The snapshot after ``msg`` (a pymavlink message) arrived at ``t_s``."""
    mtype = msg.get_type()
    src = (msg.get_srcSystem(), msg.get_srcComponent())
    if mtype == "HEARTBEAT":
        if src == autopilot:
            armed = bool(msg.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
            return replace(tel, autopilot_heartbeat_t_s=t_s, armed=armed)
        if src == (autopilot[0], companion_component):
            return replace(tel, companion_heartbeat_t_s=t_s)
        return tel
    if mtype == "ATTITUDE":
        return replace(tel, roll_rad=_finite(msg.roll), pitch_rad=_finite(msg.pitch), yaw_rad=_finite(msg.yaw))
    if mtype == "SYS_STATUS":
        volt = None if msg.voltage_battery in (0, 0xFFFF) else msg.voltage_battery / 1000.0
        rem = None if msg.battery_remaining < 0 else int(msg.battery_remaining)
        return replace(tel, battery_v=volt, battery_remaining_pct=rem)
    if mtype == "OBSTACLE_DISTANCE":
        valid = [d for d in msg.distances if msg.min_distance <= d <= msg.max_distance and d != 0xFFFF]
        return replace(tel, obstacle_distance_min_m=min(valid) / 100.0 if valid else None)
    if mtype == "STATUSTEXT":
        return replace(tel, last_statustext=str(msg.text).rstrip("\x00"), statustext_t_s=t_s)
    if mtype == "TELEOP_FEEDBACK":
        dist = float(msg.obstacle_distance)
        fb = Feedback(
            t_recv_s=t_s, time_usec=int(msg.time_usec),
            v_h_m_s=(_finite(msg.vx_h), _finite(msg.vy_h), _finite(msg.vz_h)),
            v_cmd_h_m_s=(_finite(msg.vx_cmd), _finite(msg.vy_cmd), _finite(msg.vz_cmd)),
            v_rep_h_m_s=(_finite(msg.vx_rep), _finite(msg.vy_rep), _finite(msg.vz_rep)),
            alpha_rad=_finite(msg.alpha), pan_scan_yaw_rate_rad_s=_finite(msg.pan_scan_yaw_rate),
            yaw_rate_cmd_rad_s=_finite(msg.yaw_rate_cmd), gyro_yaw_rate_rad_s=_finite(msg.gyro_yaw_rate),
            obstacle_h_m=(_finite(msg.obstacle_x), _finite(msg.obstacle_y), _finite(msg.obstacle_z)),
            obstacle_distance_m=dist if math.isfinite(dist) and dist >= 0 else None,
            mode=int(msg.mode), flags=int(msg.flags))
        return replace(tel, feedback=fb)
    return tel


def min_obstacle_m(tel: Telemetry) -> float | None:
    candidates = [d for d in (tel.obstacle_distance_min_m,
                              tel.feedback.obstacle_distance_m if tel.feedback else None) if d is not None]
    return min(candidates) if candidates else None

"""SET_POSITION_TARGET_LOCAL_NED as a typed value, and the setpoints a ground client streams (pure).

The constructors are named after MAVSDK's offboard calls and take its units; the type_mask of each comes from
:mod:`quadlink.mavlink.setpoint_masks` (a set bit ignores a field), so the sender and the readers (the companion's
arbiter, the bridge's trackers) share one rule.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

from quadlink.mavlink import mavlink
from quadlink.mavlink.setpoint_masks import TM_POSITION_VELOCITY_ACCEL_YAW, TM_VELOCITY_YAW, TM_VELOCITY_YAW_RATE

TIME_BOOT_MS_MASK = 0xFFFFFFFF  # time_boot_ms is a uint32: it wraps after 49.7 days


@dataclass(frozen=True)
class PositionTarget:
    """One SET_POSITION_TARGET_LOCAL_NED: ``frame`` (MAV_FRAME), ``type_mask`` and the fields in ``frame``'s axes
    (NED-like: x forward or north, y right or east, z down); the fields the mask ignores are 0."""

    frame: int
    type_mask: int
    x_m: float = 0.0
    y_m: float = 0.0
    z_m: float = 0.0
    vx_m_s: float = 0.0
    vy_m_s: float = 0.0
    vz_m_s: float = 0.0
    ax_m_s2: float = 0.0
    ay_m_s2: float = 0.0
    az_m_s2: float = 0.0
    yaw_rad: float = 0.0
    yaw_rate_rad_s: float = 0.0


def velocity_body(forward_m_s: float, right_m_s: float, down_m_s: float, yawspeed_rad_s: float) -> PositionTarget:
    """Velocity in the body frame (yaw-rotated only) and a yaw rate: MAVSDK's ``set_velocity_body``."""
    return PositionTarget(mavlink.MAV_FRAME_BODY_NED, TM_VELOCITY_YAW_RATE, vx_m_s=forward_m_s, vy_m_s=right_m_s,
                          vz_m_s=down_m_s, yaw_rate_rad_s=yawspeed_rad_s)


def velocity_ned(north_m_s: float, east_m_s: float, down_m_s: float, yaw_rad: float) -> PositionTarget:
    """Velocity in local NED and a heading: MAVSDK's ``set_velocity_ned``."""
    return PositionTarget(mavlink.MAV_FRAME_LOCAL_NED, TM_VELOCITY_YAW, vx_m_s=north_m_s, vy_m_s=east_m_s,
                          vz_m_s=down_m_s, yaw_rad=yaw_rad)


def position_velocity_accel_ned(p_ned_m: Iterable[float], v_ned_m_s: Iterable[float], a_ned_m_s2: Iterable[float],
                                yaw_rad: float) -> PositionTarget:
    """Position, velocity, acceleration in local NED (three numbers each) and a heading: a PX4 trajectory setpoint."""
    (x, y, z), (vx, vy, vz), (ax, ay, az) = _xyz(p_ned_m), _xyz(v_ned_m_s), _xyz(a_ned_m_s2)
    return PositionTarget(mavlink.MAV_FRAME_LOCAL_NED, TM_POSITION_VELOCITY_ACCEL_YAW, x, y, z, vx, vy, vz, ax, ay, az,
                          yaw_rad=float(yaw_rad))


def _xyz(v: Iterable[float]) -> tuple[float, float, float]:
    x, y, z = (float(c) for c in v)
    return x, y, z

"""Pure builders of the MAVLink messages the companion sends (no I/O; pack them with a MAVLink codec).

Conventions stated once here:

* Setpoints: SET_POSITION_TARGET_LOCAL_NED in MAV_FRAME_BODY_OFFSET_NED with type_mask 1479
  (velocity + yaw rate only). As PX4 and ArduPilot interpret it for velocity, the vector is expressed
  in the frame rotated by the vehicle's yaw only: that is H (x along the heading, z down).
* ODOMETRY: frame_id MAV_FRAME_LOCAL_FRD (the VO world frame, its x along the initial heading),
  child_frame_id MAV_FRAME_BODY_FRD; position in the world frame, quaternion [w, x, y, z] body->world,
  velocity and rates in body FRD (as PX4's vision interface expects). quality 0 = odometry failed
  (consumers must not use the estimate), else 1..100.
* OBSTACLE_DISTANCE: 72 sectors of 5 deg in MAV_FRAME_BODY_FRD (yaw-aligned, i.e. perception's H), sector
  i centred on ``angle_offset + 5 i`` deg clockwise from the heading (angle_offset 0 from perception), cm;
  unknown = UINT16_MAX, free = max_distance + 1; the distances are the avoidance's points
  (:meth:`companion.frame_state.FrameState.obstacle_sectors`).
* Times: autopilot time (SITL: simulated time), ms or us as each message asks.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from quadlink.frames import R_from_euler, R_hq, Rz, quat_wxyz_from_R
from quadlink.mavlink import mavlink
from quadlink.mavlink.setpoint_masks import TM_VELOCITY_ACCEL_YAW_RATE, TM_VELOCITY_YAW_RATE

TYPE_MASK_VELOCITY_YAW_RATE = TM_VELOCITY_YAW_RATE  # 1479: position, acceleration and yaw ignored
UINT16_UNKNOWN = 65535
N_SECTORS = 72
SECTOR_DEG = 5.0


def setpoint_message(time_s: float, target_system: int, target_component: int, v_h_m_s: ArrayLike,
                     yaw_rate_rad_s: float, accel_h_m_s2: ArrayLike | None = None) -> Any:
    """The velocity setpoint in H (BODY_OFFSET_NED, 1479); with ``accel_h_m_s2`` (a trajectory's feed-forward,
    issue 19) also the acceleration (mask TM_VELOCITY_ACCEL_YAW_RATE, 1031), which the bridge's geometric
    tracker (BRG_TRACKER 1) adds as eq. (4)'s a_d."""
    v = np.asarray(v_h_m_s, dtype=float)
    mask, a = TYPE_MASK_VELOCITY_YAW_RATE, np.zeros(3)
    if accel_h_m_s2 is not None:
        mask, a = TM_VELOCITY_ACCEL_YAW_RATE, np.asarray(accel_h_m_s2, dtype=float)
    return mavlink.MAVLink_set_position_target_local_ned_message(
        _ms(time_s), target_system, target_component, mavlink.MAV_FRAME_BODY_OFFSET_NED,
        mask, 0.0, 0.0, 0.0, float(v[0]), float(v[1]), float(v[2]), float(a[0]), float(a[1]), float(a[2]), 0.0,
        float(yaw_rate_rad_s))


def _ms(time_s: float) -> int:
    return int(max(time_s, 0.0) * 1e3) & 0xFFFFFFFF


def _us(time_s: float) -> int:
    return int(max(time_s, 0.0) * 1e6)


def velocity_body_m_s(v_h_m_s: ArrayLike, roll_rad: float, pitch_rad: float) -> NDArray[np.float64]:
    """v_q = R_hq^T v_h (eq. 13 inverted)."""
    return R_hq(roll_rad, pitch_rad).T @ np.asarray(v_h_m_s, dtype=float)


def quality_percent(ok: bool, fitness: float) -> int:
    if not ok:
        return 0
    if not math.isfinite(fitness):
        return 50
    return int(min(100, max(1, round(100.0 * min(max(fitness, 0.0), 1.0)))))


def odometry_message(time_s: float, position_m: ArrayLike | None, roll_rad: float, pitch_rad: float, yaw_rad: float,
                     v_h_m_s: ArrayLike, omega_q_rad_s: ArrayLike, v_h_cov: ArrayLike | None, ok: bool,
                     fitness: float, reset_counter: int) -> Any:
    p = np.zeros(3) if position_m is None else np.asarray(position_m, dtype=float)
    q = quat_wxyz_from_R(R_from_euler(roll_rad, pitch_rad, yaw_rad))
    v_q = velocity_body_m_s(v_h_m_s, roll_rad, pitch_rad)
    w = np.asarray(omega_q_rad_s, dtype=float)
    pose_cov = [math.nan] + [0.0] * 20  # NaN first element: pose covariance unknown (MAVLink convention)
    vel_cov = [math.nan] + [0.0] * 20
    if v_h_cov is not None:
        C = np.asarray(v_h_cov, dtype=float)
        if C.shape == (3, 3) and np.all(np.isfinite(C)):
            R = R_hq(roll_rad, pitch_rad).T
            C = R @ C @ R.T
            # upper triangle of the 6x6 (vx, vy, vz, wx, wy, wz) covariance, row-major
            full = np.zeros((6, 6))
            full[:3, :3] = C
            full[3:, 3:] = np.eye(3) * 1e-4
            vel_cov = [float(full[i, j]) for i in range(6) for j in range(i, 6)]
    return mavlink.MAVLink_odometry_message(
        _us(time_s), mavlink.MAV_FRAME_LOCAL_FRD, mavlink.MAV_FRAME_BODY_FRD, float(p[0]), float(p[1]), float(p[2]),
        [float(x) for x in q], float(v_q[0]), float(v_q[1]), float(v_q[2]), float(w[0]), float(w[1]), float(w[2]),
        pose_cov, vel_cov, reset_counter & 0xFF, mavlink.MAV_ESTIMATOR_TYPE_VIO, quality_percent(ok, fitness))


def local_position_message(time_s: float, position_m: ArrayLike | None, yaw_rad: float, v_h_m_s: ArrayLike) -> Any:
    p = np.zeros(3) if position_m is None else np.asarray(position_m, dtype=float)
    v_w = Rz(yaw_rad) @ np.asarray(v_h_m_s, dtype=float)
    return mavlink.MAVLink_local_position_ned_message(_ms(time_s), float(p[0]), float(p[1]), float(p[2]),
                                                      float(v_w[0]), float(v_w[1]), float(v_w[2]))


def attitude_message(time_s: float, roll_rad: float, pitch_rad: float, yaw_rad: float, omega_q_rad_s: ArrayLike) -> Any:
    w = np.asarray(omega_q_rad_s, dtype=float)
    return mavlink.MAVLink_attitude_message(_ms(time_s), float(roll_rad), float(pitch_rad), float(yaw_rad),
                                            float(w[0]), float(w[1]), float(w[2]))


def sector_arrays(sectors: Any) -> tuple[NDArray[np.float64] | None, float, float]:
    """(distances_m, increment_deg, angle_offset_deg) of perception's ObstacleSectors or of a bare array
    (72 sectors of 5 deg, sector 0 centred on the heading)."""
    if sectors is None:
        return None, SECTOR_DEG, 0.0
    if hasattr(sectors, "distances_m"):
        return (np.asarray(sectors.distances_m, dtype=float), float(sectors.increment_deg),
                float(sectors.angle_offset_deg))
    return np.asarray(sectors, dtype=float), SECTOR_DEG, 0.0


def obstacle_distances_cm(sectors_m: ArrayLike | None, min_cm: int, max_cm: int) -> list[int]:
    """72 sector distances in cm: NaN (unknown) -> UINT16_MAX, inf/beyond range (free) -> max + 1."""
    out = [UINT16_UNKNOWN] * N_SECTORS
    if sectors_m is None:
        return out
    s = np.asarray(sectors_m, dtype=float).ravel()[:N_SECTORS]
    for i, d in enumerate(s):
        if math.isnan(d):
            continue
        cm = d * 100.0
        out[i] = max_cm + 1 if (math.isinf(cm) or cm > max_cm) else int(max(min_cm, round(cm)))
    return out


def obstacle_distance_message(time_s: float, sectors: Any, min_cm: int, max_cm: int) -> Any:
    """OBSTACLE_DISTANCE from perception's ObstacleSectors (or a bare 72-array, sector 0 centred ahead)."""
    distances, inc_deg, offset_deg = sector_arrays(sectors)
    return mavlink.MAVLink_obstacle_distance_message(
        _us(time_s), mavlink.MAV_DISTANCE_SENSOR_INFRARED, obstacle_distances_cm(distances, min_cm, max_cm),
        int(round(inc_deg)), min_cm, max_cm, inc_deg, offset_deg, mavlink.MAV_FRAME_BODY_FRD)


# TELEOP_FEEDBACK.flags: the dialect's QUADLINK_TELEOP_FLAGS
FLAG_PAN_SCAN = mavlink.QUADLINK_TELEOP_FLAGS_PAN_SCAN_ON
FLAG_ODOMETRY_OK = mavlink.QUADLINK_TELEOP_FLAGS_ODOMETRY_OK
FLAG_GCS_OK = mavlink.QUADLINK_TELEOP_FLAGS_GCS_LINK_OK
FLAG_OBSTACLES_FRESH = mavlink.QUADLINK_TELEOP_FLAGS_OBSTACLES_FRESH


def feedback_flags(pan_scan_on: bool, odometry_ok: bool, gcs_ok: bool, obstacles_fresh: bool) -> int:
    return ((FLAG_PAN_SCAN if pan_scan_on else 0) | (FLAG_ODOMETRY_OK if odometry_ok else 0)
            | (FLAG_GCS_OK if gcs_ok else 0) | (FLAG_OBSTACLES_FRESH if obstacles_fresh else 0))


def teleop_feedback_message(time_s: float, v_est_h_m_s: ArrayLike, v_cmd_h_m_s: ArrayLike, v_rep_h_m_s: ArrayLike,
                            alpha_rad: float, pan_scan_yaw_rate_rad_s: float, yaw_rate_cmd_rad_s: float,
                            gyro_yaw_rate_rad_s: float, nearest_obstacle_h_m: ArrayLike, obstacle_distance_m: float,
                            mode: int, flags: int) -> Any:
    """The dialect's TELEOP_FEEDBACK (all vectors in H; obstacle_distance -1 = none)."""
    e, c, r, o = (np.asarray(x, dtype=float) for x in (v_est_h_m_s, v_cmd_h_m_s, v_rep_h_m_s, nearest_obstacle_h_m))
    return mavlink.MAVLink_teleop_feedback_message(
        _us(time_s), float(e[0]), float(e[1]), float(e[2]), float(c[0]), float(c[1]), float(c[2]),
        float(r[0]), float(r[1]), float(r[2]), float(alpha_rad), float(pan_scan_yaw_rate_rad_s),
        float(yaw_rate_cmd_rad_s), float(gyro_yaw_rate_rad_s), float(o[0]), float(o[1]), float(o[2]),
        float(obstacle_distance_m), int(mode) & 0xFF, int(flags) & 0xFF)


def heartbeat_message(mode: int) -> Any:
    """The companion's HEARTBEAT: an onboard controller, not an autopilot, its mode (QUADLINK_TELEOP_MODE) as
    custom_mode."""
    return mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0,
                                             int(mode), mavlink.MAV_STATE_ACTIVE, 3)

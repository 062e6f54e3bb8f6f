"""Pure message builders and TIMESYNC of the companion."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.messages import (
    obstacle_distance_message,
    obstacle_distances_cm,
    odometry_message,
    quality_percent,
    setpoint_message,
    velocity_body_m_s,
)
from companion.timesync import TimeSync
from perception.pipeline import ObstacleSectors
from quadlink.frames import R_from_quat_wxyz, R_hq, euler_yaw_rate_rad_s
from quadlink.mavlink import mavlink


def _roundtrip(msg):  # noqa: ANN001, ANN202 - pack and parse with the dialect codec
    mav = mavlink.MAVLink(None, 1, 191)
    return mavlink.MAVLink(None).parse_char(bytes(msg.pack(mav)))


def test_obstacle_distances_unknown_free_and_clamped() -> None:
    d = np.full(72, np.nan)
    d[0], d[1], d[2], d[3] = np.inf, 1.234, 0.2, 9.0
    cm = obstacle_distances_cm(d, 50, 350)
    assert cm[:5] == [351, 123, 50, 351, 65535]
    assert obstacle_distances_cm(None, 50, 350) == [65535] * 72
    sectors = ObstacleSectors(1.5, d, 5.0, 0.0, 0.3, 3.5)
    m = _roundtrip(obstacle_distance_message(1.5, sectors, 50, 350))
    assert m.time_usec == 1_500_000 and m.increment == 5 and m.increment_f == 5.0 and m.angle_offset == 0.0
    assert m.frame == mavlink.MAV_FRAME_BODY_FRD and list(m.distances[:3]) == [351, 123, 50]


def test_setpoint_is_velocity_and_yaw_rate_in_body_offset_ned() -> None:
    m = _roundtrip(setpoint_message(2.345, 1, 1, [0.5, -0.2, 0.1], 0.3))
    assert (m.time_boot_ms, m.coordinate_frame, m.type_mask) == (2345, mavlink.MAV_FRAME_BODY_OFFSET_NED, 1479)
    assert (m.vx, m.vy, m.vz, m.yaw_rate) == pytest.approx((0.5, -0.2, 0.1, 0.3))


def test_odometry_velocity_is_body_frd_and_quality_zero_on_failure() -> None:
    roll, pitch, yaw = 0.1, -0.2, 1.0
    v_h = np.array([0.4, 0.1, -0.05])
    m = _roundtrip(odometry_message(3.0, [1, 2, -1], roll, pitch, yaw, v_h, [0.01, 0.02, 0.3], np.eye(3) * 0.01,
                                    True, 0.8, 2))
    v_q = np.array([m.vx, m.vy, m.vz])
    assert R_hq(roll, pitch) @ v_q == pytest.approx(v_h, abs=1e-6)  # eq. (13) back to H
    assert np.allclose(velocity_body_m_s(v_h, roll, pitch), v_q, atol=1e-6)
    R = R_from_quat_wxyz(list(m.q))
    assert math.atan2(R[1, 0], R[0, 0]) == pytest.approx(yaw, abs=1e-6)
    assert (m.frame_id, m.child_frame_id) == (mavlink.MAV_FRAME_LOCAL_FRD, mavlink.MAV_FRAME_BODY_FRD)
    assert m.quality == 80 and m.reset_counter == 2 and m.estimator_type == mavlink.MAV_ESTIMATOR_TYPE_VIO
    assert m.velocity_covariance[0] > 0 and math.isnan(m.pose_covariance[0])
    failed = _roundtrip(odometry_message(3.0, None, 0, 0, 0, v_h, np.zeros(3), None, False, 0.8, 2))
    assert failed.quality == 0
    assert quality_percent(True, 0.0) == 1 and quality_percent(True, 5.0) == 100


def test_euler_yaw_rate_from_body_rates() -> None:
    assert euler_yaw_rate_rad_s([0.0, 0.0, 0.5], 0.0, 0.0) == pytest.approx(0.5)
    roll, pitch = 0.3, 0.2
    expected = (0.1 * math.sin(roll) + 0.5 * math.cos(roll)) / math.cos(pitch)
    assert euler_yaw_rate_rad_s([0.0, 0.1, 0.5], roll, pitch) == pytest.approx(expected)


def test_timesync_keeps_the_minimum_round_trip_offset() -> None:
    ts = TimeSync()
    assert ts.to_remote_s(1.0) is None
    offset = 5_000_000_000  # remote clock 5 s ahead
    # symmetric 2 ms round trip: exact; a 20 ms asymmetric one is ignored in favour of the better sample
    assert ts.on_response(10_000_000 + 1_000_000 + offset, 10_000_000, 12_000_000)
    assert ts.on_response(20_000_000 + 18_000_000 + offset, 20_000_000, 40_000_000)
    assert ts.offset_ns == offset and ts.rtt_ns == 2_000_000
    assert ts.to_remote_s(1.0) == pytest.approx(6.0)
    assert not ts.on_response(0, 1, 2) and not ts.on_response(10, 0, 10**9)

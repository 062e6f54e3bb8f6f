"""Rotation helpers: conventions checked against hand-derived cases and round trips."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from quadlink import frames
from quadlink.lie import angle_between_rad, skew

angles = st.floats(min_value=-3.0, max_value=3.0)


def test_euler_conventions_ned() -> None:
    # yaw +90 deg: body x (forward) points east (world y)
    assert np.allclose(frames.R_from_euler(0, 0, math.pi / 2) @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    # pitch +30 deg (nose up): body x gets a negative (up) z component in NED
    assert frames.R_from_euler(0, math.radians(30), 0)[2, 0] < 0
    # roll +30 deg (right wing down): body y gets a positive (down) z component
    assert frames.R_from_euler(math.radians(30), 0, 0)[2, 1] > 0


@given(angles, st.floats(min_value=-1.5, max_value=1.5), angles)
def test_euler_round_trip(roll: float, pitch: float, yaw: float) -> None:
    R = frames.R_from_euler(roll, pitch, yaw)
    assert np.allclose(frames.R_from_euler(*frames.euler_from_R(R)), R, atol=1e-9)


@given(angles, st.floats(min_value=-1.5, max_value=1.5), angles)
def test_quaternion_round_trip_wxyz(roll: float, pitch: float, yaw: float) -> None:
    R = frames.R_from_euler(roll, pitch, yaw)
    q = frames.quat_wxyz_from_R(R)
    assert q[0] >= 0 and math.isclose(float(np.linalg.norm(q)), 1.0, rel_tol=1e-12)
    assert angle_between_rad(frames.R_from_quat_wxyz(q), R) < 1e-6


def test_quaternion_order_is_wxyz() -> None:
    q = frames.quat_wxyz_from_euler(0.0, 0.0, math.pi / 2)
    assert np.allclose(q, [math.cos(math.pi / 4), 0, 0, math.sin(math.pi / 4)])


def test_horizontal_frame_removes_tilt_only() -> None:
    roll, pitch, yaw = 0.2, -0.1, 1.0
    R_wq = frames.R_from_euler(roll, pitch, yaw)
    v_q = np.array([1.0, 0.5, -0.2])
    v_h = frames.R_hq(roll, pitch) @ v_q
    assert np.allclose(frames.Rz(yaw) @ v_h, R_wq @ v_q)


def test_nwu_ned_is_involution_and_wrap() -> None:
    assert np.allclose(frames.R_NED_NWU @ frames.R_NED_NWU, np.eye(3))
    assert frames.wrap_pi(3 * math.pi) == -math.pi
    assert math.isclose(frames.wrap_pi(-0.5), -0.5)
    assert np.allclose(skew(np.array([1.0, 2, 3])) @ [4, 5, 6], np.cross([1, 2, 3], [4, 5, 6]))


@given(angles, st.floats(min_value=-1.5, max_value=1.5), st.tuples(angles, angles, angles))
def test_euler_yaw_rate_is_the_derivative_of_yaw(roll: float, pitch: float, omega: tuple[float, float, float]) -> None:
    """Independent check: integrate the body rates over a tiny step and difference the ZYX yaw."""
    from quadlink.lie import so3_exp

    w = np.array(omega)
    R0 = frames.R_from_euler(roll, pitch, 0.3)
    h = 1e-6
    yaw1 = frames.euler_from_R(R0 @ so3_exp(w * h))[2]
    yaw0 = frames.euler_from_R(R0 @ so3_exp(-w * h))[2]
    expected = frames.wrap_pi(yaw1 - yaw0) / (2 * h)
    assert math.isclose(frames.euler_yaw_rate_rad_s(w, roll, pitch), expected, rel_tol=1e-4, abs_tol=1e-4)


def test_euler_yaw_rate_beyond_90_deg_pitch_keeps_its_sign_and_is_bounded_at_gimbal_lock() -> None:
    w = [0.0, 0.0, 0.5]
    assert frames.euler_yaw_rate_rad_s(w, 0.0, math.radians(120)) == pytest.approx(0.5 / math.cos(math.radians(120)))
    assert frames.euler_yaw_rate_rad_s(w, 0.0, math.pi / 2) == 0.5

"""Velocity tracker (firmware_bridge.velocity_tracker) in closed loop with a point-mass quadrotor model."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from firmware_bridge.velocity_tracker import TrackerGains, VelocityTracker
from quadlink.frames import GRAVITY_M_S2, R_hq

MASS_KG = 1.0
T_MAX_N = 20.0
DT_S = 0.01


def simulate(tracker: VelocityTracker, v_ref_h, seconds: float, disturbance_n=(0.0, 0.0, 0.0),
             attitude_tau_s: float = 0.05, drag_n_s_m=(0.25, 0.25, 0.35)):
    """Point mass in H (NED, yaw fixed); attitude follows the command with a first-order lag."""
    v = np.zeros(3)
    roll = pitch = 0.0
    d = np.asarray(disturbance_n, dtype=float)
    drag = np.asarray(drag_n_s_m, dtype=float)
    history = []
    for _ in range(int(round(seconds / DT_S))):
        cmd = tracker.update(DT_S, np.asarray(v_ref_h, dtype=float), 0.0, v, roll, pitch)
        a = 1.0 - math.exp(-DT_S / attitude_tau_s)
        roll += a * (cmd.roll_rad - roll)
        pitch += a * (cmd.pitch_rad - pitch)
        thrust_n = cmd.thrust_fraction * T_MAX_N
        R = R_hq(roll, pitch)
        acc = np.array([0.0, 0.0, GRAVITY_M_S2]) - thrust_n / MASS_KG * (R @ np.array([0.0, 0.0, 1.0])) \
            + (d - drag * v) / MASS_KG
        v = v + acc * DT_S
        history.append((v.copy(), cmd))
    return v, history


def test_hover_thrust_and_level_attitude_at_rest():
    tracker = VelocityTracker(MASS_KG, T_MAX_N)
    cmd = tracker.update(DT_S, np.zeros(3), 0.0, np.zeros(3), 0.0, 0.0)
    assert cmd.thrust_fraction == pytest.approx(MASS_KG * GRAVITY_M_S2 / T_MAX_N, rel=1e-9)
    assert cmd.roll_rad == 0.0 and cmd.pitch_rad == 0.0


def test_hover_compensation_grows_with_measured_tilt():
    tracker = VelocityTracker(MASS_KG, T_MAX_N)
    tilt = math.radians(20.0)
    cmd = tracker.update(DT_S, np.zeros(3), 0.0, np.zeros(3), tilt, tilt)
    assert cmd.thrust_fraction == pytest.approx(MASS_KG * GRAVITY_M_S2 / (math.cos(tilt) ** 2) / T_MAX_N, rel=1e-9)


def test_angles_are_exact_inverse_of_thrust_direction():
    tracker = VelocityTracker(MASS_KG, T_MAX_N)
    for a_des in ([2.0, 0.0, 0.0], [0.0, -1.5, 0.0], [1.0, 1.0, -2.0], [-0.5, 0.7, 1.0]):
        a_des = np.array(a_des)
        roll, pitch = tracker.angles_from_acceleration(a_des)
        f = a_des - np.array([0.0, 0.0, GRAVITY_M_S2])
        b3 = R_hq(roll, pitch) @ np.array([0.0, 0.0, 1.0])
        np.testing.assert_allclose(b3, -f / np.linalg.norm(f), atol=1e-12)


def test_forward_acceleration_pitches_nose_down_and_right_rolls_right():
    tracker = VelocityTracker(MASS_KG, T_MAX_N)
    cmd = tracker.update(DT_S, np.array([1.0, 0.0, 0.0]), 0.0, np.zeros(3), 0.0, 0.0)
    assert cmd.pitch_rad < -0.05 and abs(cmd.roll_rad) < 1e-12
    tracker.reset()
    cmd = tracker.update(DT_S, np.array([0.0, 1.0, 0.0]), 0.0, np.zeros(3), 0.0, 0.0)
    assert cmd.roll_rad > 0.05 and abs(cmd.pitch_rad) < 1e-12


@pytest.mark.parametrize("v_ref", [(1.0, 0.0, 0.0), (0.0, -0.8, 0.0), (0.5, 0.5, -0.5), (0.0, 0.0, 0.4)])
def test_step_response_settles(v_ref):
    tracker = VelocityTracker(MASS_KG, T_MAX_N)
    v, history = simulate(tracker, v_ref, 6.0)
    np.testing.assert_allclose(v, v_ref, atol=0.02)
    # overshoot bounded (the PID is not tuned to ring)
    peak = max(float(np.dot(h[0], v_ref)) for h in history) / max(float(np.dot(v_ref, v_ref)), 1e-9)
    assert peak < 1.3


def test_integral_removes_steady_state_error_under_constant_disturbance():
    disturbance = (1.0, -0.6, 1.5)  # N: wind and a payload heavier than modelled
    with_i = VelocityTracker(MASS_KG, T_MAX_N)
    v_i, _ = simulate(with_i, (0.5, 0.0, 0.0), 15.0, disturbance)
    np.testing.assert_allclose(v_i, (0.5, 0.0, 0.0), atol=0.02)
    np.testing.assert_allclose(with_i.integral_h_m_s2[:2], [-1.0 + 0.25 * 0.5, 0.6], atol=0.05)

    no_i = VelocityTracker(MASS_KG, T_MAX_N, TrackerGains(ki_xy_1_s2=0.0, ki_z_1_s2=0.0))
    v_p, _ = simulate(no_i, (0.5, 0.0, 0.0), 15.0, disturbance)
    assert np.linalg.norm(v_p - np.array([0.5, 0.0, 0.0])) > 0.2  # P only leaves an error: the test can fail


def test_limits_tilt_speed_climb_and_yaw_rate():
    gains = TrackerGains(max_tilt_rad=math.radians(15.0), max_speed_xy_m_s=1.0, max_climb_m_s=0.5,
                         max_yaw_rate_rad_s=1.0)
    tracker = VelocityTracker(MASS_KG, T_MAX_N, gains)
    cmd = tracker.update(DT_S, np.array([10.0, 10.0, -5.0]), 3.0, np.zeros(3), 0.0, 0.0)
    tilt = math.acos(math.cos(cmd.roll_rad) * math.cos(cmd.pitch_rad))
    assert tilt <= math.radians(15.0) + 1e-9
    assert cmd.yaw_rate_rad_s == pytest.approx(1.0)
    v_ref, _ = tracker.clamp_reference(np.array([10.0, 10.0, -5.0]), 0.0)
    assert math.hypot(v_ref[0], v_ref[1]) == pytest.approx(1.0)
    assert v_ref[2] == pytest.approx(-0.5)
    # a large velocity error saturates on the tilt limit
    cmd = tracker.update(DT_S, np.array([1.0, 0.0, 0.0]), 0.0, np.array([-3.0, 0.0, 0.0]), 0.0, 0.0)
    assert cmd.saturated
    assert abs(cmd.pitch_rad) == pytest.approx(math.radians(15.0), abs=1e-6)
    tracker.reset()
    v, _ = simulate(tracker, (10.0, 0.0, -5.0), 8.0)
    assert v[0] == pytest.approx(1.0, abs=0.03) and v[2] == pytest.approx(-0.5, abs=0.03)


def test_anti_windup_bounds_the_integral_and_recovers_quickly():
    tracker = VelocityTracker(MASS_KG, T_MAX_N)
    # a long saturated push against a wall (velocity stays 0 while 3 m/s is asked)
    for _ in range(2000):
        tracker.update(DT_S, np.array([3.0, 0.0, 0.0]), 0.0, np.zeros(3), 0.0, 0.0)
    assert np.all(np.abs(tracker.integral_h_m_s2) <= tracker.gains.integral_max_xy_m_s2 + 1e-12)
    v, _ = simulate(tracker, (0.0, 0.0, 0.0), 4.0)
    assert np.linalg.norm(v) < 0.1


def test_non_finite_estimate_is_a_safe_fallback():
    tracker = VelocityTracker(MASS_KG, T_MAX_N)
    cmd = tracker.update(DT_S, np.zeros(3), 0.0, np.array([np.nan, 0.0, 0.0]), 0.0, 0.0)
    assert all(math.isfinite(x) for x in (cmd.roll_rad, cmd.pitch_rad, cmd.thrust_fraction))


@settings(max_examples=200, deadline=None)
@given(v_ref=arrays(np.float64, 3, elements=st.floats(-50, 50)),
       v_est=arrays(np.float64, 3, elements=st.floats(-50, 50)),
       yaw_rate=st.floats(-20, 20), roll=st.floats(-1.2, 1.2), pitch=st.floats(-1.2, 1.2),
       dt=st.floats(0.0, 1.0))
def test_output_always_finite_and_within_limits(v_ref, v_est, yaw_rate, roll, pitch, dt):
    gains = TrackerGains()
    tracker = VelocityTracker(MASS_KG, T_MAX_N, gains)
    for _ in range(3):
        cmd = tracker.update(dt, v_ref, yaw_rate, v_est, roll, pitch)
        assert all(math.isfinite(x) for x in (cmd.roll_rad, cmd.pitch_rad, cmd.yaw_rate_rad_s, cmd.thrust_fraction))
        assert math.acos(math.cos(cmd.roll_rad) * math.cos(cmd.pitch_rad)) <= gains.max_tilt_rad + 1e-6
        assert gains.thrust_min_fraction <= cmd.thrust_fraction <= gains.thrust_max_fraction
        assert abs(cmd.yaw_rate_rad_s) <= gains.max_yaw_rate_rad_s + 1e-12
    assert np.all(np.abs(tracker.integral_h_m_s2) <= [gains.integral_max_xy_m_s2] * 2 + [gains.integral_max_z_m_s2])

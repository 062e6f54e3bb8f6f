"""The companion's position loop (companion.trajectory_follow) in cascade with the bridge's geometric tracker."""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_bridge_geometric_tracker import DT_S, MASS_KG, OVAL_DURATIONS_S, OVAL_NED_M, T_MAX_N, RigidBody

from companion.trajectory_follow import FollowGains, TrajectoryFollower, position_loop
from firmware_bridge.geometric_tracker import GeometricTracker, TrackingState, TrajectoryTarget
from quadlink.mavlink import mavlink
from quadlink.trajectory import TrajectorySample, minimum_snap

OVAL = minimum_snap(OVAL_NED_M, OVAL_DURATIONS_S)


def test_position_loop_is_v_d_minus_kp_ex_with_a_d_feed_forward() -> None:
    s = TrajectorySample(1.0, np.array([1.0, 2.0, -1.0]), np.array([0.5, 0.0, 0.0]), np.array([0.1, 0.2, 0.0]),
                         np.zeros(3))
    cmd = position_loop(s, [1.2, 1.9, -1.0], FollowGains(k_p_1_s=2.0))
    np.testing.assert_allclose(cmd.e_x_ned_m, [0.2, -0.1, 0.0], atol=1e-12)
    np.testing.assert_allclose(cmd.v_ref_ned_m_s, [0.5 - 0.4, 0.2, 0.0], atol=1e-12)
    np.testing.assert_allclose(cmd.a_ff_ned_m_s2, [0.1, 0.2, 0.0])
    far = position_loop(s, [11.0, 2.0, -1.0], FollowGains(k_p_1_s=2.0, max_correction_m_s=1.0))
    np.testing.assert_allclose(far.v_ref_ned_m_s, [-0.5, 0.0, 0.0], atol=1e-12)  # correction clamped to 1 m/s
    v_h, a_h = cmd.in_h(np.pi / 2)
    np.testing.assert_allclose(v_h, [0.2, -0.1, 0.0], atol=1e-12)


def _cascade(companion_period_s: float, seconds: float, noise_m: float = 0.0, seed: int = 0):
    """Companion (position loop at its odometry rate, zero-order hold) -> bridge tracker update() at 100 Hz."""
    rng = np.random.default_rng(seed)
    body = RigidBody(p=OVAL_NED_M[0].copy())
    tracker = GeometricTracker(MASS_KG, T_MAX_N)
    follower = TrajectoryFollower(OVAL, start_s=0.0)
    cmd = None
    next_companion_s = 0.0
    rows = []
    for k in range(int(round(seconds / DT_S))):
        t = k * DT_S
        if t >= next_companion_s - 1e-9:
            cmd = follower.step(t, body.p + rng.normal(scale=noise_m, size=3) if noise_m else body.p)
            next_companion_s += companion_period_s
        assert cmd is not None
        v_h, a_h = cmd.in_h(body.yaw)
        yaw_rate = -1.5 * body.yaw  # the autopilot's heading hold (MC_YAW_P) around the tracker, heading 0
        c = tracker.update(DT_S, v_h, yaw_rate, body.v.copy(), body.roll, body.pitch, a_ref_h=a_h)
        s = follower.sample(t)
        rows.append((body.p.copy(), body.v.copy(), s.p_m, s.v_m_s))
        body.step(c.roll_rad, c.pitch_rad, c.yaw_rate_rad_s, c.thrust_fraction)
    a = np.array(rows)
    return a[:, 0], a[:, 1], a[:, 2], a[:, 3]


def test_the_cascade_at_100_hz_is_eq_4_with_kx_equal_kv_kp() -> None:
    """The companion's loop + the velocity-only tracker fly the same path as the full-state tracker."""
    p_c, _, _, _ = _cascade(DT_S, 4.0)
    body = RigidBody(p=OVAL_NED_M[0].copy())
    full = GeometricTracker(MASS_KG, T_MAX_N)  # k_x 4.0 = k_v 3.2 * k_p 1.25
    p_f = []
    for k in range(400):
        s = OVAL.sample(k * DT_S)
        out = full.step(DT_S, TrajectoryTarget(s.v_m_s, s.a_m_s2, s.p_m, yaw_rad=0.0),
                        TrackingState(body.v.copy(), body.R, body.p.copy()))
        p_f.append(body.p.copy())
        c = out.attitude
        body.step(c.roll_rad, c.pitch_rad, c.yaw_rate_rad_s, c.thrust_fraction)
    # the same law; what differs is the heading: the full tracker sends Omega_c's body z rate (which holds the
    # heading while the tilt axis turns), update() the autopilot's heading hold, so the body's yaw differs by a few
    # mrad and the paths by about a millimetre
    diff = np.abs(p_c - np.array(p_f)).max()
    print(f"cascade vs full-state tracker: max path difference {diff * 1000:.2f} mm")
    assert diff < 3e-3


def test_the_oval_through_the_companion_at_camera_rate_with_odometry_noise() -> None:
    p, v, p_d, v_d = _cascade(1.0 / 30.0, OVAL.duration_s, noise_m=0.005, seed=4)
    rmse_p = np.sqrt(np.mean((p - p_d) ** 2, axis=0))
    rmse_v = np.sqrt(np.mean((v - v_d) ** 2, axis=0))
    print(f"cascade oval (30 Hz companion, 5 mm odometry noise): position RMSE {rmse_p} m, velocity RMSE {rmse_v} m/s")
    assert np.all(rmse_p <= 0.05), rmse_p  # issue 19's targets: 0.05 m and 0.06 m/s per axis
    assert np.all(rmse_v <= 0.06), rmse_v


def test_follower_starts_where_asked_and_ends() -> None:
    f = TrajectoryFollower(OVAL, start_s=10.0, origin_ned_m=[0.0, 0.0, -1.0])
    np.testing.assert_allclose(f.sample(10.0).p_m, [0.0, 0.0, -1.0], atol=1e-12)
    assert not f.done(18.9) and f.done(19.0)
    with pytest.raises(ValueError):
        f.step(11.0, [np.nan, 0.0, 0.0])


def test_setpoint_message_reaches_the_bridge_decoder_unchanged() -> None:
    """The companion's message through the real codec into the bridge's decoder (yaw-aligned frame both ways)."""
    from firmware_bridge.geometric_tracker import decode_trajectory_setpoint
    from quadlink.mavlink import mavlink

    s = OVAL.sample(2.0)
    cmd = position_loop(s, s.p_m + [0.05, -0.02, 0.01])
    yaw = 0.9
    buf = cmd.setpoint_message(12.0, 1, 1, yaw, 0.2).pack(mavlink.MAVLink(None, 1, 191))
    msg = mavlink.MAVLink(None).parse_char(buf)
    assert msg.type_mask == 1479 & ~0x1C0 == 1031
    tgt = decode_trajectory_setpoint(msg, yaw_rad=yaw)  # the bridge's yaw anchored to the same heading
    np.testing.assert_allclose(tgt.v_ned_m_s, cmd.v_ref_ned_m_s, atol=1e-6)
    np.testing.assert_allclose(tgt.a_ned_m_s2, cmd.a_ff_ned_m_s2, atol=1e-6)
    assert tgt.p_ned_m is None and tgt.yaw_rate_rad_s == pytest.approx(0.2)


def test_the_feed_forward_goes_only_with_the_velocity_the_safety_layer_left_alone() -> None:
    from companion.trajectory_follow import feed_forward_after_safety

    a = np.array([0.3, -0.2, 0.0])
    assert feed_forward_after_safety(a, False, np.zeros(3)) == pytest.approx(a)
    assert feed_forward_after_safety(a, True, np.zeros(3)) is None            # a constraint acted
    assert feed_forward_after_safety(a, False, [0.0, 0.05, 0.0]) is None     # repulsion added to the velocity
    assert feed_forward_after_safety(None, False, np.zeros(3)) is None
    assert feed_forward_after_safety([math.nan, 0.0, 0.0], False, np.zeros(3)) is None


def test_the_companion_setpoint_carries_the_feed_forward_as_the_bridge_reads_it() -> None:
    from companion.messages import setpoint_message
    from firmware_bridge.geometric_tracker import decode_trajectory_setpoint
    from quadlink.mavlink.setpoint_masks import TM_VELOCITY_ACCEL_YAW_RATE, TM_VELOCITY_YAW_RATE

    codec = mavlink.MAVLink(None, 1, 191)
    for accel, mask in ((None, TM_VELOCITY_YAW_RATE), ((0.4, -0.1, 0.0), TM_VELOCITY_ACCEL_YAW_RATE)):
        msg = setpoint_message(12.5, 1, 1, [0.5, 0.1, -0.05], 0.2, accel)
        got = mavlink.MAVLink(None, 1, 1).parse_char(msg.pack(codec))
        assert got.type_mask == mask and got.coordinate_frame == mavlink.MAV_FRAME_BODY_OFFSET_NED
        target = decode_trajectory_setpoint(got, yaw_rad=0.0)   # H unrotated
        assert target.v_ned_m_s == pytest.approx([0.5, 0.1, -0.05], abs=1e-6)
        assert target.a_ned_m_s2 == pytest.approx(accel or (0.0, 0.0, 0.0), abs=1e-6)

"""Attitude filter, 1€ filter, velocity in H (eqs. 9-13) and the UKF against analytic cases."""

from __future__ import annotations

import math

import numpy as np
import pytest

from perception.level import LevelConfig, OdometryLevel
from perception.one_euro import OneEuroConfig, OneEuroFilter, OneEuroQuaternion
from perception.synthetic import SyntheticFlight, pose
from perception.ukf import Ukf, UkfConfig
from perception.velocity import VelocityConfig, VelocityEstimator, body_pose_in_world
from quadlink.attitude import AttitudeConfig, AttitudeFilter
from quadlink.frames import GRAVITY_M_S2, R_from_euler, R_hq, Rz, euler_from_R, quat_wxyz_from_R
from quadlink.vehicle import load_vehicle

G = np.array([0.0, 0.0, GRAVITY_M_S2])


def _specific_force(R_wq: np.ndarray, a_w: np.ndarray | None = None) -> np.ndarray:
    a = np.zeros(3) if a_w is None else a_w
    return R_wq.T @ (a - G)


def test_level_at_rest_reads_minus_g_and_filter_stays_level() -> None:
    f = AttitudeFilter()
    for i in range(500):
        f.update(i * 0.002, np.zeros(3), np.array([0.0, 0.0, -GRAVITY_M_S2]))
        est = f.estimate()
    assert abs(est.roll_rad) < 1e-9 and abs(est.pitch_rad) < 1e-9


@pytest.mark.parametrize("roll,pitch", [(0.3, -0.2), (-0.5, 0.4)])
def test_complementary_filter_converges_to_true_tilt_with_gyro_bias(roll: float, pitch: float,
                                                                    rng: np.random.Generator) -> None:
    R = R_from_euler(roll, pitch, 0.7)
    bias = np.array([0.03, -0.02, 0.01])
    f = AttitudeFilter(AttitudeConfig(kp_rad_s=1.0, ki_rad_s2=0.1))
    # start from a wrong attitude: first sample says level
    f.update(0.0, np.zeros(3), np.array([0.0, 0.0, -GRAVITY_M_S2]))
    for i in range(1, 40 * 500):
        f.update(i * 0.002, bias + rng.normal(0, 0.005, 3), _specific_force(R) + rng.normal(0, 0.05, 3))
    est = f.estimate()
    assert est.roll_rad == pytest.approx(roll, abs=math.radians(0.3))
    assert est.pitch_rad == pytest.approx(pitch, abs=math.radians(0.3))
    # the roll/pitch-observable part of the bias is estimated (yaw axis bias is not observable from gravity)
    g_body = R.T @ np.array([0.0, 0.0, 1.0])
    b_perp = bias - g_body * (g_body @ bias)
    est_perp = est.gyro_bias_rad_s - g_body * (g_body @ est.gyro_bias_rad_s)
    assert np.allclose(est_perp, b_perp, atol=3e-3)


def test_constant_rotation_is_integrated_exactly_when_level() -> None:
    f = AttitudeFilter()
    rate = 0.5  # yaw rate, level: gravity stays on z
    for i in range(1001):
        f.update(i * 0.002, np.array([0.0, 0.0, rate]), np.array([0.0, 0.0, -GRAVITY_M_S2]))
        est = f.estimate()
    assert est.yaw_gyro_rad == pytest.approx(rate * 2.0, abs=1e-6)
    assert abs(est.roll_rad) < 1e-9 and abs(est.pitch_rad) < 1e-9
    assert est.omega_q_rad_s[2] == pytest.approx(rate, abs=1e-6)


def test_constant_roll_rate_tracks_truth_through_gyro() -> None:
    """Rolling at constant rate: the gyro carries the attitude; the accel correction must not fight it."""
    f = AttitudeFilter()
    rate = 0.4
    for i in range(751):
        t = i * 0.002
        R = R_from_euler(rate * t, 0.0, 0.0)
        f.update(t, np.array([rate, 0.0, 0.0]), _specific_force(R))
        est = f.estimate()
    assert est.roll_rad == pytest.approx(rate * 1.5, abs=1e-4)


def test_gyro_lowpass_rejects_noise(rng: np.random.Generator) -> None:
    f = AttitudeFilter(AttitudeConfig(gyro_lowpass_hz=10.0, ki_rad_s2=0.0))
    out = []
    for i in range(5000):
        f.update(i * 0.002, np.array([0.2, 0.0, 0.0]) + rng.normal(0, 0.05, 3), np.array([0.0, 0.0, -GRAVITY_M_S2]))
        out.append(f.estimate().omega_q_rad_s)
    o = np.array(out[500:])
    assert o[:, 0].mean() == pytest.approx(0.2, abs=0.005)
    assert o.std(axis=0).max() < 0.05 / 3  # first order at 10 Hz on 500 Hz white noise: ~0.05*sqrt(0.06)


def test_one_euro_rejects_noise_at_rest_and_follows_a_ramp(rng: np.random.Generator) -> None:
    f = OneEuroFilter(OneEuroConfig(min_cutoff_hz=1.0, beta=0.5))
    noisy = 1.0 + rng.normal(0, 0.01, (600, 3))
    out = np.array([f(i / 30, x) for i, x in enumerate(noisy)])
    # first-order low-pass at 1 Hz sampled at 30 Hz: std ratio sqrt(a / (2 - a)) ~ 0.31 at rest
    assert out[60:].std(axis=0).max() < 0.01 * 0.36
    # a fast ramp raises the cut-off: the lag stays small (1€ filter's purpose)
    g = OneEuroFilter(OneEuroConfig(min_cutoff_hz=1.0, beta=4.0))
    slow = OneEuroFilter(OneEuroConfig(min_cutoff_hz=1.0, beta=0.0))
    for i in range(90):
        x = np.array([0.5 * i / 30, 0.0, 0.0])
        a = g(i / 30, x)
        b = slow(i / 30, x)
    truth = 0.5 * 89 / 30
    assert truth - a[0] < 0.5 * (truth - b[0])
    assert truth - a[0] < 0.05


def test_one_euro_quaternion_stays_unit_and_sign_continuous() -> None:
    f = OneEuroQuaternion()
    q = quat_wxyz_from_R(R_from_euler(0.1, 0.2, 0.3))
    for i in range(30):
        out = f(i / 30, q if i % 2 else -q)
    assert np.linalg.norm(out) == pytest.approx(1.0)
    assert abs(abs(out @ q) - 1.0) < 1e-9


def _camera_pose_sequence(R_qc, p_qc, body_pose_fn, times):
    """T_c0_ck from a body pose function (R_wq, p_w) of time."""
    R0, p0 = body_pose_fn(times[0])
    T_w_c0 = pose(R0 @ R_qc, p0 + R0 @ p_qc)
    out = []
    for t in times:
        R, p = body_pose_fn(t)
        T_w_ck = pose(R @ R_qc, p + R @ p_qc)
        out.append(np.linalg.inv(T_w_c0) @ T_w_ck)
    return out


def test_velocity_pure_translation_in_h() -> None:
    veh = load_vehicle()
    R_qc, p_qc = veh.camera.R_qc_matrix, np.asarray(veh.camera.p_qc_m)
    roll, pitch, yaw = 0.1, -0.05, 0.3
    R = R_from_euler(roll, pitch, yaw)
    v_w = np.array([0.4, -0.2, 0.1])
    times = np.arange(60) / 30
    poses = _camera_pose_sequence(R_qc, p_qc, lambda t: (R, v_w * t), times)
    est = VelocityEstimator(R_qc, p_qc)
    for t, T in zip(times, poses):
        out = est.update(t, T, True, np.zeros(3), roll, pitch)
    assert out.valid
    assert np.allclose(out.v_h_m_s, Rz(yaw).T @ v_w, atol=2e-3)   # eq. (13): v_h = R_hq R^T v_w
    assert np.allclose(out.v_q_m_s, R.T @ v_w, atol=2e-3)


def test_a_failed_odometrys_last_velocity_decays_to_zero() -> None:
    """While the odometry fails the last velocity is not held for good (the map's time update moves on it): after
    one decay time it is e^-1 of what it was, after three e^-3. Held (``lost_decay_s`` 0), it stays (the control)."""
    veh = load_vehicle()
    R_qc, p_qc = veh.camera.R_qc_matrix, np.asarray(veh.camera.p_qc_m)
    v_w = np.array([0.4, -0.2, 0.1])
    times = np.arange(60) / 30
    poses = _camera_pose_sequence(R_qc, p_qc, lambda t: (np.eye(3), v_w * t), times)

    def fly(config: VelocityConfig) -> list:
        est = VelocityEstimator(R_qc, p_qc, config)
        out = [est.update(t, T, True, np.zeros(3), 0.0, 0.0) for t, T in zip(times[:30], poses[:30])]
        t_ok = times[29]
        out += [est.update(t_ok + dt, poses[29], False, np.zeros(3), 0.0, 0.0) for dt in (0.5, 1.5)]
        return out

    ok, one, three = fly(VelocityConfig(lost_decay_s=0.5))[-3:]
    assert ok.valid and np.allclose(ok.v_h_m_s, v_w, atol=5e-3)
    assert not one.valid and np.allclose(one.v_h_m_s, ok.v_h_m_s * math.exp(-1.0), atol=1e-9)
    assert not three.valid and np.allclose(three.v_h_m_s, ok.v_h_m_s * math.exp(-3.0), atol=1e-9)
    held = fly(VelocityConfig(lost_decay_s=0.0))[-1]
    assert np.allclose(held.v_h_m_s, ok.v_h_m_s, atol=1e-9)
    with pytest.raises(ValueError, match="lost_decay_s"):
        VelocityConfig(lost_decay_s=-1.0)


def test_velocity_constant_rotation_lever_arm_is_removed() -> None:
    """Yawing in place: the camera moves on a circle (lever arm), the body does not -> v ~ 0 (eq. 12)."""
    veh = load_vehicle()
    R_qc, p_qc = veh.camera.R_qc_matrix, np.asarray(veh.camera.p_qc_m)
    rate = 0.8
    times = np.arange(90) / 30
    poses = _camera_pose_sequence(R_qc, p_qc, lambda t: (Rz(rate * t), np.zeros(3)), times)
    est = VelocityEstimator(R_qc, p_qc, VelocityConfig())
    cam_speed = []
    for t, T in zip(times, poses):
        out = est.update(t, T, True, np.array([0.0, 0.0, rate]), 0.0, 0.0)
        cam_speed.append(np.linalg.norm(out.v_c_m_s))
    assert np.median(cam_speed[30:]) == pytest.approx(rate * np.linalg.norm(p_qc[:2]), rel=0.05)
    assert np.linalg.norm(out.v_h_m_s) < 0.01


def test_body_pose_in_world_inverts_the_extrinsics() -> None:
    veh = load_vehicle()
    R_qc, p_qc = veh.camera.R_qc_matrix, np.asarray(veh.camera.p_qc_m)
    R1, p1 = R_from_euler(0.1, 0.2, 0.9), np.array([1.0, -2.0, 0.5])
    (T,) = _camera_pose_sequence(R_qc, p_qc, lambda t: (np.eye(3), np.zeros(3)) if t == 0 else (R1, p1), [0, 1])[1:]
    R_wq, p_w = body_pose_in_world(T, R_qc, p_qc, np.eye(3))
    assert np.allclose(R_wq, R1, atol=1e-5)  # config R_qc has 6 decimals
    assert np.allclose(p_w, p1, atol=1e-9)


def test_ukf_fuses_imu_and_pose_to_the_true_velocity(rng: np.random.Generator) -> None:
    veh = load_vehicle()
    flight = SyntheticFlight(veh.camera.R_qc_matrix, np.asarray(veh.camera.p_qc_m))
    bias = np.array([0.15, -0.1, 0.2])
    ukf = Ukf(UkfConfig())
    ukf.initialise(0.0, flight.R_wq(0.0), flight.position(0.0))
    errs = []
    for i in range(1, 12 * 500):
        t = i / 500
        ukf.on_imu(t, flight.gyro(t) + rng.normal(0, 0.01, 3), flight.specific_force(t) + bias + rng.normal(0, 0.1, 3))
        if i % 17 == 0:
            st = ukf.on_pose(t, flight.position(t) + rng.normal(0, 0.005, 3), flight.R_wq(t))
            if t > 4.0:
                errs.append(st.velocity_w_m_s - flight.velocity(t))
    assert ukf.predictions >= 100 * 11  # >= 100 Hz output
    e = np.sqrt(np.mean(np.square(errs), axis=0))
    assert e.max() < 0.05
    st = ukf.state
    assert np.allclose(st.accel_bias_m_s2, bias, atol=0.05)
    assert np.allclose(st.v_h_m_s, flight.v_h(st.stamp_s), atol=0.05)
    assert np.allclose(st.v_h_m_s, R_hq(*flight.euler(t)[:2]) @ (flight.R_wq(t).T @ st.velocity_w_m_s), atol=0.01)


def _level_run(level: OdometryLevel, seconds: float, world_tilt: np.ndarray, filter_error_rad: float
               ) -> list[tuple[float, float, float, float, float, float]]:
    """30 Hz frames of a pan-scanning body (yaw +-0.5 rad, gentle roll and pitch): the odometry's attitude in a world
    tilted by ``world_tilt``, the filter's roll and pitch off by a manoeuvre-like +-``filter_error_rad`` (zero-mean,
    0.5 Hz); (true roll, true pitch, levelled roll, levelled pitch, the odometry's roll, pitch) per frame."""
    out = []
    for k in range(int(seconds * 30)):
        t = k / 30
        roll, pitch, yaw = 0.05 * math.sin(1.1 * t), 0.04 * math.sin(0.7 * t + 1.0), 0.5 * math.sin(1.5 * t)
        R_true = R_from_euler(roll, pitch, yaw)
        err = filter_error_rad * math.sin(math.pi * t)
        lr, lp = level.update(t, world_tilt @ R_true, roll + err, pitch - err)
        out.append((roll, pitch, lr, lp, *euler_from_R(world_tilt @ R_true)[:2]))
    return out


def test_odometry_level_removes_a_world_tilt_and_not_the_filter_s_manoeuvres() -> None:
    """The odometry's world tilted by 3 deg about a horizontal axis, the body pan-scanning: after five time
    constants the levelled roll and pitch are the truth within 0.05 deg (at the start they are the odometry's,
    3 deg off). With the world level and the filter 3 deg off back and forth (a manoeuvre's acceleration), the
    levelled attitude stays within 0.15 deg of the truth: the filter's errors average out."""
    tilt = R_from_euler(math.radians(2.4), math.radians(-1.8), 0.0)
    run = _level_run(OdometryLevel(LevelConfig(time_constant_s=2.0)), 10.0, tilt, 0.0)
    first, last = np.degrees(run[0]), np.degrees(run[-1])
    assert max(abs(first[2] - first[0]), abs(first[3] - first[1])) > 1.5
    assert abs(last[2] - last[0]) < 0.05 and abs(last[3] - last[1]) < 0.05
    run = _level_run(OdometryLevel(LevelConfig(time_constant_s=20.0)), 30.0, np.eye(3), math.radians(3.0))
    e = np.degrees(np.array([(r[2] - r[0], r[3] - r[1]) for r in run]))
    assert np.abs(e).max() < 0.15


def test_odometry_level_without_a_time_constant_keeps_the_odometry_s_attitude() -> None:
    tilt = R_from_euler(0.03, 0.0, 0.0)
    run = _level_run(OdometryLevel(LevelConfig(time_constant_s=0.0)), 2.0, tilt, 0.0)
    assert [r[2:4] for r in run] == [r[4:6] for r in run]

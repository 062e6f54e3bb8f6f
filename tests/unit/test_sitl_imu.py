"""IMU model: gravity at rest, quantisation (via the wire codec), noise, bias random walk, vibration."""

from __future__ import annotations

import math

import numpy as np
import pytest

from quadlink.frames import GRAVITY_M_S2, R_from_euler
from quadlink.mk.messages import ImuSample
from quadlink.vehicle import ImuConfig
from sim_sitl.config import ImuNoiseConfig
from sim_sitl.imu import ImuModel, specific_force_q

QUIET = ImuNoiseConfig(accel_noise_m_s2=0.0, gyro_noise_rad_s=0.0, accel_bias_walk_m_s2_sqrt_s=0.0,
                       gyro_bias_walk_rad_s_sqrt_s=0.0, accel_bias_init_m_s2=0.0, gyro_bias_init_rad_s=0.0,
                       vibration_accel_m_s2=0.0, vibration_gyro_rad_s=0.0)
DT = 0.002


def test_gravity_at_rest_level_and_rolled():
    np.testing.assert_allclose(specific_force_q(np.eye(3), np.zeros(3)), [0.0, 0.0, -GRAVITY_M_S2])
    # rolled 90 deg right: the right side (body +y) points down, the accelerometer reads -g on y
    np.testing.assert_allclose(specific_force_q(R_from_euler(math.pi / 2, 0, 0), np.zeros(3)),
                               [0.0, -GRAVITY_M_S2, 0.0], atol=1e-12)
    # pitched nose-up 30 deg: gravity shows on body +x
    f = specific_force_q(R_from_euler(0, math.radians(30), 0), np.zeros(3))
    assert f[0] == pytest.approx(GRAVITY_M_S2 * 0.5)
    model = ImuModel(QUIET, np.random.default_rng(0), 5.0)
    r = model.measure(0.0, DT, np.eye(3), np.zeros(3), np.zeros(3), np.zeros(4))
    cfg = ImuConfig()
    s = ImuSample.from_si(r.accel_q_m_s2, r.gyro_q_rad_s, cfg, 0)
    np.testing.assert_allclose(s.accel_m_s2(cfg), [0.0, 0.0, -GRAVITY_M_S2], atol=cfg.accel_lsb_m_s2 / 2)
    assert s.gyro_counts == (cfg.zero_count,) * 3


def test_quantisation_step_is_one_lsb_and_saturates_at_2g():
    cfg = ImuConfig()
    values = np.linspace(0.0, 1.0, 2001)  # m/s^2, much finer than one LSB (0.038 m/s^2)
    decoded = np.array([ImuSample.from_si([v, 0, 0], [0, 0, 0], cfg, 0).accel_m_s2(cfg)[0] for v in values])
    steps = np.diff(np.unique(decoded))
    np.testing.assert_allclose(steps, cfg.accel_lsb_m_s2, rtol=1e-9)
    assert np.max(np.abs(decoded - values)) <= cfg.accel_lsb_m_s2 / 2 + 1e-12
    sat = ImuSample.from_si([5 * GRAVITY_M_S2, -5 * GRAVITY_M_S2, 0], [10.0, 0, 0], cfg, 0)
    assert sat.accel_counts[:2] == (1023, 0) and sat.gyro_counts[0] == 1023
    assert sat.accel_m_s2(cfg)[0] == pytest.approx(2.0 * GRAVITY_M_S2, rel=0.01)  # +-2 g range
    assert sat.gyro_rad_s(cfg)[0] == pytest.approx(math.radians(300.0), rel=0.01)  # +-300 deg/s


def test_white_noise_sigma():
    cfg = ImuNoiseConfig(accel_bias_walk_m_s2_sqrt_s=0.0, gyro_bias_walk_rad_s_sqrt_s=0.0, vibration_accel_m_s2=0.0,
                         vibration_gyro_rad_s=0.0)
    model = ImuModel(cfg, np.random.default_rng(1), 5.0)
    acc = np.array([model.measure(k * DT, DT, np.eye(3), np.zeros(3), np.zeros(3), np.zeros(4)).accel_q_m_s2
                    for k in range(4000)])
    assert acc.std(axis=0) == pytest.approx([cfg.accel_noise_m_s2] * 3, rel=0.06)
    np.testing.assert_allclose(acc.mean(axis=0) - model.accel_bias_m_s2, [0, 0, -GRAVITY_M_S2], atol=0.01)


def test_bias_random_walk_statistics():
    density = 0.01
    cfg = ImuNoiseConfig(accel_noise_m_s2=0.0, gyro_noise_rad_s=0.0, accel_bias_walk_m_s2_sqrt_s=density,
                         gyro_bias_walk_rad_s_sqrt_s=density / 10, vibration_accel_m_s2=0.0,
                         vibration_gyro_rad_s=0.0)
    model = ImuModel(cfg, np.random.default_rng(2), 5.0)
    bias = []
    for k in range(20000):  # 40 s
        model.measure(k * DT, DT, np.eye(3), np.zeros(3), np.zeros(3), np.zeros(4))
        bias.append(model.accel_bias_m_s2.copy())
    bias = np.array(bias)
    steps = np.diff(bias, axis=0)
    assert steps.std() == pytest.approx(density * math.sqrt(DT), rel=0.03)  # per-sample increment
    # variance of the drift over windows of 0.4 s grows as density^2 * T
    drift = bias[200::200] - bias[:-200:200]
    assert drift.var() == pytest.approx(density ** 2 * 0.4, rel=0.2)
    assert abs(steps.mean()) < 5 * density * math.sqrt(DT) / math.sqrt(steps.size)


def test_vibration_grows_with_motor_thrust():
    cfg = ImuNoiseConfig(accel_noise_m_s2=0.0, gyro_noise_rad_s=0.0, accel_bias_walk_m_s2_sqrt_s=0.0,
                         gyro_bias_walk_rad_s_sqrt_s=0.0, accel_bias_init_m_s2=0.0, gyro_bias_init_rad_s=0.0)

    def spread(thrust_n: float) -> float:
        model = ImuModel(cfg, np.random.default_rng(4), 5.0)
        acc = np.array([model.measure(k * DT, DT, np.eye(3), np.zeros(3), np.zeros(3), np.full(4, thrust_n))
                        .accel_q_m_s2 for k in range(2000)])
        return float(np.linalg.norm(acc.std(axis=0)))

    idle, hover, full = spread(0.0), spread(2.45), spread(5.0)
    assert idle < 1e-9
    assert 0.05 < hover < full < 4 * cfg.vibration_accel_m_s2

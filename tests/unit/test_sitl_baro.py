"""The pressure sensor on ADC6 (sim_sitl/baro.py) and the sensor-to-pin laws of firmware/HARDWARE.md
(sim_sitl/avr_board.py): pure functions, no simavr."""

from __future__ import annotations

import math

import numpy as np
import pytest

from quadlink.mk.messages import ImuSample
from quadlink.vehicle import ImuConfig
from sim_sitl.avr_board import adc_count, imu_volts
from sim_sitl.baro import BaroConfig, BaroModel, amplified_v, pressure_from_adc_v, pressure_pa, sensor_v


def test_standard_atmosphere_reference_values() -> None:
    assert pressure_pa(0.0) == pytest.approx(101_325.0)
    assert pressure_pa(1000.0) == pytest.approx(89_874.6, abs=1.0)  # ISA table
    assert pressure_pa(120.0) - pressure_pa(121.0) == pytest.approx(11.9, abs=0.2)  # ~12 Pa per metre near ground


def test_mpx4115a_and_amplifier_laws() -> None:
    # HARDWARE.md: V_sensor = 5.0 (0.009 P_kPa - 0.095); V_adc = 2.5 + 10 (V_sensor - 4.05)
    assert sensor_v(100_000.0) == pytest.approx(5.0 * (0.9 - 0.095))
    p_mid = (4.05 / 5.0 + 0.095) / 0.009 * 1000.0
    assert amplified_v(sensor_v(p_mid)) == pytest.approx(2.5)
    # one ADC count (5 V / 1024 = 4.88 mV at the pin, 0.488 mV at the sensor, 0.045 mV/Pa) is 10.85 Pa, about
    # 0.9 m (HARDWARE.md's "about 6.1 Pa, 0.5 m per count" does not follow from its own laws: the laws win)
    pa_per_count = pressure_from_adc_v(2.5 + 5.0 / 1024) - pressure_from_adc_v(2.5)
    assert pa_per_count == pytest.approx(5.0 / 1024 / 10.0 / (5.0 * 0.009) * 1000.0)
    assert pa_per_count == pytest.approx(10.85, abs=0.01)
    # the rails
    assert amplified_v(sensor_v(80_000.0)) == 0.0
    assert amplified_v(sensor_v(120_000.0)) == 5.0
    for p in (96_000.0, 100_000.0, 105_000.0):
        assert pressure_from_adc_v(amplified_v(sensor_v(p))) == pytest.approx(p)


def test_site_altitude_keeps_the_arena_inside_the_rails() -> None:
    cfg = BaroConfig()
    for h in (0.0, 3.0, 50.0):
        v = amplified_v(sensor_v(pressure_pa(cfg.site_altitude_m + h)))
        assert 0.5 < v < 4.5


def test_noise_drift_and_offset_statistics() -> None:
    cfg = BaroConfig(offset_sigma_pa=0.0, drift_pa_sqrt_s=0.0, noise_pa=4.0)
    model = BaroModel(cfg, np.random.default_rng(3))
    truth = pressure_pa(cfg.site_altitude_m + 1.0)
    samples = []
    for _ in range(5000):
        model.measure(1.0, 0.002)
        samples.append(model.last_pressure_pa - truth)
    assert np.mean(samples) == pytest.approx(0.0, abs=0.3)
    assert np.std(samples) == pytest.approx(4.0, rel=0.05)

    # a random walk: its spread after t grows as drift * sqrt(t)
    drift_cfg = BaroConfig(offset_sigma_pa=0.0, drift_pa_sqrt_s=2.0, noise_pa=0.0)
    ends = []
    for seed in range(200):
        m = BaroModel(drift_cfg, np.random.default_rng(seed))
        for _ in range(500):  # 1 s
            m.measure(0.0, 0.002)
        ends.append(m.drift_pa)
    assert np.std(ends) == pytest.approx(2.0, rel=0.15)

    offsets = [BaroModel(BaroConfig(), np.random.default_rng(s)).offset_pa for s in range(400)]
    assert np.std(offsets) == pytest.approx(BaroConfig().offset_sigma_pa, rel=0.15)


def test_height_moves_the_pin_the_right_way() -> None:
    model = BaroModel(BaroConfig(offset_sigma_pa=0.0, drift_pa_sqrt_s=0.0, noise_pa=0.0), np.random.default_rng(0))
    v_floor = model.measure(0.0, 0.002)
    v_up = model.measure(10.0, 0.002)
    assert v_up < v_floor  # higher = lower pressure = lower voltage
    counts = (v_floor - v_up) / (5.0 / 1024)
    assert counts == pytest.approx(10.0 * 11.9 / 10.85, rel=0.05)


def test_same_seed_same_readings() -> None:
    a = BaroModel(BaroConfig(), np.random.default_rng(9))
    b = BaroModel(BaroConfig(), np.random.default_rng(9))
    assert [a.measure(1.0, 0.002) for _ in range(50)] == [b.measure(1.0, 0.002) for _ in range(50)]


def test_imu_pins_give_the_counts_of_the_wire_codec(rng: np.random.Generator) -> None:
    """The firmware's ADC reads exactly the counts ImuSample.from_si would send, saturation included."""
    cfg = ImuConfig()
    for _ in range(2000):
        accel = rng.normal(0.0, 15.0, 3)
        gyro = rng.normal(0.0, 4.0, 3)
        want = ImuSample.from_si(accel, gyro, cfg, 0)
        got_a = tuple(adc_count(imu_volts(float(x), cfg.accel_lsb_m_s2, cfg.zero_count)) for x in accel)
        got_g = tuple(adc_count(imu_volts(float(x), cfg.gyro_lsb_rad_s, cfg.zero_count)) for x in gyro)
        assert got_a == want.accel_counts
        assert got_g == want.gyro_counts


def test_adc_law_of_hardware_md() -> None:
    assert adc_count(0.0) == 0
    assert adc_count(2.5) == 512
    assert adc_count(5.0) == 1023  # clamped
    assert adc_count(12.6 / 4.0) == round(3.15 / 5.0 * 1024)
    assert adc_count(-1.0) == 0
    assert math.isclose(imu_volts(0.0, 0.1, 512), 2.5)

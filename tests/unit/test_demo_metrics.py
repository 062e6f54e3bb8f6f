"""Flight-report metrics against cases with known answers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from harness.demo import metrics
from harness.demo.report import FlightLog, check_targets, compute_report, setpoints_in_control, summary_table
from quadlink.mavlink import mavlink


def test_velocity_into_h_uses_yaw_only() -> None:
    v_ned = np.array([[0.0, 1.0, 0.2]])  # flying east, descending
    v_h = metrics.velocity_ned_to_h(v_ned, np.array([math.pi / 2]))  # heading east
    assert np.allclose(v_h, [[1.0, 0.0, 0.2]], atol=1e-12)


def test_rmse_interpolates_reference(rng: np.random.Generator) -> None:
    t_ref = np.linspace(0, 10, 1001)
    v_ref = np.stack([np.sin(t_ref), np.cos(t_ref), 0 * t_ref], axis=1)
    t_est = np.sort(rng.uniform(0.5, 9.5, 300))
    noise = rng.normal(0, 0.03, (300, 3))
    v_est = np.stack([np.sin(t_est), np.cos(t_est), 0 * t_est], axis=1) + noise
    rmse = metrics.rmse_per_axis(t_est, v_est, t_ref, v_ref)
    assert np.allclose(rmse, np.sqrt(np.mean(noise**2, axis=0)), atol=2e-3)
    masked = metrics.rmse_per_axis(t_est, v_est, t_ref, v_ref, mask=t_est > 5)
    assert np.all(np.isfinite(masked))


def test_gaps() -> None:
    t = np.concatenate([np.arange(0, 1, 1 / 30), np.arange(1.25, 2, 1 / 30)])
    gaps = metrics.stream_gaps(t, 0.1)
    assert gaps.count_over == 1 and gaps.max_gap_s == pytest.approx(0.25 + 1 / 30, abs=1e-6)
    assert metrics.stream_gaps(np.arange(0, 5, 1 / 30)).count_over == 0


def test_fraction_at_or_below() -> None:
    t = np.linspace(0, 1, 11)
    truth = np.full(11, 1.0)
    est = np.array([0.9] * 9 + [1.1, -1.0])  # one over, one invalid (-1 = none)
    assert metrics.fraction_at_or_below(t, est, t, truth) == pytest.approx(9 / 10)


def test_sinusoid_fit_recovers_pan_scan(rng: np.random.Generator) -> None:
    t = np.sort(rng.uniform(0, 20, 800))
    y = 0.4 + 0.6 * np.sin(2 * math.pi * 0.25 * t + 0.7) + rng.normal(0, 0.05, t.size)
    fit = metrics.fit_sinusoid(t, y)
    assert fit.frequency_hz == pytest.approx(0.25, rel=0.01)
    assert fit.amplitude == pytest.approx(0.6, rel=0.03)
    assert fit.phase_rad == pytest.approx(0.7, abs=0.1)
    assert fit.offset == pytest.approx(0.4, abs=0.02)


def test_report_on_synthetic_flight(rng: np.random.Generator) -> None:
    t = np.arange(0, 20, 0.02)
    alt = np.clip(np.minimum(t - 1, 1.0 - 0.4 * (t - 15)), 0, 1.0)   # up to 1 m, down at 0.4 m/s from 15 s
    v_n = np.where(t > 5, 0.3, 0.0)
    f = FlightLog(
        t_truth=t, p_ned=np.stack([np.cumsum(v_n) * 0.02, 0 * t, -alt], axis=1),
        v_ned=np.stack([v_n, 0 * t, 0 * t], axis=1), t_att=t, yaw_true=0 * t,
        t_dist0=t, dist0_m=np.full(t.size, 1.0), t_dist1=t, dist1_m=np.where(t > 3, 0.85, 3.0),
        t_fb=t, v_est_h=np.stack([v_n + rng.normal(0, 0.01, t.size), 0 * t, 0 * t], axis=1),
        v_cmd_h=np.stack([v_n, 0 * t, 0 * t], axis=1), v_rep_h=np.zeros((t.size, 3)),
        pan_scan_rate=0.5 * np.sin(2 * math.pi * 0.2 * t), yaw_rate_cmd=0.5 * np.sin(2 * math.pi * 0.2 * t),
        gyro_yaw_rate=0.4 * np.sin(2 * math.pi * 0.2 * t - 0.3), obstacle_est_m=np.where(t > 3, 0.8, 3.5),
        mode=np.full(t.size, 2.0), t_setpoint=np.arange(0, 20, 1 / 30),
    )
    report = compute_report(f, {"sitl": 10.0}, "synthetic")
    assert report["velocity_rmse_m_s"]["x"] == pytest.approx(0.01, abs=0.003)
    assert report["min_true_obstacle_distance_m"] == pytest.approx(0.85)
    # within eq. (7)'s influence distance (0.9 m) the estimate is on the safe side; before t = 3 s the nearest
    # wall (3.0 m) was seen 0.5 m too far: it counts for the whole flight only
    assert report["estimate_le_truth_within_m"] == pytest.approx(0.9)
    assert report["fraction_estimate_le_truth"] == 1.0
    flying = (alt > 0.3)
    assert report["fraction_estimate_le_truth_whole_flight"] == pytest.approx(
        np.sum(flying & (t > 3)) / np.sum(flying), abs=0.01)
    assert report["pan_scan"]["measured_amplitude_rad_s"] == pytest.approx(0.4, rel=0.05)
    assert report["pan_scan"]["phase_lag_rad"] == pytest.approx(0.3, abs=0.05)
    # the yaw loop identified from the feedback: 0.8 of the carrier, 0.3 rad late (eq. 5's -pi added)
    ident = report["pan_scan"]["identified"]
    assert ident["gain"] == pytest.approx(0.8, rel=0.03)
    assert ident["phase_rad"] == pytest.approx(math.remainder(-0.3 - math.pi, 2 * math.pi), abs=0.03)
    assert all(t["pass"] for t in report["targets"].values())
    bad = check_targets({**report, "min_true_clearance_m": 0.3})
    assert not bad["min_true_clearance_m"]["pass"]
    assert report["touchdown_m_s"] == pytest.approx(0.4, abs=0.01)
    assert check_targets({**report, "touchdown_m_s": 0.9})["touchdown_m_s"]["pass"] is False


def test_a_flight_never_near_a_surface_has_its_estimate_check_not_measured() -> None:
    """The estimate <= truth share counts only the samples with a true surface within the influence distance
    (0.9 m): a flight that never came that near has no such sample. The report says the target was not measured
    (neither PASS nor FAIL), and a measured one still passes or fails on its value."""
    t = np.arange(0, 20, 0.02)
    alt = np.clip(t - 1, 0, 1.0)
    far = FlightLog(
        t_truth=t, p_ned=np.stack([0 * t, 0 * t, -alt], axis=1), v_ned=np.zeros((t.size, 3)), t_att=t,
        yaw_true=0 * t, t_dist0=t, dist0_m=np.full(t.size, 1.0), t_dist1=t, dist1_m=np.full(t.size, 1.3),
        t_fb=t, v_est_h=np.zeros((t.size, 3)), v_cmd_h=np.zeros((t.size, 3)), v_rep_h=np.zeros((t.size, 3)),
        pan_scan_rate=0 * t, yaw_rate_cmd=0 * t, gyro_yaw_rate=0 * t, obstacle_est_m=np.full(t.size, 1.2),
        mode=np.full(t.size, 2.0), t_setpoint=np.arange(0, 20, 1 / 30),
    )
    report = compute_report(far, {"sitl": 10.0}, "synthetic")
    assert math.isnan(report["fraction_estimate_le_truth"])
    target = report["targets"]["fraction_estimate_le_truth"]
    assert target["pass"] is None and "never within 0.90 m" in target["note"]
    assert "NOT MEASURED" in summary_table(report) and "FAIL" not in summary_table(report)
    assert report["targets"]["touchdown_m_s"]["pass"] is None    # still in the air at the end: not measured
    assert check_targets({**report, "fraction_estimate_le_truth": 0.5})["fraction_estimate_le_truth"]["pass"] is False


def test_setpoint_gaps_count_only_while_the_companion_is_in_control() -> None:
    """Campaign 7: a companion that connected late sent a setpoint on the SITL's first buffered frame (0.006 s)
    and the next 29 s of sim time later, on the ground; a gap in flight still counts."""
    flight = FlightLog()
    flight.t_setpoint = np.concatenate([[0.006], np.arange(29.134, 50.0, 1 / 30), np.arange(50.3, 80.0, 1 / 30)])
    flight.t_fb = np.arange(25.0, 85.0, 0.02)
    flight.mode = np.where((flight.t_fb >= 30.0) & (flight.t_fb < 75.0), mavlink.QUADLINK_TELEOP_MODE_TELEOP,
                           mavlink.QUADLINK_TELEOP_MODE_IDLE).astype(float)
    t = setpoints_in_control(flight)
    assert t[0] >= 30.0 and t[-1] < 75.0
    gaps = metrics.stream_gaps(t, 0.1)
    assert gaps.count_over == 1 and gaps.max_gap_s == pytest.approx(0.3, abs=0.04)   # the one in flight
    assert metrics.stream_gaps(flight.t_setpoint, 0.1).max_gap_s > 29.0              # all of them: the ground's

"""Paper 003's tables, push recoveries and figures from time series (harness.demo.paper003)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from harness.demo.paper003 import Paper003Series, Recovery, hover_pass, make_plots, push_recoveries, tables
from harness.demo.paper003_cli import Recording
from harness.demo.paper003_cli import _series as flight_series
from quadlink.frames import Rz
from quadlink.trajectory.minsnap import minimum_snap


def _series(offset_p: np.ndarray, offset_v: np.ndarray, est_bias_v: np.ndarray) -> Paper003Series:
    t = np.linspace(0.0, 9.0, 900)  # even: the +/- offsets cancel exactly in the cross terms
    p_d = np.column_stack([np.cos(t), np.sin(t), -1.2 + 0 * t])
    v_d = np.column_stack([-np.sin(t), np.cos(t), 0 * t])
    sign = np.where(np.arange(t.size) % 2 == 0, 1.0, -1.0)[:, None]  # +/- offsets: RMSE = |offset|
    p_true = p_d + sign * offset_p
    v_true = v_d + sign * offset_v
    return Paper003Series(t, p_d, v_d, p_true, v_true, p_est_m=p_true.copy(), v_est_m_s=v_true + est_bias_v)


def test_tables_are_the_rms_errors_and_check_issue_19s_targets() -> None:
    s = _series(np.array([0.02, 0.04, 0.01]), np.array([0.03, 0.05, 0.0]), np.array([0.01, 0.0, 0.02]))
    tab = tables(s)
    np.testing.assert_allclose(tab["true_position_vs_desired_m"], [0.02, 0.04, 0.01], atol=1e-12)
    np.testing.assert_allclose(tab["table4_position_m"], [0.02, 0.04, 0.01], atol=1e-12)
    np.testing.assert_allclose(tab["table3_velocity_m_s"], [0.01, 0.0, 0.02], atol=1e-12)
    v5 = np.sqrt(np.array([0.03, 0.05, 0.0]) ** 2 + np.array([0.01, 0.0, 0.02]) ** 2)  # +/- offset and a bias
    np.testing.assert_allclose(tab["table5_velocity_m_s"], v5, atol=1e-12)
    assert tab["pass"] == {"table4_position_m": True, "table5_velocity_m_s": True, "table3_velocity_m_s": True}
    bad = tables(_series(np.array([0.06, 0.0, 0.0]), np.zeros(3), np.zeros(3)))
    assert bad["pass"]["table4_position_m"] is False
    truth_only = tables(Paper003Series(s.t_s, s.p_d_m, s.v_d_m_s, s.p_true_m, s.v_true_m_s))
    assert "table4_position_m" not in truth_only and truth_only["pass"] == {}
    assert tab["paper"]["table4_position_m"] == [0.0565, 0.0657, 0.0125]


def test_push_recovery_of_a_decaying_excursion() -> None:
    t = np.arange(0.0, 20.0, 0.01)
    hold = np.array([0.0, 0.0, -1.0])
    p = np.tile(hold, (t.size, 1))
    release = 5.0
    after = t >= release
    p[after, 1] += 0.7 * np.exp(-(t[after] - release) / 0.5)  # back within 5 cm when 0.7 e^(-x/0.5) = 0.05
    pushing = (t >= 4.4) & ~after
    p[pushing, 1] += 0.7 * (t[pushing] - 4.4) / 0.6  # moved 0.7 m during the push (1.17 m/s)
    v = np.gradient(p, t, axis=0)
    (r,) = push_recoveries(t, p, v, hold, [(4.4, release)])
    assert r.peak_displacement_m == pytest.approx(0.7, abs=1e-9)
    assert r.back_after_s == pytest.approx(0.5 * np.log(0.7 / 0.05), abs=0.011)
    assert r.peak_speed_m_s == pytest.approx(1.4, rel=0.02)
    (never,) = push_recoveries(t, p + [0.0, 0.1, 0.0], v, hold, [(4.4, release)])
    assert never.back_after_s == np.inf


def test_plots_are_written(tmp_path: Path) -> None:
    s = _series(np.array([0.02, 0.04, 0.01]), np.zeros(3), np.zeros(3))
    paths = make_plots(s, tmp_path)
    assert [p.name for p in paths] == ["paper003_fig10_xy.png", "paper003_fig11_position.png",
                                       "paper003_fig12_velocity.png"]
    assert all(p.stat().st_size > 10_000 for p in paths)


def test_oval_figures_turn_the_truth_into_the_odometrys_axes() -> None:
    """A flight started at yaw 120 deg that tracks perfectly: the truth (arena axes) and the estimate (start-heading
    axes) differ by the start yaw; the figures must see no error."""
    traj = minimum_snap(np.array([[-1.0, -1.5, -1.2], [0.0, -0.5, -1.2], [0.0, 0.5, -1.2], [-1.0, -1.5, -1.2]]),
                        [3.0, 1.7, 4.3])
    yaw = math.radians(120.0)
    rec = Recording()
    t0 = 10.0
    for t in np.arange(0.0, 25.0, 0.02):
        s = traj.sample(min(max(t - t0, 0.0), traj.duration_s))
        v = s.v_m_s if t0 <= t <= t0 + traj.duration_s else np.zeros(3)
        p_arena, v_arena = Rz(yaw) @ s.p_m + [0.3, -0.2, 0.0], Rz(yaw) @ v   # truth: arena axes, another origin
        rec.truth.append((t, *p_arena, *v_arena))
        if round(t / 0.02) % 2 == 0:   # the estimate at half the rate
            rec.estimate.append((t, *s.p_m, *v))
    series, _ = flight_series(rec, traj, t0, yaw)
    tab = tables(series)
    for key in ("table4_position_m", "table3_velocity_m_s", "true_position_vs_desired_m"):
        assert max(tab[key]) < 2e-3, (key, tab[key])
    unturned = tables(flight_series(rec, traj, t0, 0.0)[0])
    assert max(unturned["table3_velocity_m_s"]) > 0.2   # without the turn the truth's velocity is elsewhere


def test_hover_pass_per_criterion() -> None:
    good = [Recovery(30.0, 0.72, 1.3, 1.7), Recovery(40.0, 0.81, 1.2, 2.1), Recovery(50.0, 0.8, 1.2, 2.6)]
    assert hover_pass(good) == {"three_pushes": True, "push_size": True, "back_within_3_s": True}
    assert hover_pass(good[:2])["three_pushes"] is False
    assert hover_pass([*good[:2], Recovery(50.0, 0.4, 0.8, 1.0)])["push_size"] is False
    assert hover_pass([*good[:2], Recovery(50.0, 0.8, 1.2, math.inf)])["back_within_3_s"] is False

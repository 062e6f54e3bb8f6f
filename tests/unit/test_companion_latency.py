"""companion.latency: the age of a setpoint's data and what the safety law pays for it (issue 30)."""

from __future__ import annotations

import math

import pytest

from companion.latency import LatencyGuard, LatencyParams

pytestmark = pytest.mark.unit

P = LatencyParams(nominal_s=0.10, hold_s=0.35, resume_s=0.20, hold_after_frames=3, resume_after_s=1.0)
STOP_S, SPEED = 0.8, 1.5


def test_the_stopping_time_counts_the_measured_excess_and_the_speed_limit_falls() -> None:
    g = LatencyGuard(P)
    young = g.on_frame(0.0, 0.05, STOP_S, SPEED)
    assert young.stopping_time_s == STOP_S and young.max_speed_m_s == SPEED and not young.holding
    late = g.on_frame(0.033, 0.25, STOP_S, SPEED)
    assert late.stopping_time_s == pytest.approx(STOP_S + 0.15)
    assert late.max_speed_m_s == pytest.approx(SPEED * (0.35 - 0.25) / 0.25) and not late.holding
    # an unknown age (no autopilot clock yet) is taken as nominal: nothing is known to be late
    assert g.on_frame(0.066, math.nan, STOP_S, SPEED).stopping_time_s == STOP_S


def test_a_run_of_late_frames_holds_and_only_a_second_of_young_ones_resumes() -> None:
    g = LatencyGuard(P)
    t = 0.0
    verdicts = []
    for age in (0.4, 0.4, 0.05, 0.4, 0.4, 0.4):   # one young frame breaks the run: hold on the 3rd in a row
        verdicts.append(g.on_frame(t, age, STOP_S, SPEED))
        t += 1 / 30
    assert [v.holding for v in verdicts] == [False, False, False, False, False, True]
    assert verdicts[-1].changed and g.holds == 1 and verdicts[-1].max_speed_m_s == 0.0
    # young again, but 0.25 s (above resume_s) does not count toward resuming; 1 s of <= 0.2 s does
    for _ in range(40):
        assert g.on_frame(t, 0.25, STOP_S, SPEED).holding
        t += 1 / 30
    n = 0
    while g.on_frame(t, 0.15, STOP_S, SPEED).holding:
        t += 1 / 30
        n += 1
    assert n == pytest.approx(30, abs=1)   # 1.0 s at 30 Hz
    assert not g.holding and g.holds == 1


def test_bad_params_are_refused() -> None:
    with pytest.raises(ValueError):
        LatencyParams(nominal_s=0.3, hold_s=0.2)
    with pytest.raises(ValueError):
        LatencyParams(hold_after_frames=0)
    with pytest.raises(ValueError):
        LatencyParams(max_drift_scale=0.5)


def test_the_map_drift_margin_grows_with_the_frames_skipped_and_recovers() -> None:
    g = LatencyGuard(P)
    assert g.on_frame(0.0, 0.05, STOP_S, SPEED).drift_scale == 1.0
    t, v = 0.0, None
    for _ in range(40):                       # one frame in two processed: the margin tends to 2 x
        t += 2 / 30
        v = g.on_frame(t, 0.05, STOP_S, SPEED, seq_gap=2)
    assert v is not None and v.drift_scale == pytest.approx(2.0, abs=0.03)
    for _ in range(40):                       # one in five, capped at max_drift_scale
        t += 5 / 30
        v = g.on_frame(t, 0.05, STOP_S, SPEED, seq_gap=5)
    assert v.drift_scale == P.max_drift_scale
    for _ in range(60):                       # none skipped again: back to the configured margin
        t += 1 / 30
        v = g.on_frame(t, 0.05, STOP_S, SPEED, seq_gap=1)
    assert v.drift_scale == pytest.approx(1.0, abs=0.01)
    # a restarted camera (the sequence went back) counts as no gap, and a single skip moves it a little
    assert g.on_frame(t, 0.05, STOP_S, SPEED, seq_gap=-500).drift_scale < 1.01
    assert 1.0 < g.on_frame(t, 0.05, STOP_S, SPEED, seq_gap=2).drift_scale < 1.2

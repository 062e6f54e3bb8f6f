"""Section VI-B filters: band-pass (unit gain, zero phase at f), peak-to-peak frequency estimator, and the
pan-scan estimator recovering a synthetic oscillation (frequency, amplitude, phase) through bias and noise."""

from __future__ import annotations

import math

import numpy as np
import pytest

from teleop.view.panscan import BandPass, PanScanEstimator, PeakToPeakFrequency


def fit_sinusoid(t: np.ndarray, x: np.ndarray, f_hz: float) -> tuple[float, float]:
    """Amplitude and phase (rad) of x ~ a sin(2 pi f t + phase) by least squares."""
    A = np.column_stack([np.sin(2 * np.pi * f_hz * t), np.cos(2 * np.pi * f_hz * t), np.ones_like(t)])
    (s, c, _), *_ = np.linalg.lstsq(A, x, rcond=None)
    return math.hypot(s, c), math.atan2(c, s)


def phase_diff_deg(a: float, b: float) -> float:
    return abs(math.degrees(math.atan2(math.sin(a - b), math.cos(a - b))))


@pytest.mark.parametrize("f0", [0.2, 0.5, 1.5])
def test_bandpass_unit_gain_zero_phase_at_centre(f0):
    fs = 30.0
    bp = BandPass(f0, 1.5, fs)
    t = np.arange(0, 40 / f0, 1 / fs)
    x = 0.7 * np.sin(2 * np.pi * f0 * t + 0.4) + 0.3     # plus a bias the filter must reject
    y = np.array([bp.step(v) for v in x])
    tail = t > 20 / f0
    amp, ph = fit_sinusoid(t[tail], y[tail], f0)
    assert amp == pytest.approx(0.7, rel=1e-3)
    assert phase_diff_deg(ph, 0.4) < 0.2
    assert abs(np.mean(y[tail])) < 1e-3
    # off-centre frequencies are attenuated
    bp2 = BandPass(f0, 1.5, fs)
    y2 = np.array([bp2.step(v) for v in np.sin(2 * np.pi * 4 * f0 * t)])
    assert fit_sinusoid(t[tail], y2[tail], 4 * f0)[0] < 0.2


def test_peak_to_peak_frequency_from_noisy_oscillation(rng):
    est = PeakToPeakFrequency(initial_hz=0.5, min_hz=0.05, max_hz=3.0)
    fs, f = 50.0, 0.23
    t = np.arange(0, 30, 1 / fs)
    x = np.sin(2 * np.pi * f * t) + rng.normal(0, 0.05, t.size)
    for ti, xi in zip(t, x):
        est.update(float(xi), float(ti))
    assert est.frequency_hz == pytest.approx(f, rel=0.02)
    assert est.amplitude == pytest.approx(1.0, rel=0.1)


@pytest.mark.parametrize("f_true, f_initial", [(0.4, 0.7), (0.25, 0.5), (1.0, 0.5)])
def test_pan_scan_estimator_recovers_frequency_amplitude_phase(rng, f_true, f_initial):
    fs, A, phase = 30.0, 0.8, 0.3
    t = np.arange(0, 60, 1 / fs) + rng.uniform(-2e-3, 2e-3, int(60 * fs))   # jittered sample times
    t.sort()
    w = 2 * np.pi * f_true
    rate = A * np.sin(w * t + phase)
    psi = -A / w * np.cos(w * t + phase)                  # zero-mean yaw displacement it causes
    operator = 0.15 * np.clip(np.sin(2 * np.pi * 0.02 * t), 0, None)    # slow operator yaw command
    gyro = rate + operator + 0.07 + rng.normal(0, 0.05, t.size)         # + gyro bias + noise
    est = PanScanEstimator(initial_hz=f_initial, q=1.5)
    out = [est.update(float(g), float(ti)) for g, ti in zip(gyro, t)]
    tail = t > 30
    r = np.array([o.yaw_rate_rad_s for o in out])[tail]
    p = np.array([o.yaw_rad for o in out])[tail]
    assert out[-1].locked
    assert out[-1].frequency_hz == pytest.approx(f_true, rel=0.03)
    amp, ph = fit_sinusoid(t[tail], r, f_true)
    assert amp == pytest.approx(A, rel=0.05)
    assert phase_diff_deg(ph, phase) < 5.0
    residual = np.sqrt(np.mean((p - psi[tail]) ** 2)) / np.sqrt(np.mean(psi[tail] ** 2))
    assert residual < 0.10


def test_disabling_fades_the_estimate_out(rng):
    est = PanScanEstimator(initial_hz=0.5, fade_time_s=1.0)
    t = np.arange(0, 40, 1 / 30)
    for ti in t:
        last = est.update(0.8 * math.sin(2 * math.pi * 0.5 * ti), float(ti), enabled=ti < 30)
    assert last.yaw_rad == 0.0 and last.yaw_rate_rad_s == 0.0


def test_bad_samples_and_gaps_are_ignored():
    est = PanScanEstimator()
    first = est.update(0.1, 0.0)
    assert est.update(float("nan"), 0.1) is first
    assert est.update(0.2, 0.0).yaw_rad == 0.0           # time did not advance
    est.update(0.2, 5.0)                                 # 5 s gap: restart, no integration across it
    assert abs(est.update(0.2, 5.033).yaw_rad) < 0.01


def test_operator_turns_are_removed_before_the_band_pass(rng):
    """Operator yaw commands leak into the band-pass (transients of the turns); subtracting the known command
    through the yaw-loop model keeps psi_s within 10 % (without it the residual is several times larger)."""
    fs, A, w, tau = 30.0, 0.6, 1.5, 0.15
    t = np.arange(0, 90, 1 / fs)
    phase = np.sin(2 * np.pi * t / 23.0)
    op_cmd = 0.25 * ((phase > 0.6).astype(float) - (phase < -0.6).astype(float))
    # first-order yaw loop, exact per step for the (held) inputs
    pan_cmd = A * np.sin(w * t)
    rate_pan, rate_op = np.zeros_like(t), np.zeros_like(t)
    a = 1 - math.exp(-1 / (fs * tau))
    for k in range(1, t.size):
        rate_pan[k] = rate_pan[k - 1] + a * (pan_cmd[k - 1] - rate_pan[k - 1])
        rate_op[k] = rate_op[k - 1] + a * (op_cmd[k - 1] - rate_op[k - 1])
    psi = np.cumsum(rate_pan) / fs
    psi -= psi[t > 20].mean()
    gyro = rate_pan + rate_op + 0.03 + rng.normal(0, 0.02, t.size)
    residuals = []
    for use in (False, True):
        est = PanScanEstimator(initial_hz=0.25, operator_yaw_time_constant_s=tau)
        out = np.array([est.update(float(g), float(ti), True, float(c) if use else 0.0).yaw_rad
                        for g, ti, c in zip(gyro, t, op_cmd)])
        tail = t > 30
        residuals.append(np.sqrt(np.mean((out[tail] - psi[tail]) ** 2)) / np.sqrt(np.mean(psi[tail] ** 2)))
    assert residuals[1] < 0.10
    assert residuals[0] > 2 * residuals[1]

"""Yaw-loop identification from a flight's TELEOP_FEEDBACK: the fit against a simulated loop with known
dynamics, and ``quadlink identify-yaw`` on a .tlog as a user runs it."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from quadlink.analysis.yaw_identification import FeedbackSeries, IdentificationError, fit_yaw_loop, identify_first_order
from quadlink.cli import main
from quadlink.mavlink import mavlink
from quadlink.mavlink.tlog import TlogWriter

GYRO_LSB_RAD_S = 0.0102276   # the MK gyro's count (configs/vehicle.yaml): the feedback's yaw rate is quantised
OMEGA = 1.5


def _flight(tau: float, delay: float, gain: float, seconds: float = 40.0, seed: int = 3) -> FeedbackSeries:
    """50 Hz feedback of a loop ``gain exp(-s delay) / (tau s + 1)`` driven by the pan-scan carrier plus an
    operator who yaws now and then (a few slow sinusoids), measured with a 0.02 rad/s bias and quantised."""
    rng = np.random.default_rng(seed)
    dt_sim = 0.002
    t = np.arange(0.0, seconds, dt_sim)
    pan = 0.6 * np.sin(OMEGA * t)
    operator = 0.3 * np.sin(0.37 * t + 1.0) + 0.2 * np.sin(2.9 * t) + 0.1 * np.sign(np.sin(0.8 * t))
    cmd = pan + operator
    delayed = np.interp(t - delay, t, cmd, left=cmd[0])
    a = math.exp(-dt_sim / tau)
    y = np.zeros_like(t)
    for k in range(1, t.size):
        y[k] = a * y[k - 1] + (1 - a) * gain * delayed[k - 1]
    gyro = np.round((y + 0.02 + rng.normal(0.0, 0.005, t.size)) / GYRO_LSB_RAD_S) * GYRO_LSB_RAD_S
    keep = np.arange(0, t.size, 10)[5 * 50:]           # 50 Hz, after 5 s
    return FeedbackSeries(t[keep], pan[keep], cmd[keep], gyro[keep])


@pytest.mark.parametrize("tau,delay,gain", [(0.15, 0.02, 1.0), (0.06, 0.04, 1.14), (0.3, 0.0, 0.9)])
def test_fit_recovers_the_loop_and_its_response_at_the_carrier(tau: float, delay: float, gain: float) -> None:
    fit = fit_yaw_loop(_flight(tau, delay, gain), OMEGA)
    assert fit.time_constant_s == pytest.approx(tau, rel=0.15, abs=0.01)
    assert fit.delay_s == pytest.approx(delay, abs=0.021)          # one 50 Hz sample
    assert fit.static_gain == pytest.approx(gain, rel=0.03)
    model = identify_first_order(tau, OMEGA, delay)
    assert fit.response.gain == pytest.approx(gain * model.gain, rel=0.03)
    assert fit.response.phase_rad == pytest.approx(model.phase_rad, abs=0.03)
    assert fit.rms_residual_rad_s < 0.02                            # quantisation and noise only


def test_no_excitation_is_an_identification_error() -> None:
    t = np.arange(0.0, 10.0, 0.02)
    flat = np.zeros_like(t)
    with pytest.raises(IdentificationError, match="does not move"):
        fit_yaw_loop(FeedbackSeries(t, flat, flat, flat + 0.01), OMEGA)
    with pytest.raises(IdentificationError, match="at least 8"):
        fit_yaw_loop(FeedbackSeries(t[:5], flat[:5], flat[:5], flat[:5]), OMEGA)


def _feedback(enc: mavlink.MAVLink, t_us: int, pan: float, cmd: float, gyro: float, mode: int,
              flags: int) -> mavlink.MAVLink_teleop_feedback_message:
    return enc.teleop_feedback_encode(t_us, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, pan, cmd, gyro,
                                      0.0, 0.0, 0.0, 1.5, mode, flags)


def _write_tlog(path: Path, series: FeedbackSeries | None, others: int = 20) -> None:
    enc = mavlink.MAVLink(None, 1, 191)
    with TlogWriter(path) as tlog:
        for k in range(others):   # before take-off: idle, pan-scan off (not used)
            m = _feedback(enc, k * 20_000, 0.3, 0.3, 0.0, 0, 0)
            tlog.write(m.pack(enc), 1e9 + k * 0.02)
            hb = enc.heartbeat_encode(mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            tlog.write(hb.pack(enc), 1e9 + k * 0.02)
        if series is not None:
            for t, pan, cmd, gyro in zip(series.t_s, series.pan_scan_rad_s, series.yaw_rate_cmd_rad_s,
                                         series.gyro_yaw_rate_rad_s):
                m = _feedback(enc, int(round(t * 1e6)) + 1_000_000, float(pan), float(cmd), float(gyro), 2, 1 | 2)
                tlog.write(m.pack(enc), 1e9 + t)


def test_identify_yaw_command_on_a_tlog(tmp_path: Path) -> None:
    series = _flight(0.06, 0.04, 1.14)
    _write_tlog(tmp_path / "companion.tlog", series)
    result = CliRunner().invoke(main, ["identify-yaw", str(tmp_path / "companion.tlog")])
    assert result.exit_code == 0, result.output
    assert f"{series.t_s.size} TELEOP_FEEDBACK in teleop with the pan-scan on" in result.output
    snippet = yaml.safe_load(result.output[result.output.index("pan_scan:"):])
    expected = identify_first_order(0.06, OMEGA, 0.04)
    assert snippet["pan_scan"]["response"] == "fixed"
    assert snippet["pan_scan"]["gain"] == pytest.approx(1.14 * expected.gain, rel=0.03)
    assert snippet["pan_scan"]["phase_rad"] == pytest.approx(expected.phase_rad, abs=0.03)


def test_identify_yaw_on_a_log_without_teleop_or_a_missing_file_is_a_one_line_error(tmp_path: Path) -> None:
    _write_tlog(tmp_path / "ground.tlog", None)
    result = CliRunner().invoke(main, ["identify-yaw", str(tmp_path / "ground.tlog")])
    assert result.exit_code == 2
    assert "no TELEOP_FEEDBACK in teleop with the pan-scan on (40 messages read)" in result.output
    result = CliRunner().invoke(main, ["identify-yaw", str(tmp_path / "missing.tlog")])
    assert result.exit_code == 2 and "cannot read the log" in result.output

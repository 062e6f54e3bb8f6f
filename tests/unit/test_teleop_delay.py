"""The operator view under delay (issue 18, item 4): the measured round trip and where the vehicle is now."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.frame_step import operator_image_meta
from companion.modes import Mode
from companion.pan_scan import PanScanParams, PanScanState
from companion.reference import ReferenceOutput
from quadlink.frames import R_from_euler, Rz
from quadlink.mavlink.timesync import NS, TimesyncEstimator
from quadlink.operator_image import OperatorImageMeta
from quadlink.vehicle import load_vehicle
from teleop.config import TeleopConfig
from teleop.delay import LinkDelay, link_delay, predicted_displacement_h_m, predicted_points_c_m
from teleop.view.render import OperatorViewRenderer
from teleop.view_loop import overlay


def test_predicted_points_are_the_points_seen_from_the_moved_vehicle(rng) -> None:
    """Forward composition, independent of teleop.delay: world points seen from the vehicle at capture and
    after it flew v_h for the latency (attitude held) -> the camera-frame points must agree."""
    R_qc = load_vehicle().camera.R_qc_matrix
    p_qc = np.array([0.08, 0.0, 0.02])
    for _ in range(20):
        roll, pitch, yaw = rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3), rng.uniform(-math.pi, math.pi)
        R_wq = R_from_euler(roll, pitch, yaw)
        p0_w = rng.uniform(-2, 2, 3)
        v_h = rng.uniform(-1.0, 1.0, 3)
        latency = rng.uniform(0.0, 0.4)
        p1_w = p0_w + Rz(yaw) @ (v_h * latency)          # H -> W is the yaw rotation (NED)
        pts_w = rng.uniform(-3, 3, (5, 3))
        seen0_c = ((pts_w - p0_w) @ R_wq - p_qc) @ R_qc   # p_c = R_qc^T (R_wq^T (p_w - p) - p_qc)
        seen1_c = ((pts_w - p1_w) @ R_wq - p_qc) @ R_qc
        d_h = predicted_displacement_h_m(v_h, latency)
        assert d_h is not None
        np.testing.assert_allclose(predicted_points_c_m(seen0_c, d_h, roll, pitch, R_qc), seen1_c, atol=1e-9)


def test_no_prediction_without_a_sane_latency() -> None:
    assert predicted_displacement_h_m([1.0, 0, 0], math.nan) is None
    assert predicted_displacement_h_m([1.0, 0, 0], -0.1) is None
    assert predicted_displacement_h_m([math.nan, 0, 0], 0.1) is None
    assert predicted_displacement_h_m([1.0, 0.5, 0], 0.2) == pytest.approx((0.2, 0.1, 0.0))


def test_link_delay_reports_the_estimators_round_trip() -> None:
    est = TimesyncEstimator()
    offset_s = 3.0
    for k, rtt in enumerate([0.30, 0.32, 0.28, 0.31, 0.60]):
        t_send = 10.0 + k
        est.on_response(int((t_send + rtt / 2 + offset_s) * NS), int(t_send * NS), int((t_send + rtt) * NS))
    d = link_delay(est)
    assert d.rtt_p50_s == pytest.approx(0.31) and d.samples == 5
    assert d.rtt_p99_s == pytest.approx(0.32 + 0.96 * (0.60 - 0.32))   # sorted samples, linear between ranks
    assert d.offset_s == pytest.approx(offset_s, abs=1e-6)
    assert d.status()["rtt_p50_ms"] == pytest.approx(310.0)
    assert LinkDelay().status()["rtt_ms"] is None


def _meta() -> OperatorImageMeta:
    """The companion's own producer of the image metadata: moving forward at 1 m/s, two avoidance points
    ahead (in H; the producer maps them to the camera frame)."""
    class Out:
        roll_rad, pitch_rad, yaw_rad = 0.05, -0.1, 0.3
        v_h_m_s = np.array([1.0, 0.0, 0.0])

    ref = ReferenceOutput(np.array([1.0, 0.0, 0.0]), 0.0, np.array([1.0, 0.0, 0.0]), np.zeros(3), 0.0, 0.0, 0.0,
                          False)
    return operator_image_meta(12.0, Out(), ref, PanScanState(0.0, 0.0, False), PanScanParams(enabled=False),
                               np.zeros(3), Mode.TELEOP, np.array([[1.5, 0.0, 0.0], [2.0, 0.3, -0.1]]),
                               load_vehicle().camera.R_qc_matrix, np.zeros(3))


def _status(rtt_ms: float | None) -> dict:
    return {"battery_v": 15.0, "min_obstacle_m": 1.5, "link": "ok", "mode": "TELEOP", "armed": True,
            "force_n": [0.0, 0.0, 0.0], "warnings": [], "rtt_ms": rtt_ms, "rtt_p50_ms": rtt_ms,
            "rtt_p99_ms": None if rtt_ms is None else rtt_ms + 40.0}


def test_overlay_shows_the_round_trip_and_the_vehicle_now() -> None:
    cfg = TeleopConfig()
    R_qc = load_vehicle().camera.R_qc_matrix
    meta = _meta()
    ov = overlay(cfg, _status(600.0), meta, R_qc=R_qc)
    assert any("RTT 600 ms" in line and "p99 640" in line and "+0.30 m" in line for line in ov.status_lines)
    assert ov.prediction_h_m == pytest.approx((0.3, 0.0, 0.0))
    expected = predicted_points_c_m(meta.obstacle_points_c_m, (0.3, 0.0, 0.0), meta.roll_rad, meta.pitch_rad, R_qc)
    np.testing.assert_allclose(np.asarray(ov.predicted_points_c_m), expected, atol=1e-9)
    # moving toward the points: they are nearer now than in the image
    assert np.all(np.linalg.norm(expected, axis=1) < np.linalg.norm(np.asarray(meta.obstacle_points_c_m), axis=1))
    none = overlay(cfg, _status(None), meta, R_qc=R_qc)
    assert none.prediction_h_m is None and none.predicted_points_c_m == ()
    assert any("RTT - ms" in line for line in none.status_lines)


def test_renderer_draws_the_ghost_where_the_prediction_is() -> None:
    cfg = TeleopConfig()
    ov = overlay(cfg, _status(600.0), _meta(), R_qc=load_vehicle().camera.R_qc_matrix)
    r = OperatorViewRenderer(320, 240, 1.0)
    with_ghost = r.render(None, None, np.eye(3), 0.0, 0.0, 0.0, 0.0, ov)
    import dataclasses

    without = OperatorViewRenderer(320, 240, 1.0).render(None, None, np.eye(3), 0.0, 0.0, 0.0, 0.0,
                                                         dataclasses.replace(ov, prediction_h_m=None))
    diff = np.any(with_ghost != without, axis=2)
    ys, xs = np.nonzero(diff)
    # inset centre (55, 185), 0.3 m forward of a 0.5 m rim of 45 px: 27 px up
    assert ys.size > 0 and ys.min() <= 185 - 27 + 6 and xs.min() >= 55 - 8 and xs.max() <= 55 + 8


def test_csv_row_carries_the_round_trip_and_the_passivity_account() -> None:
    """The station's CSV: the controller's own report after a few ticks of a delayed cue, and the estimator's
    round trip, land in their columns (the demo report reads them back by name)."""
    import csv
    import io

    from teleop.config import PassivityConfig
    from teleop.devices.base import DeviceState
    from teleop.force_loop import ForceSnapshot
    from teleop.mapping import ManualControl
    from teleop.passivity import PassivityController
    from teleop.recording import CSV_FIELDS, csv_row
    from teleop.telemetry import Telemetry

    pc = PassivityController(PassivityConfig(enabled=True), (0.25, 0.25, 0.25))
    q = 0.0
    for k in range(200):   # the hand pulled along by a force that leads the motion: energy out of the port
        q = 0.01 * math.sin(0.05 * k)
        pc.observe(k * 1e-3, [q, 0.0, 0.0])
        tau = pc.control([0.5 * math.cos(0.05 * k), 0.0, 0.0], [2.0 * math.cos(0.05 * k), 0.0, 0.0], 1e-3)
        pc.applied(tau, [2.0 * math.cos(0.05 * k), 0.0, 0.0])
    report = pc.report()
    snap = ForceSnapshot(DeviceState(0.2, np.array([q, 0, 0]), np.zeros(3)), np.zeros(3), None, 1.0,
                         passivity=report)
    delay = LinkDelay(0.612, 0.600, 0.700, 0.004, 9)
    row = csv_row(1.0, snap, ManualControl(0, 0, 500, 0), Telemetry(), None, delay)
    assert len(row) == len(CSV_FIELDS)
    text = io.StringIO()
    csv.writer(text).writerows([CSV_FIELDS, row])
    back = next(csv.DictReader(io.StringIO(text.getvalue())))
    assert float(back["rtt_ms"]) == pytest.approx(612.0) and float(back["rtt_p99_ms"]) == pytest.approx(700.0)
    assert float(back["pass_output_j"]) == pytest.approx(report.output_j, abs=1e-6)
    assert float(back["pass_min_observed_j"]) == pytest.approx(report.min_observed_j, abs=1e-6)
    assert float(back["pass_dissipated_j"]) == pytest.approx(report.dissipated_j, abs=1e-6)
    empty = next(csv.DictReader(io.StringIO(",".join(CSV_FIELDS) + "\n" + ",".join(
        map(str, csv_row(1.0, None, ManualControl(0, 0, 500, 0), Telemetry(), None))) + "\n")))
    assert empty["rtt_ms"] == "" and empty["pass_observed_j"] == ""


def test_the_station_warns_when_the_autopilot_falls_silent_behind_a_talking_companion() -> None:
    from dataclasses import replace

    from teleop.station import warnings_for
    from teleop.telemetry import Telemetry

    cfg = TeleopConfig()   # network.heartbeat_timeout_s 2 s
    heard = replace(Telemetry(), autopilot_heartbeat_t_s=10.0)
    assert not [w for w in warnings_for(heard, True, 11.9, cfg) if "AUTOPILOT" in w]
    assert "AUTOPILOT SILENT 3 s" in warnings_for(heard, True, 13.0, cfg)
    # the whole link lost is its own warning, and an autopilot never heard is "no vehicle link yet"'s business
    assert not [w for w in warnings_for(heard, False, 13.0, cfg) if "AUTOPILOT" in w]
    assert not [w for w in warnings_for(Telemetry(), True, 13.0, cfg) if "AUTOPILOT" in w]

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
    """The companion's own producer of the image metadata: moving forward at 1 m/s, one obstacle ahead."""
    class Out:
        roll_rad, pitch_rad, yaw_rad = 0.05, -0.1, 0.3
        v_h_m_s = np.array([1.0, 0.0, 0.0])
        obstacle_points_c_m = np.array([[0.0, 0.0, 1.5], [0.3, -0.1, 2.0]])

    ref = ReferenceOutput(np.array([1.0, 0.0, 0.0]), 0.0, np.array([1.0, 0.0, 0.0]), np.zeros(3), 0.0, 0.0, 0.0,
                          False)
    return operator_image_meta(12.0, Out(), ref, PanScanState(0.0, 0.0, False), PanScanParams(enabled=False),
                               np.zeros(3), Mode.TELEOP)


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

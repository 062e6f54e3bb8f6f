"""OperatorImageMeta's wire form: strict decode (protocol tier)."""

from __future__ import annotations

import dataclasses
import json
import math
from typing import Any

import numpy as np
import pytest

from companion.frame_step import operator_image_meta
from companion.modes import Mode
from companion.operator_input import OperatorInput
from companion.pan_scan import PanScanParams, pan_scan
from companion.reference import reference_velocity
from companion.reference_params import ReferenceParams
from quadlink.camera import CameraIntrinsics, RecordDecoder, RgbdFrame, encode_record
from quadlink.errors import ProtocolError
from quadlink.operator_image import OperatorImageMeta
from teleop.view_loop import image_meta


class Out:
    """The fields of perception.pipeline.PerceptionOutput that the producer reads."""

    roll_rad, pitch_rad, yaw_rad = 0.05, -0.02, 0.3
    v_h_m_s = np.array([0.2, -0.1, 0.0])


AVOIDANCE_POINTS_H_M = np.array([[1.2, 0.1, 0.0], [np.nan, 0.0, 1.0], [2.0, -0.3, 0.1]])


def _producer_meta(enabled: bool) -> OperatorImageMeta:
    params = PanScanParams(enabled, 0.6, 1.5)
    scan = pan_scan(params, 0.7)
    R_qc = np.eye(3)
    ref = reference_velocity(OperatorInput(1.0, 0.0, 0.0), R_qc, scan, None, ReferenceParams())
    return operator_image_meta(12.5, Out(), ref, scan, params, np.array([0.0, 0.0, 0.4]), Mode.TELEOP,
                               AVOIDANCE_POINTS_H_M, R_qc, np.zeros(3))


def _wire(meta: OperatorImageMeta) -> dict[str, Any]:
    return json.loads(json.dumps(meta.to_wire()))


def test_producer_output_round_trips_through_the_camera_record() -> None:
    meta = _producer_meta(True)
    k = CameraIntrinsics.from_fov(64, 48, 80.0, 60.0)
    rec = encode_record(RgbdFrame(3, 12.5, np.zeros((48, 64, 3), np.uint8), None, k, meta=meta.to_wire()), True)
    (frame,) = RecordDecoder().feed(rec)
    got = image_meta(frame)
    assert got == meta
    assert got.pan_scan.enabled and got.mode == "teleop"
    assert len(got.obstacle_points_c_m) == 2                       # the NaN point is not sent
    assert got.v_est_h_m_s == pytest.approx((0.2, -0.1, 0.0))
    assert not _producer_meta(False).pan_scan.enabled


@pytest.mark.parametrize("mutate", [
    lambda d: d.pop("v_cmd_h_m_s"),                                  # missing
    lambda d: d.__setitem__("v_cmd_h", d.pop("v_cmd_h_m_s")),       # renamed
    lambda d: d.__setitem__("pan_scan_on", True),                   # unknown
    lambda d: d["pan_scan"].pop("enabled"),                          # missing nested
    lambda d: d["pan_scan"].__setitem__("enabled", 1),               # wrong type (int for bool)
    lambda d: d.__setitem__("roll_rad", "0.1"),                      # wrong type
    lambda d: d.__setitem__("roll_rad", True),                       # bool is not a number here
    lambda d: d.__setitem__("stamp_s", math.inf),                    # non-finite
    lambda d: d.__setitem__("v_est_h_m_s", [0.0, 0.0]),              # wrong length
    lambda d: d.__setitem__("obstacle_points_c_m", [[0.0, "x", 1.0]]),
    lambda d: d.__setitem__("version", 1),                           # another version
    lambda d: d.__setitem__("mode", 2),
    lambda d: d.pop("vertical"),                                     # version 2's vertical limits
    lambda d: d["vertical"].__setitem__("ceiling_height_m", "2.5"),
    lambda d: d["vertical"].__setitem__("ceiling_height_m", math.inf),   # unbounded is null, never inf
    lambda d: d["vertical"].pop("floor_height_m"),
])
def test_decode_rejects_anything_but_the_contract(mutate: Any) -> None:
    d = _wire(_producer_meta(True))
    OperatorImageMeta.from_wire(d)   # the unmutated dict decodes
    mutate(d)
    with pytest.raises(ProtocolError):
        OperatorImageMeta.from_wire(d)


def test_the_vertical_limits_reach_the_station_overlay() -> None:
    """Issue 14: the ground station shows the safety layer's vertical limits as the companion applied them."""
    from teleop.config import TeleopConfig
    from teleop.view_loop import overlay

    params = PanScanParams(False, 0.6, 1.5)
    scan = pan_scan(params, 0.0)
    ref = reference_velocity(OperatorInput(0.0, 0.0, 1.0), np.eye(3), scan, None,
                             ReferenceParams(room_height_m=3.0, max_height_m=None), height_m=1.2)
    meta = operator_image_meta(1.0, Out(), ref, scan, params, np.zeros(3), Mode.TELEOP, None, np.eye(3),
                               np.zeros(3))
    got = OperatorImageMeta.from_wire(_wire(meta))
    assert got.vertical.ceiling_height_m == pytest.approx(3.0 - 0.10 - 0.45)  # the entry minus its error and d_safe
    assert got.vertical.floor_height_m == pytest.approx(0.3) and got.vertical.height_m == pytest.approx(1.2)
    status = {"battery_v": None, "min_obstacle_m": None, "link": "ok", "mode": "TELEOP", "armed": True,
              "force_n": [0.0, 0.0, 0.0], "warnings": []}
    assert "height 1.20 m  floor 0.30  ceiling 2.45" in overlay(TeleopConfig(), status, got).status_lines
    unknown = reference_velocity(OperatorInput(), np.eye(3), scan, None, ReferenceParams())   # no height known
    none = OperatorImageMeta.from_wire(_wire(operator_image_meta(1.0, Out(), unknown, scan, params, np.zeros(3),
                                                                 Mode.TELEOP, None, np.eye(3), np.zeros(3))))
    assert none.vertical.ceiling_height_m is None and none.vertical.height_m is None


def test_decode_rejects_a_non_dict() -> None:
    with pytest.raises(ProtocolError):
        OperatorImageMeta.from_wire([])
    with pytest.raises(ProtocolError):
        OperatorImageMeta.from_wire({})


def _landing_output(points_h_m: np.ndarray, height_m: float) -> Any:
    """The producer's own output type (perception.pipeline.PerceptionOutput) for a vehicle height_m up, level, still;
    no sectors (the map's points alone)."""
    from perception.pipeline import PerceptionOutput

    return PerceptionOutput(stamp_s=0.0, roll_rad=0.0, pitch_rad=0.0, yaw_rad=0.0, omega_q_rad_s=np.zeros(3),
                            v_h_m_s=np.zeros(3), v_h_cov=np.eye(3) * 1e-4,
                            position_m=np.array([0.0, 0.0, -height_m]), odometry_ok=True, odometry_fitness=1.0,
                            obstacle_points_c_m=np.zeros((0, 3)), obstacle_points_h_m=points_h_m,
                            sectors=None, nearest_obstacle_h_m=None, processing_time_s=0.0)  # type: ignore[arg-type]


def _floor_h_m(height_m: float) -> np.ndarray:
    """A 2 m x 2 m floor grid (5 cm) height_m below the vehicle, in H (z down)."""
    xs = np.arange(-1.0, 1.0, 0.05)
    gx, gy = np.meshgrid(xs, xs)
    return np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, height_m)])


@pytest.mark.parametrize("height_m", [0.5, 0.2, 0.1])
def test_the_floor_is_neither_a_dot_nor_an_obstacle_warning_while_landing(height_m: float) -> None:
    """Landing over a bare floor: the avoidance ignores it (below the band, or within the floor margin), so the
    feedback's nearest obstacle is none and the image carries no obstacle dots (was: the floor's points as
    orange dots and 'OBSTACLE 0.50 m')."""
    from companion.avoidance import repulsion_velocity
    from companion.frame_step import frame_step

    params = ReferenceParams()
    floor = _floor_h_m(height_m)
    assert np.allclose(repulsion_velocity(floor, params, height_m), 0.0)   # what the avoidance does with it
    out = _landing_output(floor, height_m)
    R_qc = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])   # optical axis ahead
    scan = pan_scan(PanScanParams(False, 0.6, 1.5), 0.0)
    step = frame_step(out, OperatorInput(), R_qc, scan, params, True, True)
    assert step.nearest is None
    meta = operator_image_meta(1.0, out, step.ref, scan, PanScanParams(False, 0.6, 1.5), np.zeros(3), Mode.LAND,
                               step.obstacle_points_h_m, R_qc, np.zeros(3))
    assert meta.obstacle_points_c_m == ()


def test_a_column_over_the_floor_is_the_one_obstacle_shown_where_it_is() -> None:
    """A column 0.7 m ahead over the floor, vehicle 0.5 m up: the feedback's nearest obstacle is the column at
    0.7 m (its band points count horizontally; the floor 0.5 m below would have been 0.5 m), and the image's
    dots are the column's points, each mapped back to H (tilted camera, offset mount, a rolled body) where the
    avoidance has it."""
    from companion.frame_step import frame_step
    from quadlink.frames import R_hq, Rx

    params = ReferenceParams()
    height = 0.5
    zs = np.linspace(-0.25, 0.25, 6)   # within the band about the vehicle's height
    column = np.column_stack([np.full(6, 0.7), np.full(6, 0.1), zs])
    out = dataclasses.replace(_landing_output(np.vstack([_floor_h_m(height), column]), height),
                              roll_rad=0.1, pitch_rad=-0.05)
    R_qc = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]) @ Rx(-0.3)   # tilted down
    p_qc = np.array([0.08, 0.0, 0.03])
    scan = pan_scan(PanScanParams(False, 0.6, 1.5), 0.0)
    step = frame_step(out, OperatorInput(), R_qc, scan, params, True, True)
    assert step.nearest is not None
    assert step.nearest[1] == pytest.approx(math.hypot(0.7, 0.1))
    meta = operator_image_meta(1.0, out, step.ref, scan, PanScanParams(False, 0.6, 1.5), np.zeros(3),
                               Mode.TELEOP, step.obstacle_points_h_m, R_qc, p_qc)
    p_c = np.asarray(meta.obstacle_points_c_m)
    assert p_c.shape == (6, 3)
    back_h = (p_c @ R_qc.T + p_qc) @ R_hq(out.roll_rad, out.pitch_rad).T   # p_h = R_hq (R_qc p_c + p_qc)
    assert sorted(map(tuple, np.round(back_h, 2))) == sorted(map(tuple, np.round(column, 2)))

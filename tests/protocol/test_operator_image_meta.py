"""OperatorImageMeta's wire form: strict decode (protocol tier)."""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np
import pytest

from companion.frame_step import operator_image_meta
from companion.modes import Mode
from companion.pan_scan import PanScanParams, pan_scan
from companion.reference import OperatorInput, ReferenceParams, reference_velocity
from quadlink.camera import CameraIntrinsics, RecordDecoder, RgbdFrame, encode_record
from quadlink.errors import ProtocolError
from quadlink.operator_image import OperatorImageMeta
from teleop.view_loop import image_meta


class Out:
    """The fields of perception.pipeline.PerceptionOutput that the producer reads."""

    roll_rad, pitch_rad, yaw_rad = 0.05, -0.02, 0.3
    v_h_m_s = np.array([0.2, -0.1, 0.0])
    obstacle_points_c_m = np.array([[0.1, 0.0, 1.2], [np.nan, 0.0, 1.0], [-0.3, 0.1, 2.0]])


def _producer_meta(enabled: bool) -> OperatorImageMeta:
    params = PanScanParams(enabled, 0.6, 1.5)
    scan = pan_scan(params, 0.7)
    R_qc = np.eye(3)
    ref = reference_velocity(OperatorInput(1.0, 0.0, 0.0), R_qc, scan, None, ReferenceParams())
    return operator_image_meta(12.5, Out(), ref, scan, params, np.array([0.0, 0.0, 0.4]), Mode.TELEOP)


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
    lambda d: d.__setitem__("version", 2),                           # another version
    lambda d: d.__setitem__("mode", 2),
])
def test_decode_rejects_anything_but_the_contract(mutate: Any) -> None:
    d = _wire(_producer_meta(True))
    OperatorImageMeta.from_wire(d)   # the unmutated dict decodes
    mutate(d)
    with pytest.raises(ProtocolError):
        OperatorImageMeta.from_wire(d)


def test_decode_rejects_a_non_dict() -> None:
    with pytest.raises(ProtocolError):
        OperatorImageMeta.from_wire([])
    with pytest.raises(ProtocolError):
        OperatorImageMeta.from_wire({})

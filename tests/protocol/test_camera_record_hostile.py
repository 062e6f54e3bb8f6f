"""Hostile camera records (issue 16): every malformed header is a ProtocolError before any allocation, the
decoder's buffer stays bounded, and a well-formed record after a bad one still decodes."""

from __future__ import annotations

import json
import struct

import cv2
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from test_camera_stream import make_frame

from quadlink.camera import MAX_PAYLOAD_BYTES, RecordDecoder, encode_record, jpeg_size
from quadlink.errors import ProtocolError

pytestmark = pytest.mark.fuzz


def _with_header(record: bytes, **changes: object) -> bytes:
    _, n = struct.unpack_from("<4sI", record)
    header = json.loads(record[8:8 + n])
    header.update(changes)
    head = json.dumps(header).encode()  # json writes NaN / Infinity as the bare tokens a hostile peer sends
    return struct.pack("<4sI", b"QLCF", len(head)) + head + record[8 + n:]


@pytest.mark.parametrize("changes", [
    {"depth_bytes": -1536},                     # was: the buffer never shrank, 1.46 GB and growing
    {"rgb_bytes": float("inf")},                # was: OverflowError into the loop
    {"seq": float("inf")},                      # 1e999 parses as inf
    {"height": float("-inf")},
    {"stamp_s": float("nan")},                  # was: NaN stamps reached the estimator
    {"stamp_s": float("inf")},
    {"R_qc": [[1.0, 0.0], [0.0, 1.0]]},         # wrong shape
    {"R_qc": [[2.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]]},  # not a rotation
    {"p_qc_m": [0.0, float("nan"), 0.0]},
    {"width": 0},
    {"width": 100000},
    {"intrinsics": {"fx": -1.0, "fy": 1.0, "cx": 0.0, "cy": 0.0}},
    {"rgb_encoding": "png"},
    {"rgb_bytes": MAX_PAYLOAD_BYTES + 1},
])
def test_bad_header_field_is_refused_and_the_next_record_decodes(rng: np.random.Generator,
                                                                  changes: dict[str, object]) -> None:
    bad, good = encode_record(make_frame(rng, 1)), encode_record(make_frame(rng, 2))
    decoder = RecordDecoder()
    with pytest.raises(ProtocolError):
        decoder.feed(_with_header(bad, **changes))
    assert decoder.pending_bytes <= len(bad)
    frames: list = []
    for _ in range(3):  # a framing error clears the buffer; a content error drops the one record
        try:
            frames += decoder.feed(good)
            break
        except ProtocolError:
            continue
    assert [f.seq for f in frames][-1:] == [2]


def test_decoded_jpeg_must_match_the_header_size(rng: np.random.Generator) -> None:
    frame = make_frame(rng, 5)
    record = encode_record(frame, rgb_jpeg=True)
    with pytest.raises(ProtocolError, match="JPEG is"):
        RecordDecoder().feed(_with_header(record, width=16, height=12, depth_bytes=16 * 12 * 2,
                                          depth_encoding="mm_u16le")[: 8 + 10 ** 6])
    assert RecordDecoder().feed(record)[0].rgb.shape == (24, 32, 3)


def test_jpeg_claiming_a_huge_image_is_refused_before_decoding() -> None:
    ok, buf = cv2.imencode(".jpg", np.zeros((8, 8, 3), np.uint8))
    assert ok
    data = bytearray(buf.tobytes())
    sof = data.index(b"\xff\xc0")
    data[sof + 5:sof + 9] = struct.pack(">HH", 30000, 30000)  # height, width in the frame header
    assert jpeg_size(bytes(data)) == (30000, 30000)
    assert len(data) < 1000
    # header consistent with the JPEG's claim: still refused, by the image-side limit
    k = {"fx": 100.0, "fy": 100.0, "cx": 0.0, "cy": 0.0}
    header = {"seq": 1, "stamp_s": 0.0, "width": 30000, "height": 30000, "intrinsics": k,
              "R_qc": np.eye(3).tolist(), "p_qc_m": [0, 0, 0], "rgb_encoding": "jpeg", "rgb_bytes": len(data),
              "depth_encoding": "none", "depth_bytes": 0, "meta": {}}
    head = json.dumps(header).encode()
    with pytest.raises(ProtocolError, match="width"):
        RecordDecoder().feed(struct.pack("<4sI", b"QLCF", len(head)) + head + bytes(data))


@given(st.dictionaries(st.sampled_from(["seq", "stamp_s", "width", "height", "rgb_bytes", "depth_bytes", "R_qc",
                                        "p_qc_m", "rgb_encoding", "depth_encoding", "intrinsics", "meta"]),
                       st.one_of(st.integers(-10**20, 10**20), st.floats(allow_nan=True), st.text(max_size=5),
                                 st.none(), st.lists(st.floats(), max_size=4),
                                 st.dictionaries(st.text(max_size=3), st.floats(), max_size=3))),
       st.binary(max_size=64))
def test_fuzzed_headers_never_escape_as_anything_but_protocol_errors(changes: dict, tail: bytes) -> None:
    rng = np.random.default_rng(1)
    decoder = RecordDecoder()
    record = _with_header(encode_record(make_frame(rng, 1)), **changes) + tail
    try:
        frames = decoder.feed(record)
    except ProtocolError:
        frames = []
    for frame in frames:
        assert np.isfinite(frame.stamp_s) and frame.R_qc.shape == (3, 3)
        assert frame.rgb.shape == (frame.intrinsics.height, frame.intrinsics.width, 3)
    assert decoder.pending_bytes <= len(record)

"""Camera stream records: exact round trip, chunking, corruption, acks for lock-step."""

from __future__ import annotations

import json
import struct
import time

import numpy as np
import pytest

from quadlink.camera import (
    CameraIntrinsics,
    CameraStreamClient,
    CameraStreamServer,
    RecordDecoder,
    RgbdFrame,
    encode_record,
)
from quadlink.errors import LinkError, ProtocolError


def make_frame(rng: np.random.Generator, seq: int = 3) -> RgbdFrame:
    k = CameraIntrinsics.from_fov(32, 24, 58.0, 45.0)
    depth = rng.uniform(0.5, 3.5, (24, 32)).astype(np.float32)
    depth[0, :5] = 0.0
    return RgbdFrame(seq, 12.5 + seq / 30, rng.integers(0, 256, (24, 32, 3), dtype=np.uint8), depth, k,
                     R_qc=np.eye(3)[[1, 2, 0]], p_qc_m=np.array([0.1, 0.0, 0.05]), meta={"roll_rad": 0.1})


def test_intrinsics_from_xtion_fov() -> None:
    k = CameraIntrinsics.from_fov(320, 240, 58.0, 45.0)
    assert k.fx == pytest.approx(288.6, abs=0.1) and k.fy == pytest.approx(289.7, abs=0.1)
    half = k.scaled(0.5)
    assert (half.width, half.height) == (160, 120) and half.fx == pytest.approx(k.fx / 2)


def test_record_round_trip_with_byte_chunking(rng: np.random.Generator) -> None:
    frames = [make_frame(rng, seq) for seq in range(3)]
    stream = b"".join(encode_record(f) for f in frames)
    decoder = RecordDecoder()
    out = []
    cut = sorted(rng.choice(len(stream), 20, replace=False))
    for start, end in zip([0, *cut], [*cut, len(stream)]):
        out += decoder.feed(stream[start:end])
    assert [f.seq for f in out] == [0, 1, 2]
    for sent, got in zip(frames, out):
        assert np.array_equal(got.rgb, sent.rgb)
        assert got.depth_m is not None and sent.depth_m is not None
        assert np.max(np.abs(got.depth_m - sent.depth_m)) <= 0.0005 + 1e-6  # millimetre quantisation
        assert got.depth_m[0, 0] == 0.0
        assert got.meta == sent.meta
        assert got.stamp_s == sent.stamp_s and got.intrinsics == sent.intrinsics


def test_a_sensor_record_carries_no_mount_and_the_vehicles_own_stream_does(rng: np.random.Generator) -> None:
    """Issue 29: where the camera sits is the reader's calibration; only the vehicle's operator image stream, whose
    producer is the vehicle itself, names the mount it used."""
    frame = make_frame(rng, seq=5)
    assert not np.allclose(frame.R_qc, np.eye(3))
    sensor = encode_record(frame)
    header = json.loads(sensor[8:8 + struct.unpack_from("<I", sensor, 4)[0]])
    assert "R_qc" not in header and "p_qc_m" not in header
    (got,) = RecordDecoder().feed(sensor)
    assert np.array_equal(got.R_qc, np.eye(3)) and np.array_equal(got.p_qc_m, np.zeros(3))
    (own,) = RecordDecoder().feed(encode_record(frame, with_mount=True))
    assert np.allclose(own.R_qc, frame.R_qc) and np.allclose(own.p_qc_m, frame.p_qc_m)


@pytest.mark.parametrize("extra", [{"true_R_qc": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}, {"scene": "paper-arena"},
                                   {"p_qc_m": [0.0, 0.0, 0.0]}])
def test_a_header_outside_the_schema_is_refused(rng: np.random.Generator, extra: dict[str, object]) -> None:
    rec = encode_record(make_frame(rng))
    n = struct.unpack_from("<I", rec, 4)[0]
    header = {**json.loads(rec[8:8 + n]), **extra}
    head = json.dumps(header).encode()
    with pytest.raises(ProtocolError, match="schema|without the other"):
        RecordDecoder().feed(struct.pack("<4sI", b"QLCF", len(head)) + head + rec[8 + n:])


def test_jpeg_colour_is_close(rng: np.random.Generator) -> None:
    frame = make_frame(rng)
    smooth = np.repeat(np.linspace(0, 255, 32, dtype=np.uint8)[None, :, None], 24, axis=0).repeat(3, axis=2)
    frame = RgbdFrame(frame.seq, frame.stamp_s, smooth, None, frame.intrinsics)
    (got,) = RecordDecoder().feed(encode_record(frame, rgb_jpeg=True))
    assert got.depth_m is None
    assert np.mean(np.abs(got.rgb.astype(int) - smooth.astype(int))) < 4.0


def test_corrupt_stream_raises_protocol_error(rng: np.random.Generator) -> None:
    with pytest.raises(ProtocolError):
        RecordDecoder().feed(b"JUNK" + bytes(100))
    record = bytearray(encode_record(make_frame(rng)))
    record[10] = ord("{")  # break the JSON header
    with pytest.raises(ProtocolError):
        RecordDecoder().feed(bytes(record))


def test_record_with_wrong_image_sizes_is_dropped_and_the_next_decodes(rng: np.random.Generator) -> None:
    """A record whose header says 32x24 but whose colour image is 12 bytes short: a ProtocolError, the record
    leaves the buffer whole (nothing of it keeps the buffer locked), and the decoder reads the next one."""
    import json
    import struct

    bad, good = make_frame(rng, 1), make_frame(rng, 2)
    rec = encode_record(bad)
    magic, n = struct.unpack_from("<4sI", rec)
    header = json.loads(rec[8:8 + n])
    header["rgb_bytes"] -= 12
    head = json.dumps(header).encode()
    body = rec[8 + n:]
    broken = struct.pack("<4sI", magic, len(head)) + head + body[:header["rgb_bytes"]] + body[-header["depth_bytes"]:]
    decoder = RecordDecoder()
    with pytest.raises(ProtocolError, match="corrupt camera record"):
        decoder.feed(broken + encode_record(good)[:40])
    assert decoder.pending_bytes == 40
    (got,) = decoder.feed(encode_record(good)[40:])
    assert got.seq == 2 and np.array_equal(got.rgb, good.rgb)


def test_server_client_acks_for_lockstep(rng: np.random.Generator) -> None:
    server = CameraStreamServer("127.0.0.1", 0)
    client = CameraStreamClient(f"tcp://127.0.0.1:{server.port}")
    try:
        assert client.read(0.2) is None  # nothing published yet; the read connects (lazily)
        assert server.wait_for_client(2.0)
        frame = make_frame(rng, seq=41)
        assert server.publish(frame) == 1
        got = client.read(2.0)
        assert got is not None and got.seq == 41
        assert not server.wait_acks(41, 0.05)  # not acked yet: lock-step would wait
        client.ack(41)
        assert server.wait_acks(41, 2.0)
    finally:
        client.close()
        server.close()


def test_client_url_must_be_tcp() -> None:
    with pytest.raises(LinkError):
        CameraStreamClient("udp://127.0.0.1:5762")


def test_a_consumer_that_fell_behind_reads_the_newest_frame(rng: np.random.Generator) -> None:
    """Issue 30: a starved companion processes the present, never a backlog; what it skipped is counted."""
    server = CameraStreamServer("127.0.0.1", 0)
    client = CameraStreamClient(f"tcp://127.0.0.1:{server.port}")
    try:
        assert client.read(0.2) is None
        assert server.wait_for_client(2.0)
        for seq in range(10, 15):
            assert server.publish(make_frame(rng, seq=seq)) == 1
        time.sleep(0.3)   # all five are in the socket now
        got = client.read(2.0, newest=True)
        assert got is not None and got.seq == 14 and client.frames_skipped == 4
        assert server.publish(make_frame(rng, seq=15)) == 1
        nxt = client.read(2.0, newest=True)
        assert nxt is not None and nxt.seq == 15 and client.frames_skipped == 4
    finally:
        client.close()
        server.close()

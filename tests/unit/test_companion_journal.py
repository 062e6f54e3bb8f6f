"""companion.journal's file format: what a writer writes reads back as events with their readings and writes, and a
file that is not a journal, or is cut or corrupt, is a clear error or a warning, never a crash or a silent loss."""

from __future__ import annotations

import logging
import struct
from pathlib import Path

import numpy as np
import pytest

from companion.config import CompanionConfig
from companion.journal import JournalWriter, Kind, decode_frame, read_events
from companion.replay import replay_journal
from perception.pipeline import PerceptionConfig
from quadlink.camera import CameraIntrinsics, RgbdFrame
from quadlink.config import to_dict
from quadlink.errors import ConfigError, ProtocolError
from quadlink.mavlink.security import SecurityConfig


def _header(cfg: CompanionConfig | None = None) -> dict[str, object]:
    return {"companion": to_dict(cfg or CompanionConfig()), "perception": to_dict(PerceptionConfig()), "seed": 3}


class _Sink:
    def __init__(self) -> None:
        self.written: list[bytes] = []

    def write(self, buf: bytes) -> None:
        self.written.append(buf)

    def recv_msg(self) -> None:
        return None

    def close(self) -> None:
        pass


def test_events_read_back_with_the_readings_and_writes_taken_inside_them(tmp_path: Path) -> None:
    w = JournalWriter(tmp_path / "j.qljn", _header())
    t = iter([1.0, 2.0, 3.0, 4.0, 5.0])
    clock = w.clock(lambda: next(t), Kind.CLOCK)
    sink = _Sink()
    link = w.link(sink, Kind.OUT_GCS)
    clock()                                   # outside any event: not journaled
    with w.event(Kind.INIT):
        clock()
    with w.event(Kind.GCS, b"\xfd\x01"):
        clock()
        clock()
        link.write(b"abc")
        with w.event(Kind.PERIODIC):          # nested: part of the outer event
            link.write(b"de")
    link.write(b"outside")                    # outside: passed on, not journaled
    w.close()
    assert sink.written == [b"abc", b"de", b"outside"]
    header, events = read_events(tmp_path / "j.qljn")
    assert header["seed"] == 3 and header["version"] == 1
    got = list(events)
    assert [e.kind for e in got] == [Kind.INIT, Kind.GCS]
    assert list(got[0].readings[Kind.CLOCK]) == [2.0]
    assert got[1].payload == b"\xfd\x01" and list(got[1].readings[Kind.CLOCK]) == [3.0, 4.0]
    assert got[1].outputs == [(Kind.OUT_GCS, b"abc"), (Kind.OUT_GCS, b"de")]


def test_a_frame_round_trips_with_its_mount_and_millimetre_depth(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    K = CameraIntrinsics.from_fov(32, 24, 58.0, 45.0)
    depth = (rng.integers(0, 4000, (24, 32)) / 1000.0).astype(np.float32)
    R = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    w = JournalWriter(tmp_path / "j.qljn", _header())
    # a frame as the companion has it: decoded from the camera stream's millimetres
    frame = decode_frame(w.frame_payload(RgbdFrame(7, 1.25, rng.integers(0, 255, (24, 32, 3), dtype=np.uint8), depth,
                                                   K, R, np.array([0.1, 0, 0]))))
    assert frame.depth_m is not None
    depth = frame.depth_m
    back = decode_frame(w.frame_payload(frame))
    w.close()
    assert back.seq == 7 and back.stamp_s == 1.25 and np.array_equal(back.rgb, frame.rgb)
    assert back.depth_m is not None and np.array_equal(back.depth_m, depth)
    assert np.array_equal(back.R_qc, R) and np.array_equal(back.p_qc_m, frame.p_qc_m)


def test_not_a_journal_or_another_version_is_a_clear_error(tmp_path: Path) -> None:
    (tmp_path / "a").write_bytes(b"QLCF" + b"\x00" * 20)
    with pytest.raises(ProtocolError, match="not a companion journal"):
        read_events(tmp_path / "a")
    (tmp_path / "b").write_bytes(b"QL")
    with pytest.raises(ProtocolError, match="too short"):
        read_events(tmp_path / "b")
    head = b'{"version": 99}'
    (tmp_path / "c").write_bytes(struct.pack("<4sI", b"QLJN", len(head)) + head)
    with pytest.raises(ProtocolError, match="version 99"):
        read_events(tmp_path / "c")


def test_a_cut_journal_keeps_its_whole_events_and_a_corrupt_one_is_refused(tmp_path: Path,
                                                                            caplog: pytest.LogCaptureFixture) -> None:
    w = JournalWriter(tmp_path / "j.qljn", _header())
    for k in range(3):
        with w.event(Kind.AUTOPILOT, bytes([k]) * 30):
            pass
    w.close()
    data = (tmp_path / "j.qljn").read_bytes()
    (tmp_path / "cut").write_bytes(data[:-10])
    with caplog.at_level(logging.WARNING):
        _, events = read_events(tmp_path / "cut")
        assert [e.payload[0] for e in events] == [0, 1]
    assert "truncated" in caplog.text
    bad = bytearray(data)
    bad[-35] = 200   # the last record's kind
    (tmp_path / "bad").write_bytes(bytes(bad))
    with pytest.raises(ProtocolError, match="unknown record kind 200"):
        list(read_events(tmp_path / "bad")[1])


def test_a_signed_ground_link_is_not_replayed(tmp_path: Path) -> None:
    cfg = CompanionConfig(security=SecurityConfig(require_signing=True))
    JournalWriter(tmp_path / "j.qljn", _header(cfg)).close()
    with pytest.raises(ConfigError, match="signed"):
        replay_journal(tmp_path / "j.qljn")


def test_a_journal_without_events_is_not_identical(tmp_path: Path) -> None:
    JournalWriter(tmp_path / "j.qljn", _header()).close()
    assert not replay_journal(tmp_path / "j.qljn").identical


def test_an_event_before_the_init_is_a_clear_error(tmp_path: Path) -> None:
    """(quadlink.journal.replay_events: both processes' replays share the loop that checks this)."""
    w = JournalWriter(tmp_path / "early.qljn", _header())
    with w.event(Kind.PERIODIC):
        pass
    w.close()
    with pytest.raises(ConfigError, match="before the INIT"):
        replay_journal(tmp_path / "early.qljn")

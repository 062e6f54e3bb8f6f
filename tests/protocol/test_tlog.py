"""The .tlog writer produces files pymavlink's own tools read, and our reader reads them back."""

from __future__ import annotations

from pathlib import Path

from quadlink.mavlink import mavlink
from quadlink.mavlink.connection import _install_dialect
from quadlink.mavlink.tlog import TlogWriter, read_tlog


def write_sample(path: Path) -> None:
    codec = mavlink.MAVLink(None, srcSystem=1, srcComponent=191)
    with TlogWriter(path) as log:
        for k in range(20):
            log.write(codec.heartbeat_encode(18, 8, 0, 0, 4).pack(codec), 1_700_000_000.0 + k * 0.1)
            log.write(codec.teleop_feedback_encode(k, *([0.1 * k] * 16), -1.0, 2, 3).pack(codec),
                      1_700_000_000.05 + k * 0.1)


def test_round_trip_and_corruption(tmp_path: Path) -> None:
    path = tmp_path / "flight.tlog"
    write_sample(path)
    records = read_tlog(path)
    assert [m.get_type() for _, m in records[:2]] == ["HEARTBEAT", "TELEOP_FEEDBACK"]
    assert len(records) == 40
    assert records[1][0] == 1_700_000_000.05
    data = bytearray(path.read_bytes())
    data[200:210] = b"\x00" * 10  # damage one record in the middle
    path.write_bytes(bytes(data))
    survivors = read_tlog(path)
    assert 35 <= len(survivors) < 40


def test_pymavlink_mavutil_reads_our_tlog(tmp_path: Path) -> None:
    path = tmp_path / "flight.tlog"
    write_sample(path)
    mavutil = _install_dialect()
    log = mavutil.mavlink_connection(str(path))
    types = []
    try:
        while (msg := log.recv_match(blocking=False)) is not None:
            types.append(msg.get_type())
    finally:
        log.close()   # an unclosed file surfaced as an unraisable ResourceWarning in a later test
    assert types.count("TELEOP_FEEDBACK") == 20 and types.count("HEARTBEAT") == 20


def test_a_full_disk_stops_the_recording_not_the_caller(caplog) -> None:
    """/dev/full: every write fails with ENOSPC once the buffer is flushed; the writer logs it once, says so in
    ``failed`` and ignores the rest (a flight loop that records must not stop for its log)."""
    codec = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    packet = codec.heartbeat_encode(2, 12, 0, 0, 4).pack(codec)
    log = TlogWriter("/dev/full")
    for k in range(2000):   # ~60 kB: past any write buffer
        log.write(packet, 1_700_000_000.0 + k)
    log.close()
    assert log.failed is not None and log.failed.errno == 28
    assert 0 < log.records < 2000
    assert [r.levelname for r in caplog.records if "recording stopped" in r.getMessage()] == ["ERROR"]

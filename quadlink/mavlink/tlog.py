"""Telemetry logs in the ``.tlog`` format of MAVProxy/QGroundControl (read by mavlogdump.py, MAVExplorer).

Each record is an 8-byte big-endian count of microseconds since the Unix epoch followed by one raw
MAVLink packet. For simulated flights the time base is the simulation's, offset to a fixed epoch so
the tools show plausible dates.
"""

from __future__ import annotations

import logging
import struct
import threading
from pathlib import Path
from typing import Any, BinaryIO

_STAMP = struct.Struct(">Q")
log = logging.getLogger(__name__)


class TlogWriter:
    """Append MAVLink packets with their time to a .tlog file (thread-safe; flushes on close).

    A write error (a full disk) stops the recording with one logged error and ``failed`` set, never the caller:
    the flight loops that record must not stop for their log. Opening the file raises :class:`OSError` as usual.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file: BinaryIO = open(self.path, "wb")  # noqa: SIM115 - closed in close()
        self._lock = threading.Lock()
        self.records = 0
        self.failed: OSError | None = None

    def write(self, packet: bytes, stamp_s: float) -> None:
        """Log one raw MAVLink packet (``msg.get_msgbuf()``) taken at ``stamp_s`` (Unix seconds)."""
        with self._lock:
            if self._file.closed:
                return
            try:
                self._file.write(_STAMP.pack(int(stamp_s * 1e6)) + bytes(packet))
            except OSError as exc:
                self._fail(exc)
                return
            self.records += 1

    def _fail(self, exc: OSError) -> None:
        self.failed = exc
        log.error("%s: recording stopped after %d packets: %s", self.path, self.records, exc)
        try:
            self._file.close()
        except OSError:
            pass   # the buffered tail cannot be written either

    def close(self) -> None:
        with self._lock:
            if not self._file.closed:
                try:
                    self._file.close()
                except OSError as exc:
                    self._fail(exc)

    def __enter__(self) -> TlogWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def read_tlog(path: str | Path) -> list[tuple[float, Any]]:
    """All decodable messages of a .tlog as ``(unix_stamp_s, message)``; corrupt records are skipped.

    Parses the record framing itself (stamp, then one MAVLink 1 or 2 packet whose length is in its
    header) and decodes each packet with the quadlink dialect.
    """
    from quadlink.mavlink import mavlink

    data = Path(path).read_bytes()
    parser = mavlink.MAVLink(None)
    parser.robust_parsing = True
    out: list[tuple[float, Any]] = []
    i = 0
    while i + 8 < len(data):
        (stamp_us,) = _STAMP.unpack_from(data, i)
        start = i + 8
        magic = data[start]
        if magic == 0xFD and start + 10 <= len(data):
            signed = data[start + 2] & 0x01
            end = start + 12 + data[start + 1] + (13 if signed else 0)
        elif magic == 0xFE and start + 6 <= len(data):
            end = start + 8 + data[start + 1]
        else:
            i += 1  # lost sync: slide until a record lines up again
            continue
        if end > len(data):
            break
        try:
            messages = parser.parse_buffer(data[start:end]) or []
        except mavlink.MAVError:
            messages = []
        for msg in messages:
            if msg.get_type() != "BAD_DATA":
                out.append((stamp_us / 1e6, msg))
        i = end
    return out

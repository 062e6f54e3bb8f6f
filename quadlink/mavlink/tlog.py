"""Telemetry logs in the ``.tlog`` format of MAVProxy/QGroundControl (read by mavlogdump.py, MAVExplorer).

Each record is an 8-byte big-endian count of microseconds since the Unix epoch followed by one raw
MAVLink packet. For simulated flights the time base is the simulation's, offset to a fixed epoch so
the tools show plausible dates.
"""

from __future__ import annotations

import struct
import threading
from pathlib import Path
from typing import BinaryIO

_STAMP = struct.Struct(">Q")


class TlogWriter:
    """Append MAVLink packets with their time to a .tlog file (thread-safe; flushes on close)."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file: BinaryIO = open(self.path, "wb")  # noqa: SIM115 - closed in close()
        self._lock = threading.Lock()
        self.records = 0

    def write(self, packet: bytes, stamp_s: float) -> None:
        """Log one raw MAVLink packet (``msg.get_msgbuf()``) taken at ``stamp_s`` (Unix seconds)."""
        with self._lock:
            if self._file.closed:
                return
            self._file.write(_STAMP.pack(int(stamp_s * 1e6)) + bytes(packet))
            self.records += 1

    def close(self) -> None:
        with self._lock:
            if not self._file.closed:
                self._file.close()

    def __enter__(self) -> TlogWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

"""A MAVLink connection in memory, for the tiers' tests of the daemons' own dispatch (no socket)."""

from __future__ import annotations

from typing import Any

from quadlink.mavlink import mavlink


class MemoryConn:
    """What a daemon uses of a pymavlink ``mavfile``: its codec (``mav``, the given ids), ``write`` and ``close``;
    every byte written, by the daemon or through the codec, is kept in ``data``."""

    def __init__(self, sysid: int = 1, compid: int = 1) -> None:
        self.data = bytearray()
        self.mav = mavlink.MAVLink(self, sysid, compid)
        self.mav.robust_parsing = True

    def write(self, buf: bytes) -> None:
        self.data += buf

    def close(self) -> None:
        pass

    def messages(self) -> list[Any]:
        """What was written, decoded (BAD_DATA left out)."""
        rx = mavlink.MAVLink(None)
        rx.robust_parsing = True
        return [m for m in rx.parse_buffer(bytes(self.data)) or [] if m.get_type() != "BAD_DATA"]

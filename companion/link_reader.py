"""Reading a MAVLink link through the dialect's I/O-free codec instead of ``mavutil``'s ``recv_msg``.

``mavutil.mavfile.recv_msg`` parses one byte stream per call and then runs ``post_message`` (timestamps,
per-type message dictionaries, parameter and flight-mode bookkeeping) on every message: at the 500 Hz
HIGHRES_IMU of the autopilot link that bookkeeping costs as much as the decoding, and the daemon uses none
of it. :class:`CodecReader` keeps the link for the bytes (``recv``: a UDP datagram, or the bytes a serial
port has, with the link's own peer-address learning for ``udpin``) and decodes them with
``quadlink.mavlink.mavlink.MAVLink(None).parse_buffer``; messages come out one per ``recv_msg`` call, as
from ``mavutil``, so the daemon's loop is unchanged. Not thread-safe (pymavlink is not): parse and send in
the daemon's one thread.
"""

from __future__ import annotations

from collections import deque
from typing import Any

from quadlink.mavlink import mavlink


class CodecReader:
    """``recv_msg`` / ``write`` / ``close`` of a pymavlink ``mavfile``, decoding with the dialect's codec."""

    def __init__(self, link: Any) -> None:
        self.link = link
        self._codec = mavlink.MAVLink(None)
        self._codec.robust_parsing = True   # bad bytes come out as BAD_DATA (as with mavutil), never raise
        self._pending: deque[Any] = deque()

    def recv_msg(self) -> Any:
        """The next decoded message, or None when the link has nothing more now (non-blocking)."""
        pending = self._pending
        while not pending:
            data = self.link.recv(self._codec.bytes_needed())
            if not data:
                return None
            msgs = self._codec.parse_buffer(data)
            if msgs:
                pending.extend(msgs)
        return pending.popleft()

    def write(self, buf: bytes) -> Any:
        return self.link.write(buf)

    def close(self) -> Any:
        return self.link.close()

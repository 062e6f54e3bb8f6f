"""Reading a MAVLink link through the dialect's I/O-free codec instead of ``mavutil``'s ``recv_msg``.

``mavutil.mavfile.recv_msg`` parses one byte stream per call and then runs ``post_message`` (timestamps,
per-type message dictionaries, parameter and flight-mode bookkeeping) on every message: at the 500 Hz
HIGHRES_IMU of the autopilot link that bookkeeping costs as much as the decoding, and the daemon uses none
of it. :class:`CodecReader` keeps the link for the bytes (``recv``: a UDP datagram, or the bytes a serial
port has, with the link's own peer-address learning for ``udpin``) and decodes them with
``quadlink.mavlink.mavlink.MAVLink(None).parse_buffer``; messages come out one per ``recv_msg`` call, as
from ``mavutil``, so the daemon's loop is unchanged. Not thread-safe (pymavlink is not): parse and send in
the daemon's one thread.

**HIGHRES_IMU fast path.** The generated parser walks a datagram byte by byte through Python state
(~35 µs per message here); at 500 Hz that is the largest single cost of the daemon outside perception.
A chunk of bytes that is exactly one unsigned MAVLink 2 HIGHRES_IMU frame, arriving while the codec holds
no partial frame (a UDP datagram from the bridge always is), is checked and decoded directly: header with
``struct``, CRC-16/MCRF4XX over header + payload + CRC_EXTRA (``fastcrc``, as pymavlink itself uses when
present), payload zero-extended (MAVLink 2 trims trailing zeros) and unpacked with the message's own
``struct`` layout. The result is the dialect's own message object with the same header, buffer and CRC as
the codec would give; anything else (signed frames, other messages, several frames in one chunk, a bad
CRC) goes through the codec unchanged, so bad data is reported exactly as before.
"""

from __future__ import annotations

import struct
from collections import deque
from typing import Any

from fastcrc.crc16 import mcrf4xx as _mcrf4xx  # a pymavlink dependency; its generated code uses it too

from quadlink.mavlink import mavlink

_IMU = mavlink.MAVLink_highres_imu_message
_IMU_ID = mavlink.MAVLINK_MSG_ID_HIGHRES_IMU
_IMU_SIZE = _IMU.unpacker.size
_IMU_CRC_EXTRA = bytes([_IMU.crc_extra])
_V2_HEADER = struct.Struct("<BBBBBBBHB")   # magic, len, incompat, compat, seq, sys, comp, msgid lo16, hi8
_V2_OVERHEAD = 12                           # 10-byte header + 2-byte CRC (unsigned)


def decode_highres_imu_v2(data: bytes) -> Any | None:
    """The HIGHRES_IMU message in ``data`` if ``data`` is exactly one valid unsigned MAVLink 2 frame of
    it, else None (the caller then uses the general parser)."""
    n = len(data)
    if n < _V2_OVERHEAD or data[0] != mavlink.PROTOCOL_MARKER_V2:
        return None
    magic, mlen, incompat, compat, seq, src_sys, src_comp, id_lo, id_hi = _V2_HEADER.unpack_from(data)
    if incompat != 0 or (id_lo | (id_hi << 16)) != _IMU_ID or n != mlen + _V2_OVERHEAD or mlen > _IMU_SIZE:
        return None
    crc = data[n - 2] | (data[n - 1] << 8)
    if _mcrf4xx(bytes(data[1:n - 2]) + _IMU_CRC_EXTRA, 0xFFFF) != crc:
        return None   # let the codec report it as bad data
    payload = bytes(data[10:n - 2])
    fields = _IMU.unpacker.unpack(payload + bytes(_IMU_SIZE - mlen))   # orders are the identity here
    msg = _IMU(*fields)
    msg._msgbuf = bytearray(data)
    msg._payload = payload
    msg._crc = crc
    msg._header = mavlink.MAVLink_header(_IMU_ID, incompat, compat, mlen, seq, src_sys, src_comp)
    return msg


class CodecReader:
    """``recv_msg`` / ``write`` / ``close`` of a pymavlink ``mavfile``, decoding with the dialect's codec."""

    def __init__(self, link: Any) -> None:
        self.link = link
        self._codec = mavlink.MAVLink(None)
        self._codec.robust_parsing = True   # bad bytes come out as BAD_DATA (as with mavutil), never raise
        self._pending: deque[Any] = deque()
        self.fast_decoded = 0

    def recv_msg(self) -> Any:
        """The next decoded message, or None when the link has nothing more now (non-blocking)."""
        pending = self._pending
        while not pending:
            data = self.link.recv(self._codec.bytes_needed())
            if not data:
                return None
            if not self._codec.buf_len():   # no partial frame held: a whole-frame chunk may take the fast path
                msg = decode_highres_imu_v2(data)
                if msg is not None:
                    self.fast_decoded += 1
                    return msg
            msgs = self._codec.parse_buffer(data)
            if msgs:
                pending.extend(msgs)
        return pending.popleft()

    def write(self, buf: bytes) -> Any:
        return self.link.write(buf)

    def close(self) -> Any:
        return self.link.close()

"""The bridge's input journal: everything its main thread handles, in order, so that a flight's bridge can be re-run
open loop from it, bit for bit (issue 28), as the companion's is (:mod:`companion.journal`).

The bridge's behaviour is a function of what its main thread takes off the readers' queue (MK bytes from port 1
and port 2, MAVLink datagrams, link errors), of its housekeeping turns, and of the clocks it reads. Both loops —
the wall clock's and the deterministic lock-step's — hand them to the same two methods (``_dispatch`` and
``_housekeeping``), so the journal is written there: each *event* with the clock readings taken while it was handled
and the bytes it wrote. :func:`firmware_bridge.replay.replay_bridge_journal` builds a bridge from the journal's
header and hands it the same events on the recorded clocks.

File format: :mod:`quadlink.journal`'s container, magic ``b"QLBJ"``, with the header::

    {"version": 1, "bridge": <BridgeConfig as data>, "vehicle": <VehicleConfig as data>,
     "params": {name: value}, "started_unix_s": float}

Kinds: events (``INIT``: the daemon's construction; ``INPUT``: one item of the readers' queue, :func:`encode_input`;
``HOUSEKEEPING``: one turn of the periodic tasks); clock readings (``CLOCK``: the daemon's clock, the simulated time
in the lock-step; ``WALL``: the wall clock's readings in the main thread, which only time the IMU latency statistic;
``UNIX``: SYSTEM_TIME's Unix time); writes (``OUT_MK``: a frame for MK port 1, after one byte saying whether the
write succeeded; ``OUT_MAVLINK + i``: a MAVLink frame sent on endpoint ``i``). About 0.1 MB per second: each
500 Hz IMU sample in, its HIGHRES_IMU out, the clock readings (a 40 s real-time SITL session wrote 2.9 MB).

Limits: a signed ground link is not replayed (its key is not journaled); the reader threads' reconnections appear as
their ``link`` inputs only.
"""

from __future__ import annotations

import struct
from enum import IntEnum
from pathlib import Path
from typing import Any

from quadlink import journal as core
from quadlink.errors import ProtocolError
from quadlink.journal import JournalEvents

MAGIC = b"QLBJ"
VERSION = 1
MAX_ENDPOINTS = 16


class Kind(IntEnum):
    INIT = 1
    INPUT = 2
    HOUSEKEEPING = 3
    CLOCK = 16
    WALL = 17
    UNIX = 18
    OUT_MK = 32
    OUT_MAVLINK = 48   # + the endpoint's index


EVENTS = frozenset({Kind.INIT, Kind.INPUT, Kind.HOUSEKEEPING})
READINGS = (Kind.CLOCK, Kind.WALL, Kind.UNIX)
SCHEMA = core.JournalSchema(
    "bridge journal", MAGIC, VERSION,
    frozenset({int(k) for k in Kind} | {Kind.OUT_MAVLINK + i for i in range(MAX_ENDPOINTS)}),
    frozenset(int(k) for k in EVENTS), tuple(int(k) for k in READINGS))


def kind_name(kind: int) -> str:
    if Kind.OUT_MAVLINK <= kind < Kind.OUT_MAVLINK + MAX_ENDPOINTS:
        return f"MAVLink endpoint {kind - Kind.OUT_MAVLINK}"
    return Kind(kind).name


# ---- the readers' queue items: ("imu" | "cmd", bytes, read_wall_s), ("mav", index, bytes),
#      ("mavbad", index, text), ("link", "imu" | "cmd", text)
_TAGS = {"imu": 1, "cmd": 2, "mav": 3, "mavbad": 4, "link": 5}
_NAMES = {v: k for k, v in _TAGS.items()}
_F64 = struct.Struct("<d")


def encode_input(item: tuple[Any, ...]) -> bytes:
    """One item of the readers' queue as an INPUT event's payload (tag byte, then the item's fields)."""
    kind = item[0]
    tag = _TAGS.get(kind)
    if tag is None:
        raise ProtocolError(f"a bridge input of unknown kind {kind!r}")
    head = bytes([tag])
    if kind in ("imu", "cmd"):
        return head + _F64.pack(float(item[2])) + bytes(item[1])
    if kind == "mav":
        return head + bytes([int(item[1])]) + bytes(item[2])
    if kind == "mavbad":
        return head + bytes([int(item[1])]) + str(item[2]).encode()
    link = str(item[1]).encode()
    return head + bytes([len(link)]) + link + str(item[2]).encode()


def decode_input(payload: bytes) -> tuple[Any, ...]:
    """The queue item an INPUT event's payload holds (:func:`encode_input`'s inverse)."""
    if not payload or payload[0] not in _NAMES:
        raise ProtocolError(f"a journaled bridge input with tag {payload[:1].hex() or 'none'}")
    kind, body = _NAMES[payload[0]], payload[1:]
    if kind in ("imu", "cmd"):
        if len(body) < _F64.size:
            raise ProtocolError(f"a journaled {kind} input of {len(payload)} bytes")
        return kind, body[_F64.size:], _F64.unpack_from(body)[0]
    if not body:
        raise ProtocolError(f"a journaled {kind} input without its fields")
    if kind == "mav":
        return kind, body[0], body[1:]
    if kind == "mavbad":
        return kind, body[0], body[1:].decode(errors="replace")
    n = body[0]
    return kind, body[1:1 + n].decode(errors="replace"), body[1 + n:].decode(errors="replace")


class JournalWriter(core.JournalWriter):
    """Appends a running bridge's events to ``path`` (:class:`quadlink.journal.JournalWriter`)."""

    def __init__(self, path: str | Path, header: dict[str, Any]) -> None:
        super().__init__(path, header, SCHEMA)

    def mk_write(self, frame: bytes, ok: bool) -> None:
        self.output(Kind.OUT_MK, bytes([1 if ok else 0]) + bytes(frame))

    def mavlink_sent(self, endpoint: int, buf: bytes) -> None:
        if 0 <= endpoint < MAX_ENDPOINTS:
            self.output(Kind.OUT_MAVLINK + endpoint, buf)


def read_events(path: str | Path) -> tuple[dict[str, Any], JournalEvents]:
    """The bridge journal's header and its events (:func:`quadlink.journal.read_events`)."""
    return core.read_events(path, SCHEMA)

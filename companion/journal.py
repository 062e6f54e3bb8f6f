"""The companion's input journal: everything that reaches its handlers, in order, so that a flight's companion can be
re-run open loop from it, bit for bit (issue 28; PX4's and ArduPilot's replay of their estimators from a log).

The daemon's behaviour is a function of what its handlers are handed (the autopilot's and the ground stations'
messages, the camera's frames, the periodic tasks' turns) and of the clocks they read. Both loops — the wall clock's
and the deterministic lock-step's — hand them over through the same handlers, so the journal is written there: each
*event* (one message, one frame, one turn of the periodic tasks) with the clock readings taken while it was handled
and the bytes it wrote to each link. :func:`companion.replay.replay_journal` builds a companion from the journal's
own configuration, hands it the same events on the recorded clocks, and compares every byte written; the replay is
a third source of events beside the sockets and the lock-step, through the same handlers.

File format: :mod:`quadlink.journal`'s container, magic ``b"QLJN"``, with the header::

    {"version": 1, "companion": <CompanionConfig as data>, "perception": <PerceptionConfig as data>,
     "seed": int, "started_unix_s": float}

Kinds: an event (``INIT``: the daemon's construction; ``AUTOPILOT``/``GCS``: a message's raw frame; ``GCS_BAD``: an
undecodable ground-station datagram; ``FRAME``: a camera record, :mod:`quadlink.camera_record` with the frame's
mount; ``PERIODIC``), followed by what happened while it was handled: clock readings (``CLOCK``: the daemon's
clock; ``STOPWATCH``: what times its frame-to-setpoint statistic; float64) and writes (``OUT_AUTOPILOT``,
``OUT_GCS``: a frame's bytes). The wall clock only stamps the tlog and signs packets: it is not journaled.

Limits: a frame's depth is journaled in whole millimetres (the camera stream's unit: exact for the SITL, the Xtion and
a RealSense at its default 1 mm scale); a signed ground link is not replayed (its key is not journaled), nor the
operator image stream. About 400 kB per QVGA frame (``--record-frames``'s cost) plus ~60 B per message.
"""

from __future__ import annotations

from enum import IntEnum
from pathlib import Path
from typing import Any

from quadlink import journal as core
from quadlink.camera import RgbdFrame
from quadlink.camera_record import RecordDecoder, encode_record
from quadlink.errors import ProtocolError
from quadlink.journal import JournalEvent, JournalEvents

__all__ = ["EVENTS", "OUTPUTS", "READINGS", "SCHEMA", "JournalEvent", "JournalEvents", "JournalWriter", "Kind",
           "decode_frame", "read_events"]

MAGIC = b"QLJN"
VERSION = 1


class Kind(IntEnum):
    INIT = 1
    AUTOPILOT = 2
    GCS = 3
    GCS_BAD = 4
    FRAME = 5
    PERIODIC = 6
    CLOCK = 16
    STOPWATCH = 18
    OUT_AUTOPILOT = 32
    OUT_GCS = 33


EVENTS = frozenset({Kind.INIT, Kind.AUTOPILOT, Kind.GCS, Kind.GCS_BAD, Kind.FRAME, Kind.PERIODIC})
READINGS = (Kind.CLOCK, Kind.STOPWATCH)
OUTPUTS = (Kind.OUT_AUTOPILOT, Kind.OUT_GCS)
SCHEMA = core.JournalSchema("companion journal", MAGIC, VERSION, frozenset(int(k) for k in Kind),
                            frozenset(int(k) for k in EVENTS), tuple(int(k) for k in READINGS))


class JournalWriter(core.JournalWriter):
    """Appends a running companion's events to ``path`` (:class:`quadlink.journal.JournalWriter`)."""

    def __init__(self, path: str | Path, header: dict[str, Any]) -> None:
        super().__init__(path, header, SCHEMA)

    def link(self, link: Any, kind: Kind) -> JournaledLink:
        return JournaledLink(link, self, kind)

    def frame_payload(self, frame: RgbdFrame) -> bytes:
        return encode_record(frame, with_mount=True)


class JournaledLink:
    """A daemon's MAVLink link whose writes inside an event are journaled as ``kind``; everything else is the
    link's own (``recv_msg``, ``mav``, ``close``...)."""

    def __init__(self, link: Any, journal: JournalWriter, kind: Kind) -> None:
        self.link, self._journal, self._kind = link, journal, kind

    def write(self, buf: bytes) -> Any:
        self._journal.output(self._kind, buf)
        return self.link.write(buf)

    def recv_msg(self) -> Any:
        return self.link.recv_msg()

    def close(self) -> Any:
        return self.link.close()

    def __getattr__(self, name: str) -> Any:
        return getattr(self.link, name)


def read_events(path: str | Path) -> tuple[dict[str, Any], JournalEvents]:
    """The companion journal's header and its events (:func:`quadlink.journal.read_events`)."""
    return core.read_events(path, SCHEMA)


def decode_frame(payload: bytes) -> RgbdFrame:
    frames = RecordDecoder().feed(payload)
    if len(frames) != 1:
        raise ProtocolError(f"a journaled frame decoded to {len(frames)} frames")
    return frames[0]

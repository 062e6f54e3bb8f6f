"""The companion's input journal: everything that reaches its handlers, in order, so that a flight's companion can be
re-run open loop from it, bit for bit (issue 28; PX4's and ArduPilot's replay of their estimators from a log).

The daemon's behaviour is a function of what its handlers are handed (the autopilot's and the ground stations'
messages, the camera's frames, the periodic tasks' turns) and of the clocks they read. Both loops — the wall clock's
and the deterministic lock-step's — hand them over through the same handlers, so the journal is written there: each
*event* (one message, one frame, one turn of the periodic tasks) with the clock readings taken while it was handled
and the bytes it wrote to each link. :func:`replay_journal` builds a companion from the journal's own configuration,
hands it the same events on the recorded clocks, and compares every byte written (:class:`ReplayReport`); the
replay is a third source of events beside the sockets and the lock-step, through the same handlers.

File format (little-endian)::

    file    = b"QLJN" | uint32 header_len | header (UTF-8 JSON) | record*
    header  = {"version": 1, "companion": <CompanionConfig as data>, "perception": <PerceptionConfig as data>,
               "seed": int, "started_unix_s": float}
    record  = uint8 kind | uint32 length | payload

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

import contextlib
import json
import logging
import struct
import time
from collections import deque
from collections.abc import Callable, Generator, Iterator
from dataclasses import dataclass, field
from enum import IntEnum
from pathlib import Path
from typing import Any, BinaryIO

from quadlink.camera import RgbdFrame
from quadlink.camera_record import RecordDecoder, encode_record
from quadlink.errors import ProtocolError

log = logging.getLogger("companion.journal")

MAGIC = b"QLJN"
VERSION = 1
_PREFIX = struct.Struct("<4sI")
_RECORD = struct.Struct("<BI")
_F64 = struct.Struct("<d")
MAX_HEADER_BYTES = 1 << 20
MAX_RECORD_BYTES = 64 << 20


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


class JournalWriter:
    """Appends a running companion's events to ``path``. Not thread-safe: the daemon's one thread writes it.

    A write error (a full disk) stops the journal, never the flight loop; :attr:`failed` says so."""

    def __init__(self, path: str | Path, header: dict[str, Any]) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._f: BinaryIO | None = open(self.path, "wb", buffering=1 << 20)  # noqa: SIM115 - closed in close()
        head = json.dumps({"version": VERSION, "started_unix_s": time.time(), **header},
                          separators=(",", ":")).encode()
        self._write(_PREFIX.pack(MAGIC, len(head)) + head)
        self.active = False     # inside an event: readings and writes belong to it
        self.events = 0
        self.failed = False

    def _write(self, data: bytes) -> None:
        if self._f is None:
            return
        try:
            self._f.write(data)
        except OSError as exc:
            log.error("journal %s stopped: %s", self.path, exc)
            self.failed = True
            with contextlib.suppress(OSError):
                self._f.close()
            self._f = None

    def _record(self, kind: Kind, payload: bytes) -> None:
        self._write(_RECORD.pack(int(kind), len(payload)) + payload)

    def output(self, kind: Kind, buf: bytes) -> None:
        """Journal ``buf`` written to the link ``kind`` while an event is handled (nothing outside one)."""
        if self.active:
            self._record(kind, bytes(buf))

    @contextlib.contextmanager
    def event(self, kind: Kind, payload: bytes = b"") -> Iterator[None]:
        """``with journal.event(Kind.GCS, msg.get_msgbuf()): handle(msg)``: the event, then what its handling read
        and wrote. Events do not nest (a handler that handles another input is one event)."""
        if self.active:
            yield
            return
        self._record(kind, payload)
        self.events += 1
        self.active = True
        try:
            yield
        finally:
            self.active = False

    def clock(self, fn: Callable[[], float], kind: Kind) -> Callable[[], float]:
        """``fn``, with each reading taken inside an event journaled as ``kind``."""
        def read() -> float:
            t = fn()
            if self.active:
                self._record(kind, _F64.pack(t))
            return t
        return read

    def link(self, link: Any, kind: Kind) -> JournaledLink:
        return JournaledLink(link, self, kind)

    def frame_payload(self, frame: RgbdFrame) -> bytes:
        return encode_record(frame, with_mount=True)

    def close(self) -> None:
        if self._f is not None:
            with contextlib.suppress(OSError):
                self._f.close()
            self._f = None


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


@dataclass
class JournalEvent:
    index: int
    kind: Kind
    payload: bytes
    readings: dict[Kind, deque[float]] = field(default_factory=lambda: {k: deque() for k in READINGS})
    outputs: list[tuple[Kind, bytes]] = field(default_factory=list)


def read_header(f: BinaryIO, path: str | Path) -> dict[str, Any]:
    prefix = f.read(_PREFIX.size)
    if len(prefix) < _PREFIX.size:
        raise ProtocolError(f"{path}: not a companion journal (too short)")
    magic, n = _PREFIX.unpack(prefix)
    if magic != MAGIC:
        raise ProtocolError(f"{path}: not a companion journal (magic {magic!r}, expected {MAGIC!r})")
    if n > MAX_HEADER_BYTES:
        raise ProtocolError(f"{path}: journal header of {n} bytes is too large")
    try:
        header = json.loads(f.read(n))
    except ValueError as exc:
        raise ProtocolError(f"{path}: journal header is not JSON ({exc})") from None
    if not isinstance(header, dict) or header.get("version") != VERSION:
        raise ProtocolError(f"{path}: journal version {header.get('version') if isinstance(header, dict) else '?'} "
                            f"(this companion reads {VERSION})")
    return header


class JournalEvents:
    """The events of an open journal (an iterator); :meth:`close` closes the file, read to the end or not."""

    def __init__(self, f: BinaryIO, events: Generator[JournalEvent, None, None]) -> None:
        self._f, self._events = f, events

    def __iter__(self) -> JournalEvents:
        return self

    def __next__(self) -> JournalEvent:
        return next(self._events)

    def close(self) -> None:
        self._events.close()
        self._f.close()


def read_events(path: str | Path) -> tuple[dict[str, Any], JournalEvents]:
    """The journal's header and its events, each with the readings and writes recorded while it was handled. A
    truncated last record (the companion was killed) ends the events with a warning."""
    f = open(path, "rb")  # noqa: SIM115 - closed by the generator
    try:
        header = read_header(f, path)
    except BaseException:
        f.close()
        raise

    def events() -> Generator[JournalEvent, None, None]:
        with f:
            current: JournalEvent | None = None
            index = 0
            while True:
                head = f.read(_RECORD.size)
                if not head:
                    break
                if len(head) < _RECORD.size:
                    log.warning("%s: truncated record at the end ignored", path)
                    break
                kind_value, n = _RECORD.unpack(head)
                if n > MAX_RECORD_BYTES:
                    raise ProtocolError(f"{path}: record of {n} bytes (at most {MAX_RECORD_BYTES})")
                payload = f.read(n)
                if len(payload) < n:
                    log.warning("%s: truncated record at the end ignored", path)
                    break
                try:
                    kind = Kind(kind_value)
                except ValueError:
                    raise ProtocolError(f"{path}: unknown record kind {kind_value}") from None
                if kind in EVENTS:
                    if current is not None:
                        yield current
                    current = JournalEvent(index, kind, payload)
                    index += 1
                elif current is None:
                    raise ProtocolError(f"{path}: a {kind.name} record before any event")
                elif kind in READINGS:
                    current.readings[kind].append(_F64.unpack(payload)[0])
                else:
                    current.outputs.append((kind, payload))
            if current is not None:
                yield current

    return header, JournalEvents(f, events())


def decode_frame(payload: bytes) -> RgbdFrame:
    frames = RecordDecoder().feed(payload)
    if len(frames) != 1:
        raise ProtocolError(f"a journaled frame decoded to {len(frames)} frames")
    return frames[0]

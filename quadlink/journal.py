"""Input journals: the container every process's journal is written in (issue 28; PX4's and ArduPilot's replay of
their estimators from a log). A daemon's behaviour is a function of what its handlers are handed and of the clocks
they read; a journal holds each *event* (one input handed to a handler, one turn of a periodic task) with the clock
readings taken while it was handled and the bytes it wrote. A replay builds the daemon from the journal's header,
hands it the same events on the recorded clocks, and compares every byte written: a third source of events beside
the sockets and the lock-step, through the same handlers.

File format (little-endian)::

    file    = magic (4 bytes) | uint32 header_len | header (UTF-8 JSON, with "version") | record*
    record  = uint8 kind | uint32 length | payload

What the kinds mean is each process's (:class:`JournalSchema`): events, clock readings (float64) and writes.
Used by the companion (:mod:`companion.journal`), the bridge (:mod:`firmware_bridge.journal`) and the ground
station (:mod:`teleop.journal`).
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
from pathlib import Path
from typing import Any, BinaryIO

from quadlink.errors import ConfigError, ProtocolError

log = logging.getLogger("quadlink.journal")

_PREFIX = struct.Struct("<4sI")
_RECORD = struct.Struct("<BI")
F64 = struct.Struct("<d")
MAX_HEADER_BYTES = 1 << 20
MAX_RECORD_BYTES = 64 << 20


@dataclass(frozen=True)
class JournalSchema:
    """One process's journal: its magic and version, and which record kinds are events, clock readings (float64)
    and writes (everything else of ``kinds``)."""

    what: str                       # "companion journal"
    magic: bytes
    version: int
    kinds: frozenset[int]
    events: frozenset[int]
    readings: tuple[int, ...]

    def __post_init__(self) -> None:
        if len(self.magic) != 4:
            raise ValueError(f"a journal's magic is 4 bytes, got {self.magic!r}")
        if not self.events <= self.kinds or not set(self.readings) <= self.kinds:
            raise ValueError("the events and readings must be kinds of the journal")


class JournalWriter:
    """Appends a running daemon's events to ``path``. Not thread-safe: the daemon's one handling thread writes it
    (a clock read by another thread must not be wrapped by :meth:`clock`).

    A write error (a full disk) stops the journal, never the flight loop; :attr:`failed` says so."""

    def __init__(self, path: str | Path, header: dict[str, Any], schema: JournalSchema) -> None:
        self.path = Path(path)
        self.schema = schema
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._f: BinaryIO | None = open(self.path, "wb", buffering=1 << 20)  # noqa: SIM115 - closed in close()
        head = json.dumps({"version": schema.version, "started_unix_s": time.time(), **header},
                          separators=(",", ":")).encode()
        self._write(_PREFIX.pack(schema.magic, len(head)) + head)
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

    def _record(self, kind: int, payload: bytes) -> None:
        self._write(_RECORD.pack(int(kind), len(payload)) + payload)

    def output(self, kind: int, buf: bytes) -> None:
        """Journal ``buf`` written to the link ``kind`` while an event is handled (nothing outside one)."""
        if self.active:
            self._record(kind, bytes(buf))

    @contextlib.contextmanager
    def event(self, kind: int, payload: bytes = b"") -> Iterator[None]:
        """``with journal.event(KIND, payload): handle(...)``: the event, then what its handling read and wrote.
        Events do not nest (a handler that handles another input is one event)."""
        if self.active:
            yield
            return
        self.begin(kind, payload)
        try:
            yield
        finally:
            self.end()

    def begin(self, kind: int, payload: bytes = b"") -> None:
        """An event that is not one call (a loop's turn, begun and ended in separate steps): from here to
        :meth:`end`, what is read and written belongs to it."""
        if self.active:
            raise RuntimeError("a journal event begun inside another")
        self._record(kind, payload)
        self.events += 1
        self.active = True

    def end(self) -> None:
        self.active = False

    def clock(self, fn: Callable[[], float], kind: int) -> Callable[[], float]:
        """``fn``, with each reading taken inside an event journaled as ``kind``."""
        def read() -> float:
            t = fn()
            if self.active:
                self._record(kind, F64.pack(t))
            return t
        return read

    def close(self) -> None:
        if self._f is not None:
            with contextlib.suppress(OSError):
                self._f.close()
            self._f = None


@dataclass
class JournalEvent:
    index: int
    kind: int
    payload: bytes
    readings: dict[int, deque[float]] = field(default_factory=dict)
    outputs: list[tuple[int, bytes]] = field(default_factory=list)


def read_header(f: BinaryIO, path: str | Path, schema: JournalSchema) -> dict[str, Any]:
    prefix = f.read(_PREFIX.size)
    if len(prefix) < _PREFIX.size:
        raise ProtocolError(f"{path}: not a {schema.what} (too short)")
    magic, n = _PREFIX.unpack(prefix)
    if magic != schema.magic:
        raise ProtocolError(f"{path}: not a {schema.what} (magic {magic!r}, expected {schema.magic!r})")
    if n > MAX_HEADER_BYTES:
        raise ProtocolError(f"{path}: journal header of {n} bytes is too large")
    try:
        header = json.loads(f.read(n))
    except ValueError as exc:
        raise ProtocolError(f"{path}: journal header is not JSON ({exc})") from None
    if not isinstance(header, dict) or header.get("version") != schema.version:
        raise ProtocolError(f"{path}: journal version {header.get('version') if isinstance(header, dict) else '?'} "
                            f"(this {schema.what.split()[0]} reads {schema.version})")
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


def read_events(path: str | Path, schema: JournalSchema) -> tuple[dict[str, Any], JournalEvents]:
    """The journal's header and its events, each with the readings and writes recorded while it was handled. A
    truncated last record (the daemon was killed) ends the events with a warning."""
    f = open(path, "rb")  # noqa: SIM115 - closed by the generator
    try:
        header = read_header(f, path, schema)
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
                kind, n = _RECORD.unpack(head)
                if n > MAX_RECORD_BYTES:
                    raise ProtocolError(f"{path}: record of {n} bytes (at most {MAX_RECORD_BYTES})")
                payload = f.read(n)
                if len(payload) < n:
                    log.warning("%s: truncated record at the end ignored", path)
                    break
                if kind not in schema.kinds:
                    raise ProtocolError(f"{path}: unknown record kind {kind}")
                if kind in schema.events:
                    if current is not None:
                        yield current
                    current = JournalEvent(index, kind, payload, {k: deque() for k in schema.readings})
                    index += 1
                elif current is None:
                    raise ProtocolError(f"{path}: a record of kind {kind} before any event")
                elif kind in schema.readings:
                    current.readings[kind].append(F64.unpack(payload)[0])
                else:
                    current.outputs.append((kind, payload))
            if current is not None:
                yield current

    return header, JournalEvents(f, events())


class ReplayClock:
    """Gives back one event's recorded readings of one clock, in order; counts reads past them (``overread``)."""

    def __init__(self, kind: int, name: str) -> None:
        self.kind, self.name = kind, name
        self.queue: deque[float] = deque()
        self.overread = 0
        self._last = 0.0

    def load(self, event: JournalEvent) -> None:
        self.queue = deque(event.readings.get(self.kind, ()))
        self.overread = 0

    def __call__(self) -> float:
        if self.queue:
            self._last = self.queue.popleft()
        else:
            self.overread += 1
        return self._last


def first_difference(want: list[tuple[int, bytes]], got: list[tuple[int, bytes]], clocks: list[ReplayClock],
                     name: Callable[[int], str]) -> str | None:
    """How a replayed event differs from the flight's (its clock reads, then its writes), or None."""
    for clock in clocks:
        if clock.overread:
            return f"read the {clock.name} clock {clock.overread} more time(s) than the flight did"
        if clock.queue:
            return f"read the {clock.name} clock {len(clock.queue)} fewer time(s) than the flight did"
    if got == want:
        return None
    for i, (w, g) in enumerate(zip(want, got)):
        if w != g:
            return (f"write {i} differs: the flight wrote {w[1][:24].hex()}... to {name(w[0])}, the replay "
                    f"{g[1][:24].hex()}... to {name(g[0])}")
    return f"the flight wrote {len(want)} message(s), the replay {len(got)}"


@dataclass
class ReplayReport:
    events: int = 0
    by_kind: dict[str, int] = field(default_factory=dict)
    writes_compared: int = 0
    divergence: str | None = None     # the first event that differs, and how
    divergence_event: int | None = None

    @property
    def identical(self) -> bool:
        return self.divergence is None

    def count(self, kind_name: str, writes: int) -> None:
        self.events += 1
        self.by_kind[kind_name] = self.by_kind.get(kind_name, 0) + 1
        self.writes_compared += writes

    def summary(self) -> str:
        kinds = ", ".join(f"{k} {n}" for k, n in sorted(self.by_kind.items()))
        head = f"{self.events} events ({kinds}), {self.writes_compared} writes compared"
        return f"{head}: identical, bit for bit" if self.identical else f"{head}: {self.divergence}"

    def diverged(self, index: int, kind_name: str, how: str) -> None:
        self.divergence = f"event {index} ({kind_name}): {how}"
        self.divergence_event = index


def replay_events(path: str | Path, events: JournalEvents, clocks: list[ReplayClock], init_kind: int,
                  kind_name: Callable[[int], str], start: Callable[[JournalEvent], None],
                  handle: Callable[[JournalEvent], None], written: Callable[[], list[tuple[int, bytes]]],
                  expected: Callable[[JournalEvent], list[tuple[int, bytes]]],
                  progress: Callable[[int], None] | None = None, progress_every: int = 5000) -> ReplayReport:
    """The replay's loop, whatever the process: for each event, load the clocks with its readings, build the
    daemon (``start``, the ``init_kind`` event) or hand it the event (``handle``), then compare what it
    ``written`` (each write as (kind, bytes), per link in the order written) with what the flight wrote
    (``expected``) and the clock reads with the flight's; stop at the first difference (nothing after it can be
    compared: the state has parted). Closes ``events``. A second INIT, or an event before the INIT, is a
    :class:`ConfigError`."""
    report = ReplayReport()
    started = False
    try:
        for event in events:
            for c in clocks:
                c.load(event)
            if event.kind == init_kind:
                if started:
                    raise ConfigError(f"{path}: a second INIT event (event {event.index})")
                started = True
                start(event)
            elif not started:
                raise ConfigError(f"{path}: event {event.index} ({kind_name(event.kind)}) before the INIT")
            else:
                handle(event)
            got, want = written(), expected(event)
            report.count(kind_name(event.kind), min(len(want), len(got)))
            diff = first_difference(want, got, clocks, kind_name)
            if diff is not None:
                report.diverged(event.index, kind_name(event.kind), diff)
                break
            if progress is not None and report.events % progress_every == 0:
                progress(report.events)
    finally:
        events.close()   # a replay that stopped at a divergence closes the file too
    if not started and report.divergence is None:
        report.divergence = "the journal has no events"
    return report

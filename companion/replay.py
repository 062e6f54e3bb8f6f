"""Re-run a companion open loop from its input journal (:mod:`companion.journal`) and check every byte it writes.

The replay is a third source of events beside the sockets and the lock-step: a companion is built from the
journal's own configuration (the INIT event's clock readings), then each event is handed to the same handler the
flight's loop called (``Companion.handle_autopilot``, ``handle_gcs``, ``handle_gcs_bad_data``, ``handle_frame``,
``handle_periodic``), on clocks that give back the readings recorded during that event. What it writes to the
autopilot and to the ground stations is compared with what the flight wrote, event by event. The first event whose
writes or clock readings differ is the divergence; nothing after it can be compared (the state has parted).
"""

from __future__ import annotations

import dataclasses
import logging
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from companion.config import CompanionConfig
from companion.journal import OUTPUTS, JournalEvent, Kind, decode_frame, read_events
from companion.link_reader import decode_highres_imu_v2
from quadlink.camera import RgbdFrame
from quadlink.config import from_dict
from quadlink.errors import ConfigError
from quadlink.mavlink import mavlink

log = logging.getLogger("companion.replay")


class _Clock:
    """Gives back one event's recorded readings of one clock, in order."""

    def __init__(self, kind: Kind) -> None:
        self.kind = kind
        self.queue: deque[float] = deque()
        self.overread = 0
        self._last = 0.0

    def __call__(self) -> float:
        if self.queue:
            self._last = self.queue.popleft()
        else:
            self.overread += 1
        return self._last


class _Link:
    """A link that receives nothing (events come from the journal) and keeps what is written to it."""

    def __init__(self) -> None:
        self.written: list[bytes] = []

    def write(self, buf: bytes) -> None:
        self.written.append(bytes(buf))

    def recv_msg(self) -> Any:
        return None

    def close(self) -> None:
        pass


class _Camera:
    connected = True

    def read(self, timeout_s: float) -> RgbdFrame | None:
        return None

    def ack(self, seq: int) -> None:
        pass

    def close(self) -> None:
        pass


@dataclass
class ReplayReport:
    events: int = 0
    by_kind: dict[str, int] = dataclasses.field(default_factory=dict)
    writes_compared: int = 0
    divergence: str | None = None     # the first event that differs, and how
    divergence_event: int | None = None

    @property
    def identical(self) -> bool:
        return self.divergence is None

    def summary(self) -> str:
        kinds = ", ".join(f"{k} {n}" for k, n in sorted(self.by_kind.items()))
        head = f"{self.events} events ({kinds}), {self.writes_compared} writes compared"
        return f"{head}: identical, bit for bit" if self.identical else f"{head}: {self.divergence}"


def _decode_message(payload: bytes) -> Any:
    msg = decode_highres_imu_v2(payload)    # what the autopilot link's fast path gives (companion.link_reader)
    if msg is not None:
        return msg
    codec = mavlink.MAVLink(None)
    codec.robust_parsing = True
    msgs = codec.parse_buffer(payload) or []
    if len(msgs) != 1:
        raise ConfigError(f"a journaled message decoded to {len(msgs)} messages")
    return msgs[0]


def _perception_factory(header: dict[str, Any]) -> Callable[[RgbdFrame], Any]:
    from companion.interfaces import pipeline_factory
    from perception.pipeline import PerceptionConfig

    pcfg = from_dict(PerceptionConfig, header["perception"], source="journal header: perception")
    return pipeline_factory(pcfg, int(header["seed"]))


def _differs(event: JournalEvent, written: list[tuple[Kind, bytes]], clocks: list[_Clock]) -> str | None:
    for clock in clocks:
        if clock.overread:
            return f"read the {clock.kind.name} clock {clock.overread} more time(s) than the flight did"
        if clock.queue:
            return f"read the {clock.kind.name} clock {len(clock.queue)} fewer time(s) than the flight did"
    if written == event.outputs:
        return None
    for i, (want, got) in enumerate(zip(event.outputs, written)):
        if want != got:
            return (f"write {i} differs: the flight wrote {want[1][:24].hex()}... to {want[0].name}, the replay "
                    f"{got[1][:24].hex()}... to {got[0].name}")
    return f"the flight wrote {len(event.outputs)} message(s), the replay {len(written)}"


def replay_journal(path: str | Path, progress: Callable[[int], None] | None = None,
                   pipeline_factory: Callable[[RgbdFrame], Any] | None = None) -> ReplayReport:
    """Re-run the companion of the journal at ``path``; see the module doc. ``progress`` sees the event count;
    ``pipeline_factory``: another perception than the journal's own (a test's stand-in)."""
    from companion.daemon import Companion

    header, events = read_events(path)
    try:
        cfg = from_dict(CompanionConfig, header["companion"], source="journal header: companion")
        if cfg.security.require_signing or cfg.security.signing_key_file:
            raise ConfigError(f"{path}: a signed ground link is not replayed (the journal holds no key)")
    except BaseException:
        events.close()
        raise
    clocks = [_Clock(Kind.CLOCK), _Clock(Kind.STOPWATCH)]
    clock, stopwatch = clocks
    autopilot, gcs = _Link(), _Link()
    report = ReplayReport()
    daemon: Any = None
    try:
        for event in events:
            for c in clocks:
                c.queue = deque(event.readings[c.kind])
                c.overread = 0
            autopilot.written.clear()
            gcs.written.clear()
            if event.kind == Kind.INIT:
                if daemon is not None:
                    raise ConfigError(f"{path}: a second INIT event (event {event.index})")
                daemon = Companion(cfg, autopilot, gcs, _Camera(), pipeline_factory or _perception_factory(header),
                                   clock=clock, stopwatch=stopwatch)
            elif daemon is None:
                raise ConfigError(f"{path}: event {event.index} ({event.kind.name}) before the companion's INIT")
            elif event.kind == Kind.AUTOPILOT:
                daemon.handle_autopilot(_decode_message(event.payload))
            elif event.kind == Kind.GCS:
                daemon.handle_gcs(_decode_message(event.payload))
            elif event.kind == Kind.GCS_BAD:
                daemon.handle_gcs_bad_data()
            elif event.kind == Kind.FRAME:
                daemon.handle_frame(decode_frame(event.payload))
            elif event.kind == Kind.PERIODIC:
                daemon.handle_periodic()
            written = [(OUTPUTS[0], b) for b in autopilot.written] + [(OUTPUTS[1], b) for b in gcs.written]
            # the flight's writes are in the order they happened; the replay's are kept per link: compare per link
            want = sorted(event.outputs, key=lambda o: o[0])
            report.events += 1
            report.by_kind[event.kind.name] = report.by_kind.get(event.kind.name, 0) + 1
            report.writes_compared += min(len(want), len(written))
            diff = _differs(dataclasses.replace(event, outputs=want), written, clocks)
            if diff is not None:
                report.divergence = f"event {event.index} ({event.kind.name}): {diff}"
                report.divergence_event = event.index
                break
            if progress is not None and report.events % 5000 == 0:
                progress(report.events)
    finally:
        events.close()   # a replay that stopped at a divergence closes the file too
    if daemon is None and report.divergence is None:
        report.divergence = "the journal has no events"
    return report

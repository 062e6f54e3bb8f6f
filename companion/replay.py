"""Re-run a companion open loop from its input journal (:mod:`companion.journal`) and check every byte it writes.

The replay is a third source of events beside the sockets and the lock-step: a companion is built from the
journal's own configuration (the INIT event's clock readings), then each event is handed to the same handler the
flight's loop called (``Companion.handle_autopilot``, ``handle_gcs``, ``handle_gcs_bad_data``, ``handle_frame``,
``handle_periodic``), on clocks that give back the readings recorded during that event. What it writes to the
autopilot and to the ground stations is compared with what the flight wrote, event by event. The first event whose
writes or clock readings differ is the divergence; nothing after it can be compared (the state has parted).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

from companion.config import CompanionConfig
from companion.journal import OUTPUTS, Kind, decode_frame, read_events
from companion.link_reader import decode_highres_imu_v2
from quadlink.camera import RgbdFrame
from quadlink.config import from_dict
from quadlink.errors import ConfigError
from quadlink.journal import JournalEvent, ReplayClock, ReplayReport, replay_events
from quadlink.mavlink import mavlink

log = logging.getLogger("companion.replay")


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
    clocks = [ReplayClock(Kind.CLOCK, "CLOCK"), ReplayClock(Kind.STOPWATCH, "STOPWATCH")]
    clock, stopwatch = clocks
    autopilot, gcs = _Link(), _Link()
    daemon: Any = None

    def start(event: JournalEvent) -> None:
        nonlocal daemon
        autopilot.written.clear()
        gcs.written.clear()
        daemon = Companion(cfg, autopilot, gcs, _Camera(), pipeline_factory or _perception_factory(header),
                           clock=clock, stopwatch=stopwatch)

    def handle(event: JournalEvent) -> None:
        autopilot.written.clear()
        gcs.written.clear()
        if event.kind == Kind.AUTOPILOT:
            daemon.handle_autopilot(_decode_message(event.payload))
        elif event.kind == Kind.GCS:
            daemon.handle_gcs(_decode_message(event.payload))
        elif event.kind == Kind.GCS_BAD:
            daemon.handle_gcs_bad_data()
        elif event.kind == Kind.FRAME:
            daemon.handle_frame(decode_frame(event.payload))
        elif event.kind == Kind.PERIODIC:
            daemon.handle_periodic()

    def written() -> list[tuple[int, bytes]]:
        return [(int(OUTPUTS[0]), b) for b in autopilot.written] + [(int(OUTPUTS[1]), b) for b in gcs.written]

    def expected(event: JournalEvent) -> list[tuple[int, bytes]]:
        # the flight's writes are in the order they happened; the replay's are kept per link: compare per link
        return sorted(event.outputs, key=lambda o: o[0])

    return replay_events(path, events, clocks, Kind.INIT, lambda k: Kind(k).name, start, handle, written, expected,
                         progress, progress_every=5000)

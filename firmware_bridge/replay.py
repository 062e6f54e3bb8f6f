"""Re-run a bridge open loop from its input journal (:mod:`firmware_bridge.journal`) and check every byte it writes.

A bridge is built from the journal's header (its configuration, vehicle and stored parameters, in a temporary
parameter file: the user's is never written), with links that receive nothing and keep what is written to them
(:meth:`BridgeDaemon.attach_links`); each event is handed to the method the flight's loop called
(``handle_input`` for an input, ``housekeeping_turn`` for a housekeeping turn) on clocks that give back the
readings recorded during that event (:func:`quadlink.journal.replay_events`). What it writes to MK port 1 and to
each MAVLink endpoint is compared with what the flight wrote, event by event; the first event whose writes or clock
readings differ is the divergence (nothing after it can be compared: the state has parted).
"""

from __future__ import annotations

import tempfile
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any

from firmware_bridge.journal import Kind, decode_input, kind_name, read_events
from firmware_bridge.params import save_param_file
from quadlink.config import from_dict
from quadlink.errors import ConfigError
from quadlink.journal import JournalEvent, ReplayClock, ReplayReport, replay_events
from quadlink.mavlink import mavlink
from quadlink.vehicle import VehicleConfig


class _MkPort:
    """MK port 1: keeps the frames written, and answers each write as the flight's was answered."""

    def __init__(self) -> None:
        self.written: list[bytes] = []
        self.results: deque[bool] = deque()
        self.bytes_written = 0

    def write(self, data: bytes) -> bool:
        self.written.append(bytes(data))
        return self.results.popleft() if self.results else True

    def drop(self) -> None:
        pass


class _Endpoint:
    """A MAVLink endpoint that receives nothing and keeps each frame sent (its own codec: the flight's sequence
    numbers and ids)."""

    def __init__(self, sysid: int, compid: int) -> None:
        self.written: list[bytes] = []
        self.mav = mavlink.MAVLink(self, srcSystem=sysid, srcComponent=compid)
        self.mav.robust_parsing = True

    def write(self, buf: bytes) -> None:
        self.written.append(bytes(buf))

    def close(self) -> None:
        pass


def replay_bridge_journal(path: str | Path, progress: Callable[[int], None] | None = None) -> ReplayReport:
    """Re-run the bridge of the journal at ``path``; see the module doc. ``progress`` sees the event count."""
    from firmware_bridge.daemon import BridgeConfig, BridgeDaemon

    header, events = read_events(path)
    try:
        cfg = from_dict(BridgeConfig, header["bridge"], source="journal header: bridge")
        vehicle = from_dict(VehicleConfig, header["vehicle"], source="journal header: vehicle")
        params = header.get("params") or {}
        if cfg.security.key() is not None:
            raise ConfigError(f"{path}: a signed ground link is not replayed (the journal holds no key)")
    except BaseException:
        events.close()
        raise
    clocks = [ReplayClock(Kind.CLOCK, "CLOCK"), ReplayClock(Kind.WALL, "WALL"), ReplayClock(Kind.UNIX, "UNIX")]
    daemon_clock, wall, unix = clocks
    mk_port = _MkPort()
    endpoints = [_Endpoint(cfg.sysid, cfg.compid) for _ in cfg.mavlink_urls]
    daemon: Any = None

    def begin(event: JournalEvent) -> None:
        mk_port.written.clear()
        mk_port.results = deque(bool(p[0]) for k, p in event.outputs if k == Kind.OUT_MK and p)
        for e in endpoints:
            e.written.clear()

    def written() -> list[tuple[int, bytes]]:
        # per link, in the order written
        out = [(int(Kind.OUT_MK), b) for b in mk_port.written]
        for i, e in enumerate(endpoints):
            out += [(Kind.OUT_MAVLINK + i, b) for b in e.written]
        return out

    def expected(event: JournalEvent) -> list[tuple[int, bytes]]:
        # the flight's MK writes without their result flag (handed back to the replay's port)
        return [(k, b[1:] if k == Kind.OUT_MK else b) for k, b in sorted(event.outputs, key=lambda o: o[0])]

    with tempfile.TemporaryDirectory(prefix="quadlink-replay-bridge-") as tmp:
        params_path = Path(tmp) / "params.yaml"
        save_param_file(params_path, {str(k): float(v) for k, v in params.items()})

        def start(event: JournalEvent) -> None:
            nonlocal daemon
            begin(event)
            daemon = BridgeDaemon(cfg, vehicle, params_path, clock=wall, unix_clock=unix, daemon_clock=daemon_clock)
            daemon.attach_links(mk_port, endpoints)

        def handle(event: JournalEvent) -> None:
            begin(event)
            if event.kind == Kind.INPUT:
                daemon.handle_input(decode_input(event.payload))
            elif event.kind == Kind.HOUSEKEEPING:
                daemon.housekeeping_turn()

        return replay_events(path, events, clocks, Kind.INIT, kind_name, start, handle, written, expected,
                             progress, progress_every=50000)

"""Re-run a lock-stepped ground station open loop from its journal (:mod:`teleop.journal`) and check every byte it
sends.

A station is built from the journal's header (its configuration and operator script, the virtual device; the script
in a temporary file) with a vehicle link that has no socket (:func:`quadlink.mavlink.connection.open_replay_mavlink`)
and the journal's clock readings; then :meth:`teleop.station.Station.run_turns` runs the station's one loop over the
journal's turns (:class:`JournalTurns`: each STEP's time and the datagrams handed in it, the device's and the link's
ticks as in the lock-step). What each turn sends to the companion is compared with what the flight's sent; the first
turn whose writes or clock readings differ is the divergence (nothing after it can be compared: the state has parted).
A loop that ends before the journal does (or after) diverges too.
"""

from __future__ import annotations

import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

from quadlink.config import from_dict
from quadlink.errors import ConfigError
from quadlink.journal import JournalEvent, JournalEvents, ReplayClock, ReplayReport, first_difference
from quadlink.mavlink.connection import open_replay_mavlink
from teleop.config import TeleopConfig
from teleop.devices import open_device
from teleop.journal import Kind, decode_step, kind_name, read_events
from teleop.link import VehicleLink
from teleop.station import Station, SteppedTicks
from teleop.telemetry import Telemetry


class JournalTurns:
    """The journal's turns as an event source of the station's loop: each STEP at its recorded time, its datagrams
    handed to the link, the ticks due as in the lock-step; :meth:`done` compares the turn's writes and clock reads."""

    leaving = "the journal's turns replayed"

    def __init__(self, station: Station, events: JournalEvents, conn: Any, clock: ReplayClock, report: ReplayReport,
                 progress: Callable[[int], None] | None, progress_every: int) -> None:
        self.station, self.events, self.conn, self.clock, self.report = station, events, conn, clock, report
        self.ticks = SteppedTicks(station)
        self.event: JournalEvent | None = None
        self.ended = False          # the journal had no more turns
        self.progress, self.progress_every = progress, progress_every

    def next_time(self) -> float | None:
        event = next(self.events, None)
        if event is None:
            self.ended = True
            self.station.stop_event.set()
            return None
        if event.kind != Kind.STEP:
            self._diverged(event, f"a {kind_name(event.kind)} event where a STEP was expected")
            return None
        self.event = event
        self.clock.load(event)
        self.conn.written.clear()
        t = decode_step(event.payload)
        self.ticks.first(t)
        return t

    def run_device(self, t: float) -> None:
        self.ticks.run_device(t)

    def receive(self, link: VehicleLink, tel: Telemetry, t: float) -> Telemetry:
        assert self.event is not None
        datagrams = [payload for kind, payload in self.event.outputs if kind == Kind.IN_VEHICLE]
        self.conn.incoming.extend(datagrams)
        allow = self.station.datagrams_handed + len(datagrams)
        return self.station.receive_step(link, tel, t, allow, f"journal event {self.event.index}", 0.0)

    def link_ticks_due(self, t: float, t_first: float) -> int:
        return self.ticks.link_ticks_due(t, t_first)

    def done(self) -> None:
        assert self.event is not None
        want = [(int(Kind.OUT_VEHICLE), payload) for kind, payload in self.event.outputs if kind == Kind.OUT_VEHICLE]
        got = [(int(Kind.OUT_VEHICLE), payload) for payload in self.conn.written]
        self.report.count(kind_name(self.event.kind), min(len(want), len(got)))
        diff = first_difference(want, got, [self.clock], kind_name)
        if diff is not None:
            self._diverged(self.event, diff)
        elif self.progress is not None and self.report.events % self.progress_every == 0:
            self.progress(self.report.events)

    def _diverged(self, event: JournalEvent, how: str) -> None:
        self.report.diverged(event.index, kind_name(event.kind), how)
        self.station.stop_event.set()


def replay_teleop_journal(path: str | Path, progress: Callable[[int], None] | None = None,
                          progress_every: int = 5000) -> ReplayReport:
    """Re-run the ground station of the journal at ``path``; see the module doc. ``progress`` sees the turn count."""
    header, events = read_events(path)
    report = ReplayReport()
    try:
        cfg = from_dict(TeleopConfig, header["teleop"], source="journal header: teleop")
        if cfg.network.signing_key_file is not None:
            raise ConfigError(f"{path}: a signed vehicle link is not replayed (the journal holds no key)")
        script_text, script_clock = str(header["script"]), str(header["script_clock"])
        exit_at_script_end, duration_s = bool(header["exit_at_script_end"]), header.get("duration_s")
        first = next(events, None)
        if first is None or first.kind != Kind.INIT:
            raise ConfigError(f"{path}: the journal does not begin with the station's INIT")
        report.count(kind_name(first.kind), 0)
        with tempfile.TemporaryDirectory(prefix="quadlink-replay-teleop-") as tmp:
            script = Path(tmp) / "script.yaml"
            script.write_text(script_text)
            stations: list[Station] = []

            def vehicle_clock() -> float | None:
                return stations[0].vehicle_time_s() if stations else None

            device = open_device("virtual", cfg.device, script, vehicle_clock if script_clock == "vehicle" else None)
            station = Station(cfg, device, "replay", None, None, exit_at_script_end=exit_at_script_end)
            stations.append(station)
            conn = open_replay_mavlink(cfg.network.source_system, cfg.network.source_component)
            clock = ReplayClock(Kind.CLOCK, "CLOCK")
            station.start_replay(conn, clock)
            turns = JournalTurns(station, events, conn, clock, report, progress, progress_every)
            try:
                station.run_turns(turns, None if duration_s is None else float(duration_s))
            finally:
                station.close()
            if report.divergence is None and not turns.ended:
                rest = sum(1 for _ in events)
                if rest:
                    last = turns.event.index if turns.event is not None else 0
                    report.diverged(last, "STEP", f"the replay's loop ended here (the script's end or the duration), "
                                                  f"the flight's went on for {rest} more turn(s)")
    except KeyError as exc:
        raise ConfigError(f"{path}: the journal's header has no {exc}") from None
    finally:
        events.close()
    return report

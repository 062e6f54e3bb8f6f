"""quadlink.journal.replay_events, the loop both processes' replays share, on a toy process: a counter that reads
its clock and writes what it counted (its journal written by the real JournalWriter)."""

from __future__ import annotations

import struct
from pathlib import Path

import pytest

from quadlink.errors import ConfigError
from quadlink.journal import JournalEvent, JournalSchema, JournalWriter, ReplayClock, read_events, replay_events

pytestmark = pytest.mark.unit

INIT, TICK, CLOCK, OUT = 1, 2, 3, 4
SCHEMA = JournalSchema("toy journal", b"TOYJ", 1, frozenset({INIT, TICK, CLOCK, OUT}), frozenset({INIT, TICK}),
                       (CLOCK,))
NAMES = {INIT: "INIT", TICK: "TICK", CLOCK: "CLOCK", OUT: "OUT"}


class Counter:
    """The toy daemon: each tick reads the clock and writes the count and the time."""

    def __init__(self, clock, write, step: int = 1) -> None:
        self.clock, self.write, self.step, self.n = clock, write, step, 0

    def tick(self) -> None:
        self.n += self.step
        self.write(struct.pack("<id", self.n, self.clock()))


def record(path: Path, events: list[int], times: list[float]) -> None:
    w = JournalWriter(path, {"toy": True}, SCHEMA)
    it = iter(times)
    clock = w.clock(lambda: next(it), CLOCK)
    daemon = None
    for kind in events:
        with w.event(kind):
            if kind == INIT:
                daemon = Counter(clock, lambda b: w.output(OUT, b))
            else:
                assert daemon is not None
                daemon.tick()
    w.close()


def replay(path: Path, step: int = 1):
    _, events = read_events(path, SCHEMA)
    clock = ReplayClock(CLOCK, "CLOCK")
    out: list[bytes] = []
    holder: dict[str, Counter] = {}

    def start(event: JournalEvent) -> None:
        out.clear()
        holder["d"] = Counter(clock, out.append, step)

    def handle(event: JournalEvent) -> None:
        out.clear()
        holder["d"].tick()

    return replay_events(path, events, [clock], INIT, NAMES.__getitem__, start, handle,
                         lambda: [(OUT, b) for b in out], lambda e: list(e.outputs))


def test_the_same_daemon_replays_identical(tmp_path: Path) -> None:
    record(tmp_path / "j", [INIT, TICK, TICK, TICK], [0.1, 0.2, 0.3])
    report = replay(tmp_path / "j")
    assert report.identical, report.summary()
    assert report.events == 4 and report.by_kind == {"INIT": 1, "TICK": 3} and report.writes_compared == 3


def test_a_changed_daemon_diverges_at_its_first_different_write(tmp_path: Path) -> None:
    record(tmp_path / "j", [INIT, TICK, TICK], [0.1, 0.2])
    report = replay(tmp_path / "j", step=2)
    assert not report.identical and report.divergence_event == 1 and "write 0 differs" in (report.divergence or "")


def test_an_event_before_the_init_or_a_second_init_is_a_clear_error(tmp_path: Path) -> None:
    w = JournalWriter(tmp_path / "early", {}, SCHEMA)
    with w.event(TICK):
        pass
    w.close()
    with pytest.raises(ConfigError, match="before the INIT"):
        replay(tmp_path / "early")
    record(tmp_path / "twice", [INIT, TICK, INIT], [0.1])
    with pytest.raises(ConfigError, match="second INIT"):
        replay(tmp_path / "twice")


def test_no_events_is_not_identical(tmp_path: Path) -> None:
    JournalWriter(tmp_path / "j", {}, SCHEMA).close()
    assert replay(tmp_path / "j").divergence == "the journal has no events"

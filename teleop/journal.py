"""The ground station's input journal: every turn of its lock-stepped loop, so that a flight's station can be re-run
open loop from it, bit for bit (issue 28), as the companion's and the bridge's are (:mod:`companion.journal`,
:mod:`firmware_bridge.journal`).

A lock-stepped station (``quadlink teleop --lockstep``) is a function of its configuration, its operator script, the
steps' simulated times and the companion's datagrams each step hands it: the device, eq. (15), the link's ticks and
every clock it reads run on the step's time. Each turn of :meth:`teleop.station.Station._loop` is one *event*:
its time, the datagrams pymavlink was handed during it, the clock readings and the datagrams the station sent.
:func:`teleop.replay.replay_teleop_journal` builds a station from the header and runs the same loop over the
journal's turns (the loop's third event source, beside the wall clock's turns and the lock-step's STEPs).

File format: :mod:`quadlink.journal`'s container, magic ``b"QLTJ"``, with the header::

    {"version": 1, "teleop": <TeleopConfig as data>, "script": <the operator script's YAML text>,
     "script_clock": "wall" | "vehicle", "exit_at_script_end": bool, "duration_s": float | null,
     "started_unix_s": float}

Kinds: events (``INIT``: the station joined the lock-step; ``STEP``: one turn, its payload the step's simulated time
as float64); clock readings (``CLOCK``: the station's clock, the step's time); ``IN_VEHICLE``: a companion datagram
handed to pymavlink during the turn (the inputs, recorded where they are read); ``OUT_VEHICLE``: a datagram sent to
the companion (the writes compared). About 25 kB per second of flight.

Limits: the lock-stepped station only (free-running, the force loop runs in its own thread or process and the view
reads a camera stream: their interleaving is not journaled); a signed vehicle link is not replayed (its key is not
journaled).
"""

from __future__ import annotations

from enum import IntEnum
from pathlib import Path
from typing import Any

from quadlink import journal as core
from quadlink.errors import ProtocolError
from quadlink.journal import F64, JournalEvents, JournalWriter

MAGIC = b"QLTJ"
VERSION = 1


class Kind(IntEnum):
    INIT = 1
    STEP = 2
    CLOCK = 16
    IN_VEHICLE = 32
    OUT_VEHICLE = 48


SCHEMA = core.JournalSchema("ground-station journal", MAGIC, VERSION, frozenset(int(k) for k in Kind),
                            frozenset({int(Kind.INIT), int(Kind.STEP)}), (int(Kind.CLOCK),))


def kind_name(kind: int) -> str:
    return Kind(kind).name


def open_journal(path: str | Path, header: dict[str, Any]) -> JournalWriter:
    return JournalWriter(path, header, SCHEMA)


def read_events(path: str | Path) -> tuple[dict[str, Any], JournalEvents]:
    return core.read_events(path, SCHEMA)


def encode_step(t_s: float) -> bytes:
    return F64.pack(t_s)


def decode_step(payload: bytes) -> float:
    if len(payload) != F64.size:
        raise ProtocolError(f"a STEP event of {len(payload)} bytes (expected {F64.size})")
    return float(F64.unpack(payload)[0])


def journal_link(journal: JournalWriter, conn: Any) -> None:
    """Journal what pymavlink is handed from ``conn`` (IN_VEHICLE) and what is written to it (OUT_VEHICLE), inside
    the journal's events. ``conn``'s ``recv`` and ``write`` are wrapped where they are (after
    :class:`quadlink.lockstep.CountedMavlink`'s: the datagrams handed in the step, not those read early)."""
    recv, write = conn.recv, conn.write

    def journaled_recv(n: int | None = None) -> Any:
        data = recv(n)
        if data:
            journal.output(Kind.IN_VEHICLE, bytes(data))
        return data

    def journaled_write(buf: bytes) -> Any:
        journal.output(Kind.OUT_VEHICLE, bytes(buf))
        return write(buf)

    conn.recv, conn.write = journaled_recv, journaled_write

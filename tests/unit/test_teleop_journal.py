"""The ground station's journal (teleop.journal, teleop.replay): what it refuses and how a bad journal is told
apart. The replay of a real flight's station, bit for bit, is in tests/sitl/test_companion_journal_sitl.py."""

from __future__ import annotations

from pathlib import Path

import pytest
from click.testing import CliRunner

from quadlink.cli import main
from quadlink.config import to_dict
from quadlink.errors import ConfigError, ProtocolError
from quadlink.journal import JournalWriter
from teleop.config import load_teleop_config
from teleop.journal import SCHEMA, Kind, decode_step, encode_step, open_journal
from teleop.replay import replay_teleop_journal

SCRIPT = "name: hover\nsteps:\n  - wait_s: 1.0\n"


def _header(**extra: object) -> dict[str, object]:
    return {"teleop": to_dict(load_teleop_config()), "script": SCRIPT, "script_clock": "wall",
            "exit_at_script_end": True, "duration_s": None, **extra}


def test_a_free_running_station_is_not_journaled(tmp_path: Path) -> None:
    result = CliRunner().invoke(main, ["teleop", "--journal", str(tmp_path / "t.qltj"), "--duration", "0.1"])
    assert result.exit_code != 0
    assert "--journal journals a lock-stepped station only" in (result.output + str(result.exception))
    assert not (tmp_path / "t.qltj").exists()


def test_a_step_time_round_trips_and_a_bad_one_is_refused() -> None:
    assert decode_step(encode_step(12.345)) == 12.345
    with pytest.raises(ProtocolError):
        decode_step(b"\x00" * 4)


def test_events_do_not_nest(tmp_path: Path) -> None:
    journal = JournalWriter(tmp_path / "j.qltj", {}, SCHEMA)
    journal.begin(Kind.STEP, encode_step(0.0))
    with pytest.raises(RuntimeError):
        journal.begin(Kind.STEP, encode_step(0.01))
    journal.end()
    journal.close()


def test_a_journal_without_its_init_or_header_keys_is_a_clear_error(tmp_path: Path) -> None:
    no_init = open_journal(tmp_path / "a.qltj", _header())
    with no_init.event(Kind.STEP, encode_step(0.0)):
        pass
    no_init.close()
    with pytest.raises(ConfigError, match="INIT"):
        replay_teleop_journal(tmp_path / "a.qltj")
    header = _header()
    del header["script_clock"]
    no_key = open_journal(tmp_path / "b.qltj", header)
    no_key.close()
    with pytest.raises(ConfigError, match="script_clock"):
        replay_teleop_journal(tmp_path / "b.qltj")
    with pytest.raises(ProtocolError, match="not a ground-station journal"):
        (tmp_path / "c.qltj").write_bytes(b"QLBJ" + b"\x00" * 12)
        replay_teleop_journal(tmp_path / "c.qltj")


def test_a_turn_that_sends_what_the_flight_did_not_diverges_there(tmp_path: Path) -> None:
    """Turns recorded with nothing sent: the replayed station's first turn sends its MANUAL_CONTROL (and its
    COMMAND_STAMP, HEARTBEAT, TIMESYNC, reading its clock for them), so the replay parts from the flight at that
    turn and stops."""
    journal = open_journal(tmp_path / "long.qltj", _header(script="name: short\nsteps:\n  - wait_s: 0.05\n"))
    with journal.event(Kind.INIT):
        pass
    for k in range(200):   # 4 s of turns, no datagrams, nothing sent
        with journal.event(Kind.STEP, encode_step(0.02 * k)):
            pass
    journal.close()
    report = replay_teleop_journal(tmp_path / "long.qltj")
    assert not report.identical
    assert report.divergence_event == 1 and report.events == 2, report.summary()
    assert "more time(s) than the flight did" in (report.divergence or "")   # its clock: read for what it sends

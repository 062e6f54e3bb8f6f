"""Issue 28: a flight's companion and bridge re-run from their input journals. A deterministic lock-step demo flight
with both journaling (``quadlink demo --journal``): the real perception on the SITL's frames, the bridge's IMU and
the operator's MANUAL_CONTROL. ``quadlink replay-companion`` re-runs that companion open loop, alone, from its
journal, and must write every byte the flight's companion wrote, to the autopilot and to the ground station;
``quadlink replay-bridge`` re-runs the bridge, and must write every byte it wrote to the board and to each
MAVLink endpoint; ``quadlink replay-teleop`` re-runs the lock-stepped ground station, and must send every byte it
sent to the companion."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from companion.replay import replay_journal
from firmware_bridge.replay import replay_bridge_journal
from harness.demo.cli import BRIDGE_JOURNAL_NAME, JOURNAL_NAME, TELEOP_JOURNAL_NAME, run_demo
from harness.ports import free_port_offset
from teleop.replay import replay_teleop_journal

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(600)]

OFFSET = free_port_offset()   # harness.ports: free now, reserved for this session
SCRIPT = """name: take off, push forward, land (a short journaled flight)
steps:
  - wait_s: 1.0
  - button: arm
  - wait_s: 0.5
  - button: takeoff
  - wait_s: 5.0
  - push: forward
    force_n: 1.0
    duration_s: 2.5
  - release: true
    duration_s: 1.0
  - button: land
  - wait_s: 2.0
"""


@pytest.mark.slow   # CI: the same-seed campaign test re-runs the three journals of its flight (the CI suite's time)
def test_a_flights_companion_re_runs_from_its_journal_bit_for_bit(tmp_path: Path) -> None:
    script = tmp_path / "operator.yaml"
    script.write_text(SCRIPT)
    report = run_demo("paper-arena", 40.0, tmp_path, script, lockstep=True, port_offset=OFFSET, view=False,
                      plots=False, deterministic=True, settle_s=15.0, journal=True)
    assert report.get("flying_time_s", 0.0) > 5.0, report   # it flew: take-off and the operator's drive
    journal = tmp_path / JOURNAL_NAME
    replay = replay_journal(journal)
    print(replay.summary())
    assert replay.identical, replay.summary()
    assert replay.by_kind["FRAME"] >= 300 and replay.by_kind["AUTOPILOT"] > 5000 and replay.by_kind["GCS"] > 300
    # the command a user runs: exit status 0 and the same verdict
    done = subprocess.run([sys.executable, "-m", "quadlink.cli", "replay-companion", str(journal)],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "identical, bit for bit" in done.stdout
    # the bridge: every MK setpoint and every MAVLink frame, from the board's IMU bytes and the companion's datagrams
    bridge = replay_bridge_journal(tmp_path / BRIDGE_JOURNAL_NAME)
    print(bridge.summary())
    assert bridge.identical, bridge.summary()
    assert bridge.by_kind["INPUT"] > 1000 and bridge.by_kind["HOUSEKEEPING"] > 1000 and bridge.writes_compared > 5000
    done = subprocess.run([sys.executable, "-m", "quadlink.cli", "replay-bridge", str(tmp_path / BRIDGE_JOURNAL_NAME)],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0 and "identical, bit for bit" in done.stdout, done.stdout[-500:] + done.stderr[-2000:]
    # the ground station: every MANUAL_CONTROL, COMMAND_STAMP, command and TIMESYNC, from the steps' times and the
    # companion's datagrams (the operator script and the virtual device re-run with it)
    teleop = replay_teleop_journal(tmp_path / TELEOP_JOURNAL_NAME)
    print(teleop.summary())
    assert teleop.identical, teleop.summary()
    assert teleop.by_kind["STEP"] > 1000 and teleop.writes_compared > 1000
    done = subprocess.run([sys.executable, "-m", "quadlink.cli", "replay-teleop", str(tmp_path / TELEOP_JOURNAL_NAME)],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0 and "identical, bit for bit" in done.stdout, done.stdout[-500:] + done.stderr[-2000:]
    # a turn the flight did not take is found: the 500th STEP 0.1 s later (five link ticks fall due in it), and
    # the station parts from the flight at that turn, not before
    shifted = tmp_path / "shifted.qltj"
    shift_step(tmp_path / TELEOP_JOURNAL_NAME, shifted, 500, 0.1)
    moved = replay_teleop_journal(shifted)
    assert not moved.identical and moved.divergence_event == 500, moved.summary()   # event 0 is the INIT


def shift_step(src: Path, dst: Path, n: int, dt_s: float) -> None:
    """Copy the ground-station journal ``src`` to ``dst`` with its ``n``-th STEP (from 1) ``dt_s`` later."""
    import struct

    from teleop.journal import Kind

    data = bytearray(src.read_bytes())
    _, header_len = struct.unpack_from("<4sI", data, 0)
    at, steps = 8 + header_len, 0
    while at < len(data):
        kind, length = struct.unpack_from("<BI", data, at)
        if kind == Kind.STEP:
            steps += 1
            if steps == n:
                (t,) = struct.unpack_from("<d", data, at + 5)
                struct.pack_into("<d", data, at + 5, t + dt_s)
                break
        at += 5 + length
    assert steps == n, f"the journal has {steps} STEPs"
    dst.write_bytes(bytes(data))

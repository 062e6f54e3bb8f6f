"""``quadlink trajectory``: the YAML, the setpoint stream over real MAVLink (loopback UDP), the command line."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from firmware_bridge.geometric_tracker import decode_trajectory_setpoint
from harness.trajectory_cli import load_trajectory_file, schedule, stream
from quadlink import CONFIG_DIR
from quadlink.client import GroundClient
from quadlink.errors import ConfigError
from quadlink.mavlink.connection import open_mavlink
from quadlink.trajectory import minimum_snap

OVAL_YAML = Path(CONFIG_DIR) / "trajectories" / "oval.yaml"


def test_the_shipped_oval_is_the_papers() -> None:
    cfg, traj = load_trajectory_file(OVAL_YAML)
    assert traj.duration_s == pytest.approx(9.0)
    assert traj.peak_speed_m_s() <= 1.0
    np.testing.assert_allclose(traj.sample(0.0).p_m, [-1.0, -1.5, -1.2])
    np.testing.assert_allclose(traj.sample(traj.knots_s[1]).p_m, [0.0, -0.5, -1.2], atol=1e-9)
    assert cfg.rate_hz == 50.0


@pytest.mark.parametrize("body, match", [
    ("waypoints_ned_m: [[0, 0, 0], [1, 0, 0]]\ndurations_s: [1.0]\ntotal_duration_s: 2.0\n", "exactly one"),
    ("waypoints_ned_m: [[0, 0, 0], [3, 0, 0]]\ndurations_s: [1.0]\nmax_speed_m_s: 1.0\n", "peak speed"),
    ("waypoints_ned_m: [[0, 0, 0]]\ndurations_s: []\n", "at least two"),
    ("waypoints_ned_m: [[0, 0, 0], [1, 0, 0]]\ndurations_s: [1.0, 2.0]\n", "durations"),
    ("waypoints_ned_m: [[0, 0, 0], [1, 0, 0]]\ndurations_s: [2.0]\nspeed: 3\n", "speed"),
])
def test_bad_files_are_one_clear_error(tmp_path: Path, body: str, match: str) -> None:
    f = tmp_path / "t.yaml"
    f.write_text(body)
    with pytest.raises(ConfigError, match=match):
        load_trajectory_file(f)


def test_waypoint_velocities_from_the_file(tmp_path: Path) -> None:
    f = tmp_path / "t.yaml"
    f.write_text("waypoints_ned_m: [[0, 0, -1], [1, 0, -1], [2, 1, -1]]\ntotal_duration_s: 4.0\n"
                 "velocities_ned_m_s: [null, [0.8, 0.2, 0.0], null]\n")
    _, traj = load_trajectory_file(f)
    np.testing.assert_allclose(traj.derivative(traj.knots_s[1], 1), [0.8, 0.2, 0.0], atol=1e-9)


@pytest.mark.integration
def test_stream_sends_px4_style_setpoints_the_tracker_decodes() -> None:
    """Over loopback UDP with pymavlink on both ends; the clock is injected (no waiting)."""
    traj = minimum_snap([[0.0, 0.0, -1.0], [1.0, 0.5, -1.5]], [1.0])
    rx = open_mavlink("udpin:127.0.0.1:0", source_system=1, source_component=1)
    try:
        port = rx.port.getsockname()[1]
        tx = open_mavlink(f"udpout:127.0.0.1:{port}", source_system=255, source_component=190)
        now = [100.0]
        try:
            sent = stream(GroundClient(tx, target_system=1, target_component=1), traj, 50.0, 0.2,
                          np.array([0.5, 0.0, 0.0]), 0.3, offboard=True, clock=lambda: now[0],
                          sleep=lambda s: now.__setitem__(0, now[0] + s))
        finally:
            tx.close()
        assert sent == len(list(schedule(traj, 50.0, 0.2))) == 61
        got, commands = [], []
        while True:
            m = rx.recv_match(blocking=True, timeout=0.5)
            if m is None:
                break
            if m.get_type() == "SET_POSITION_TARGET_LOCAL_NED":
                got.append(m)
            elif m.get_type() == "COMMAND_LONG":
                commands.append(m)
        assert len(got) >= 0.9 * sent  # UDP on loopback: essentially all
        for m in got:
            tgt = decode_trajectory_setpoint(m, yaw_rad=0.0)
            s = traj.sample(m.time_boot_ms / 1000.0)
            np.testing.assert_allclose(tgt.p_ned_m, s.p_m + [0.5, 0.0, 0.0], atol=1e-5)
            np.testing.assert_allclose(tgt.v_ned_m_s, s.v_m_s, atol=1e-5)
            np.testing.assert_allclose(tgt.a_ned_m_s2, s.a_m_s2, atol=1e-4)
            assert tgt.yaw_rad == pytest.approx(0.3)
        assert len(commands) == 1 and commands[0].param2 == 6  # DO_SET_MODE, PX4 main mode OFFBOARD
    finally:
        rx.close()


@pytest.mark.integration
def test_command_line_dry_run_and_bad_input(tmp_path: Path) -> None:
    csv = tmp_path / "oval.csv"
    r = subprocess.run([sys.executable, "-m", "quadlink.cli", "trajectory", str(OVAL_YAML), "--dry-run",
                        "--csv", str(csv)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert "peak speed 0.97" in r.stdout
    rows = np.loadtxt(csv, delimiter=",", skiprows=1)
    assert rows.shape == (451, 10)
    assert np.linalg.norm(rows[:, 4:7], axis=1).max() <= 1.0
    r = subprocess.run([sys.executable, "-m", "quadlink.cli", "trajectory", str(tmp_path / "missing.yaml")],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "not found" in r.stderr

"""``quadlink teleop`` as a user runs it: bad input is one line and exit 2; a short headless run exits cleanly."""

from __future__ import annotations

import csv

from click.testing import CliRunner

from quadlink.cli import main


def test_unavailable_device_is_one_line_error():
    result = CliRunner().invoke(main, ["teleop", "--device", "omega"])
    assert result.exit_code == 2
    lines = [line for line in result.output.splitlines() if line.startswith("quadlink: error:")]
    assert len(lines) == 1 and "forcedimension-core" in lines[0]


def test_bad_script_and_bad_config_are_one_line_errors(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("steps:\n  - push: north\n    force_n: 1\n    duration_s: 1\n")
    result = CliRunner().invoke(main, ["teleop", "--script", str(bad)])
    assert result.exit_code == 2 and "steps[0].push" in result.output
    result = CliRunner().invoke(main, ["teleop", "--config", str(tmp_path / "missing.yaml")])
    assert result.exit_code == 2 and ("not found" in result.output or "no such config" in result.output)
    result = CliRunner().invoke(main, ["teleop", "--device", "gamepad", "--script", str(bad)])
    assert result.exit_code == 2 and "virtual device only" in result.output


def test_short_run_without_vehicle_logs_and_exits(tmp_path):
    script = tmp_path / "s.yaml"
    script.write_text("steps:\n  - push: forward\n    force_n: 2.0\n    duration_s: 1.0\n")
    log_csv = tmp_path / "log.csv"
    result = CliRunner().invoke(main, ["teleop", "--script", str(script), "--vehicle", "udpout:127.0.0.1:9",
                                       "--image-stream", "none", "--http-port", "-1", "--log-csv", str(log_csv),
                                       "--keep-running", "--duration", "3"])
    assert result.exit_code == 0, result.output
    with log_csv.open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) >= 5
    assert max(float(r["qx_m"]) for r in rows) > 0.01            # the script pushed the handle forward
    assert max(int(r["cmd_x"]) for r in rows) > 0                 # and that was commanded
    assert all(float(r["link_gain"]) == 0.0 for r in rows)        # no vehicle: no force feedback
    assert all(r["vx_h"] == "" for r in rows)

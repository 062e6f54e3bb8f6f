"""``quadlink bridge`` command line: help, a missing port as a one-line error, a bad config key."""

from __future__ import annotations

import socket

from click.testing import CliRunner

from quadlink.cli import main


def closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_help_lists_the_flags():
    result = CliRunner().invoke(main, ["bridge", "--help"])
    assert result.exit_code == 0
    for flag in ("--mk-cmd", "--mk-imu", "--mavlink", "--sysid", "--config", "--params"):
        assert flag in result.output


def test_missing_port_is_a_one_line_error(tmp_path):
    result = CliRunner().invoke(main, ["bridge", "--mk-cmd", f"socket://127.0.0.1:{closed_port()}",
                                       "--params", str(tmp_path / "p.yaml")])
    assert result.exit_code == 2
    lines = [line for line in result.output.splitlines() if line.startswith("quadlink: error:")]
    assert len(lines) == 1 and "cannot open" in lines[0]


def test_bad_config_key_names_the_key(tmp_path):
    config = tmp_path / "b.yaml"
    config.write_text("mk_cmd_url: socket://127.0.0.1:1\nsysidd: 3\n")
    result = CliRunner().invoke(main, ["bridge", "--config", str(config)])
    assert result.exit_code == 2 and "sysidd" in result.output

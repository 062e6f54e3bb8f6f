"""``quadlink sitl`` on the command line, scenarios, and the pty ports."""

from __future__ import annotations

import os
import time

import pytest
from click.testing import CliRunner

from quadlink.cli import main
from quadlink.errors import ConfigError
from quadlink.mk.messages import ImuSample, Version, VersionRequest, decode_message, encode_message
from quadlink.mk.protocol import FrameDecoder
from sim_sitl.config import SitlConfig, known_scenarios, load_scenario
from sim_sitl.runner import Sitl, SitlOptions


def test_scenarios_load_and_unknown_name_lists_the_known_ones():
    assert {"paper-arena", "office", "empty"} <= set(known_scenarios())
    arena = load_scenario("paper-arena")
    assert arena.room.size_m == (10.0, 10.0)
    column = next(o for o in arena.objects if o.name == "column")
    assert column.kind == "cylinder" and column.radius_m * 2 == pytest.approx(0.5) and column.height_m >= 2.5
    start = arena.start.position_m
    assert 2.0 < ((start[0] - column.position_m[0]) ** 2 + (start[1] - column.position_m[1]) ** 2) ** 0.5 < 5.0
    with pytest.raises(ConfigError, match="known: .*empty.*office.*paper-arena"):
        load_scenario("moon-base")


def test_cli_unknown_scenario_is_a_one_line_error():
    result = CliRunner().invoke(main, ["sitl", "--scenario", "moon-base", "--no-camera"])
    assert result.exit_code == 2
    assert "unknown scenario 'moon-base'" in result.output


def test_cli_bad_camera_resolution():
    result = CliRunner().invoke(main, ["sitl", "--camera-res", "100x100"])
    assert result.exit_code == 2 and "camera-res" in result.output


def test_cli_unknown_renderer():
    result = CliRunner().invoke(main, ["sitl", "--renderer", "opengl"])
    assert result.exit_code == 2 and "renderer" in result.output


@pytest.mark.sitl
def test_cli_runs_for_a_duration_and_logs_endpoints(caplog):
    with caplog.at_level("INFO"):
        result = CliRunner().invoke(main, ["sitl", "--scenario", "empty", "--no-camera", "--port1", "0", "--port2", "0",
                                           "--truth", "none", "--duration", "0.5", "--speed", "5"])
    assert result.exit_code == 0, result.output
    text = caplog.text
    assert "port1" in text and "socket://127.0.0.1:" in text and "SITL stopped at sim time 0.50" in text


@pytest.mark.sitl
def test_pty_ports_speak_the_protocol():
    sitl = Sitl(SitlOptions(config=SitlConfig(scenario="empty"), port1=0, port2=0, camera=False, truth_url=None,
                            pty=True, progress_every_s=60.0))
    assert sitl.endpoints["port1_pty"].startswith("/dev/pts/")
    sitl.start()
    try:
        fd1 = os.open(sitl.endpoints["port1_pty"], os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        fd2 = os.open(sitl.endpoints["port2_pty"], os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        try:
            os.write(fd1, encode_message(VersionRequest()))
            dec1, dec2 = FrameDecoder(), FrameDecoder()
            got_version, imu = False, 0
            deadline = time.monotonic() + 10
            while (not got_version or imu < 50) and time.monotonic() < deadline:
                time.sleep(0.02)
                for fd, dec in ((fd1, dec1), (fd2, dec2)):
                    try:
                        data = os.read(fd, 4096)
                    except BlockingIOError:
                        continue
                    for f in dec.feed(data):
                        msg = decode_message(f)
                        got_version |= isinstance(msg, Version)
                        imu += isinstance(msg, ImuSample)
            assert got_version and imu >= 50
        finally:
            os.close(fd1)
            os.close(fd2)
    finally:
        sitl.stop()

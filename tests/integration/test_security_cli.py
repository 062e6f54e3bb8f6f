"""Signing and listening addresses as the user sets them up (issue 16): the companion and teleop command
lines, the real ``quadlink companion`` process on loopback, and the local-only default of the operator image
stream and the web view."""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from click.testing import CliRunner

from companion.config import LinksConfig, load_companion_config
from companion.image_publisher import OperatorImagePublisher
from quadlink.cli import main
from quadlink.mavlink.connection import open_mavlink
from quadlink.mavlink.security import enable_signing, write_key
from teleop.config import TeleopConfig
from teleop.view.server import ViewHub, ViewServer

PORT_BASE = 31400   # this helper's block (31000-31999)


def test_require_signing_without_a_key_is_one_clear_error() -> None:
    result = CliRunner().invoke(main, ["companion", "--require-signing", "--duration", "0.1"])
    assert result.exit_code == 2 and "signing key" in result.output


def test_a_bad_key_file_is_one_clear_error(tmp_path: Path) -> None:
    (tmp_path / "bad.key").write_text("not hex\n")
    result = CliRunner().invoke(main, ["companion", "--signing-key", str(tmp_path / "bad.key"), "--duration", "0.1"])
    assert result.exit_code == 2 and "bad.key" in result.output
    result = CliRunner().invoke(main, ["teleop", "--signing-key", str(tmp_path / "bad.key"), "--duration", "0.1"])
    assert result.exit_code == 2 and "bad.key" in result.output


def test_operator_image_stream_and_web_view_listen_on_localhost_by_default() -> None:
    assert load_companion_config().links.image_host == LinksConfig().image_host == "127.0.0.1"
    publisher = OperatorImagePublisher(LinksConfig().image_host, 0)
    try:
        assert publisher.host == "127.0.0.1"
    finally:
        publisher.close()
    server = ViewServer(ViewHub(), TeleopConfig().network.http_host, 0)
    try:
        assert server.host == "127.0.0.1"
    finally:
        server.close()


def _param_values(link: object, deadline_s: float) -> list[str]:
    got: list[str] = []
    end = time.monotonic() + deadline_s
    while time.monotonic() < end:
        m = link.recv_match(type="PARAM_VALUE", blocking=True, timeout=0.2)  # type: ignore[attr-defined]
        if m is not None:
            got.append(m.param_id)
    return got


@pytest.mark.integration
def test_companion_process_answers_only_signed_ground_stations(tmp_path: Path) -> None:
    key_path = tmp_path / "vehicle.key"
    key = write_key(key_path)
    gcs_port, ap_port, cam_port = PORT_BASE, PORT_BASE + 1, PORT_BASE + 2
    proc = subprocess.Popen(
        [sys.executable, "-m", "quadlink.cli", "companion", "--gcs", f"udpin:127.0.0.1:{gcs_port}",
         "--autopilot", f"udpin:127.0.0.1:{ap_port}", "--camera", f"tcp://127.0.0.1:{cam_port}", "--image-port", "0",
         "--signing-key", str(key_path), "--require-signing", "--duration", "150"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(iter(proc.stdout.readline, "")),  # type: ignore[union-attr]
                              daemon=True)
    reader.start()
    signed = open_mavlink(f"udpout:127.0.0.1:{gcs_port}", 255, 190)
    enable_signing(signed.mav, key, require=True)
    unsigned = open_mavlink(f"udpout:127.0.0.1:{gcs_port}", 255, 191)
    try:
        end = time.monotonic() + 120.0   # its imports take half a minute on a loaded 2-core machine
        while not any("MAVLink 2 signing required" in line for line in lines):
            assert time.monotonic() < end and proc.poll() is None, "".join(lines)
            time.sleep(0.2)
        for _ in range(3):
            unsigned.mav.param_request_list_send(1, 191)
            time.sleep(0.3)
        assert _param_values(unsigned, 2.0) == [], "an unsigned request was answered"
        got: list[str] = []
        for _ in range(10):
            signed.mav.param_request_list_send(1, 191)
            got += _param_values(signed, 1.0)
            if got:
                break
        assert "PANSCAN_AMP" in got, "the signed request was not answered (or not signed back)"
        assert signed.mav.signing.goodsig_count > 0 and signed.mav.signing.badsig_count == 0
    finally:
        signed.close()
        unsigned.close()
        proc.terminate()
        proc.wait(timeout=30)
        reader.join(5.0)
        proc.stdout.close()  # type: ignore[union-attr]
    assert proc.returncode == 0, "".join(lines)

"""Ctrl-C stops a long-running command even when it was started with SIGINT ignored (a background start by a
non-interactive shell or a supervisor: Python then raises no KeyboardInterrupt). Found when a companion started
by a test from such a shell ran on for minutes after the test's SIGINT."""

from __future__ import annotations

import signal
import socket
import subprocess
import sys
import time

import pytest

from harness.ports import free_port


def _ignore_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)


@pytest.mark.parametrize("args", [
    ["companion", "--autopilot", "udpin:127.0.0.1:{u1}", "--gcs", "udpin:127.0.0.1:{u2}",
     "--camera", "tcp://127.0.0.1:{t1}", "--image-port", "0"],
    ["netem", "--listen", "udp:127.0.0.1:{u1}", "--to", "udp:127.0.0.1:{u2}"],
], ids=["companion", "netem"])
def test_sigint_stops_a_command_started_with_sigint_ignored(args: list[str]) -> None:
    ports = {"u1": free_port(socket.SOCK_DGRAM), "u2": free_port(socket.SOCK_DGRAM), "t1": free_port()}
    cmd = [sys.executable, "-m", "quadlink.cli", *(a.format(**ports) for a in args)]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            preexec_fn=_ignore_sigint)
    try:
        time.sleep(3.0)   # started and running (an early SIGINT would only test the interpreter's start-up)
        assert proc.poll() is None, "the command ended by itself"
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=30)
        assert proc.returncode == 0, err
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()

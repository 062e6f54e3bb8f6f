"""Real MAVProxy (the venv's ``python -m MAVProxy.mavproxy``), driven line by line over its stdin, against
SITL + bridge and through the companion: it downloads the parameters (FTP NAKed at once: no timeout), sets
one, arms, takes off, changes mode and lands; each step is asserted on the SITL truth (or the bridge's
persisted parameter file). The odometry comes from the truth (as in test_bridge_sitl.py: no camera here).
"""

from __future__ import annotations

import os
import queue
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from test_bridge_sitl import Gcs, Odometry, Stack

from harness.demo.parts import CompanionPart

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(420),
              pytest.mark.skipif(subprocess.run([sys.executable, "-c", "import MAVProxy"]).returncode != 0,
                                 reason="needs MAVProxy")]


class MavProxy:
    """MAVProxy with its console on pipes: ``cmd`` writes a command line, ``expect`` waits for an output line."""

    def __init__(self, master: str, cwd: Path) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "MAVProxy.mavproxy", f"--master={master}", "--source-system=255",
             "--source-component=190", "--nodtr", "--state-basedir", str(cwd), "--logfile", str(cwd / "mav.tlog")],
            cwd=cwd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1,
            start_new_session=True)
        self.lines: queue.Queue = queue.Queue()
        self.log: list[str] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.log.append(line.rstrip())
            self.lines.put(line.rstrip())

    def cmd(self, line: str) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write(line + "\n")
        self.proc.stdin.flush()

    def expect(self, text: str, timeout_s: float) -> str:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            try:
                line = self.lines.get(timeout=0.2)
            except queue.Empty:
                continue
            if text in line:
                return line
        raise AssertionError(f"MAVProxy never printed {text!r}; last lines: {self.log[-25:]}")

    def close(self) -> None:
        if self.proc.poll() is None:
            try:
                self.cmd("exit")
                self.proc.wait(timeout=5.0)
            except (OSError, subprocess.TimeoutExpired):
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(timeout=5.0)
        self._reader.join(timeout=5.0)   # stdout at EOF once the process is gone
        for pipe in (self.proc.stdin, self.proc.stdout):
            if pipe is not None:
                try:
                    pipe.close()
                except OSError:
                    pass


def height_m(stack: Stack) -> float:
    return -float(stack.state()[0][2])


def wait_until(pred, timeout_s: float, what: str, mp: MavProxy) -> None:  # type: ignore[no-untyped-def]
    deadline = time.monotonic() + timeout_s
    while not pred():
        assert time.monotonic() < deadline, f"timed out waiting for {what}; MAVProxy: {mp.log[-20:]}"
        time.sleep(0.1)


def session(stack: Stack, master: str, tmp: Path, hold: bool = True) -> list[str]:
    """The scripted session; returns MAVProxy's output. ``hold`` False: no POSCTL hold after the take-off (the
    companion without a camera lands the vehicle itself once the take-off ends: odometry failed too long)."""
    mp = MavProxy(master, tmp)
    try:
        t0 = time.monotonic()
        from firmware_bridge.params import ParamTable

        line = mp.expect("Received ", 120.0)   # after FTP's prompt NAK, by PARAM_REQUEST_LIST
        assert line.endswith(f"Received {len(ParamTable().names())} parameters"), line   # all of the bridge's
        fetch_s = time.monotonic() - t0
        assert not any("timeout" in line.lower() and "ftp" in line.lower() for line in mp.log), mp.log
        mp.cmd("param set MPC_LAND_SPEED 0.6")
        wait_until(lambda: "MPC_LAND_SPEED: 0.6" in (stack.params_file.read_text() if stack.params_file.exists()
                                                      else ""), 20.0, "the parameter persisted by the bridge", mp)
        mp.cmd("arm throttle")
        mp.expect("ARMED", 20.0)
        ground = height_m(stack)
        mp.cmd("takeoff 1.0")
        mp.expect("Mode TAKEOFF", 30.0)   # the heartbeat's PX4 mode, named by MAVProxy
        wait_until(lambda: height_m(stack) - ground > 0.7, 120.0, "the take-off (truth height > 0.7 m)", mp)
        if not hold:
            mp.cmd("long DO_SET_MODE 1 4 6")   # AUTO.LAND (the companion may have asked for it first)
            mp.expect("Mode LAND", 60.0)
            wait_until(lambda: height_m(stack) - ground < 0.1, 120.0, "the landing (truth height < 0.1 m)", mp)
            mp.expect("DISARMED", 60.0)
            return mp.log
        mp.expect("Mode LOITER", 60.0)   # the take-off's end, reported by name
        # MAVProxy 1.8.75's `mode NAME` cannot set a PX4 vehicle's mode: it hands px4_map's (base, main, sub)
        # tuple to set_mode_px4 as one number ("required argument is not a float"); DO_SET_MODE with PX4's
        # (CUSTOM_MODE_ENABLED, main, sub), sent with MAVProxy's `long`, is what `mode` means to send
        mp.cmd("long DO_SET_MODE 1 3 0")   # POSCTL
        mp.expect("Mode POSCTL", 30.0)
        time.sleep(3.0)
        assert height_m(stack) - ground > 0.5, "not holding in POSCTL"
        mp.cmd("long DO_SET_MODE 1 4 6")   # AUTO.LAND
        mp.expect("Mode LAND", 30.0)
        wait_until(lambda: height_m(stack) - ground < 0.1, 120.0, "the landing (truth height < 0.1 m)", mp)
        mp.expect("DISARMED", 60.0)
        mp.log.append(f"# parameters fetched in {fetch_s:.1f} s")
        return mp.log
    finally:
        mp.close()


def test_mavproxy_session_on_the_bridge(tmp_path: Path) -> None:
    stack = Stack(tmp_path)
    odo_gcs = Gcs(stack.mavsdk_port)
    odom = Odometry(stack, odo_gcs)
    try:
        assert odo_gcs.recv("HEARTBEAT", 60.0) is not None
        odom.start()
        log = session(stack, f"udpin:127.0.0.1:{stack.gcs_port}", tmp_path)
        print(log[-1])
    finally:
        odom.stop.set()
        odo_gcs.close()
        stack.close()


def test_mavproxy_session_through_the_companion(tmp_path: Path) -> None:
    """The bridge's first endpoint feeds the companion; MAVProxy talks to the companion's ground-station port."""
    stack = Stack(tmp_path)   # its gcs_port becomes the companion's autopilot link
    odo_gcs = Gcs(stack.mavsdk_port)
    odom = Odometry(stack, odo_gcs)
    try:
        stack.start_companion(CompanionPart(autopilot="gcs_bridge"))   # no camera behind its camera port
        assert odo_gcs.recv("HEARTBEAT", 60.0) is not None
        odom.start()
        log = session(stack, f"udpout:127.0.0.1:{stack.ports.vehicle}", tmp_path, hold=False)
        print(log[-1])
    finally:
        odom.stop.set()
        odo_gcs.close()
        stack.close()   # the companion first

"""The bridge as a deterministic lock-step participant (``quadlink bridge --lockstep``, quadlink/lockstep.py).

The test plays the SITL: the real :class:`~quadlink.lockstep.Coordinator` (the bridge its only participant),
MK ports 1 and 2 on loopback TCP, and the companion as a UDP socket on the bridge's MAVLink endpoint 0. Per
chunk ``k`` it applies what the bridge wrote on port 1 in step ``k - 1`` (its arm state, a version answer),
writes 5 IMU samples (a BoardStatus every 10th chunk), announces ``STEP k`` with what it and the "companion"
have sent, and waits for ``DONE k``: the flow of sim_sitl's deterministic lock-step, without physics.
"""

from __future__ import annotations

import random
import select
import socket
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import pytest
from click.testing import CliRunner

from firmware_bridge.daemon import BridgeConfig, BridgeDaemon
from firmware_bridge.step_inputs import StepInputs
from quadlink.cli import main
from quadlink.frames import GRAVITY_M_S2
from quadlink.lockstep import Coordinator, LockstepError, Step
from quadlink.mavlink import mavlink
from quadlink.mk import messages as mk
from quadlink.mk.protocol import FrameDecoder
from quadlink.vehicle import VehicleConfig

pytestmark = pytest.mark.timeout(120)

IMU_PER_CHUNK = 5
WAIT_S = 10.0


@dataclass
class Timing:
    """How the fake SITL and companion spread their sends over wall time (the part a flight must not see)."""

    seed: int = 0
    jitter_s: float = 0.0  # random sleeps up to this before each write and before STEP
    companion_early: bool = False  # send each datagram a step before the step that announces it
    companion_late_s: float = 0.0  # else: send it this long after the announcing STEP went out


@dataclass
class Flight:
    port1: bytes = b""  # everything the bridge wrote on MK port 1
    companion_rx: list[bytes] = field(default_factory=list)  # every datagram the bridge sent on endpoint 0
    setpoints_per_step: list[int] = field(default_factory=list)
    mavlink_in_after: list[int] = field(default_factory=list)  # daemon.stats.mavlink_in after each DONE
    done_sent: list[dict[str, int]] = field(default_factory=list)  # the bridge's counts per DONE
    setpoints: list[mk.AttitudeSetpoint] = field(default_factory=list)


def companion_message(kind: str) -> bytes:
    """One MAVLink 2 datagram from a ground-station id on the allowlist (through the companion's link)."""
    mav = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
    if kind == "request_version":
        msg = mav.command_long_encode(1, 1, mavlink.MAV_CMD_REQUEST_MESSAGE, 0,
                                      mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION, 0, 0, 0, 0, 0, 0)
    elif kind == "arm":
        msg = mav.command_long_encode(1, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
    else:
        raise ValueError(kind)
    return bytes(msg.pack(mav))


class FakeSitl:
    """The SITL side of the lock-step for the bridge alone (see the module docstring)."""

    def __init__(self, tmp_path: Path, timing: Timing) -> None:
        self.timing = timing
        self.rng = random.Random(timing.seed)
        self.cmd_srv = socket.create_server(("127.0.0.1", 0))
        self.imu_srv = socket.create_server(("127.0.0.1", 0))
        self.coord = Coordinator("127.0.0.1", 0, ("bridge",))
        self.companion = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.companion.bind(("127.0.0.1", 0))
        self.bridge_addr: tuple[str, int] | None = None
        self.config = BridgeConfig(
            mk_cmd_url=f"socket://127.0.0.1:{self.cmd_srv.getsockname()[1]}",
            mk_imu_url=f"socket://127.0.0.1:{self.imu_srv.getsockname()[1]}",
            mavlink_urls=(f"udpout:127.0.0.1:{self.companion.getsockname()[1]}",),
            params_file=str(tmp_path / "p.yaml"), lockstep_url=self.coord.url)
        self.flight = Flight()
        self._port1 = bytearray()
        self._decoder = FrameDecoder()
        self._armed = False
        self._version_answers = 0
        self._imu_k = 0
        self._senders: list[threading.Thread] = []
        self.cmd: socket.socket | None = None
        self.imu: socket.socket | None = None

    def accept(self) -> None:
        self.cmd_srv.settimeout(WAIT_S)
        self.imu_srv.settimeout(WAIT_S)
        self.cmd, _ = self.cmd_srv.accept()
        self.imu, _ = self.imu_srv.accept()
        deadline = time.monotonic() + WAIT_S
        while not self.coord.all_registered():
            assert time.monotonic() < deadline, "the bridge did not register"
            self.coord.poll(0.05)

    # ------------------------------------------------------------------ one chunk
    def chunk(self, k: int, companion: list[bytes], announce: int) -> Step:
        """Chunk ``k``: the bridge's bytes of step ``k - 1`` applied, MK bytes out, ``companion`` datagrams sent
        (announced as ``announce`` datagrams in total), STEP k, DONE k; returns the step announced."""
        assert self.cmd is not None and self.imu is not None
        cmd_out = b""
        for _ in range(self._version_answers):
            cmd_out += mk.encode_message(mk.Version(2, 10, 11, 0, 0))
        self._version_answers = 0
        if k % 10 == 0:
            status = mk.BoardStatus(self._armed, 0, False, 12000, 0, self._imu_k * 2, self._imu_k, 0)
            cmd_out += mk.encode_message(status)
        imu_out = b""
        for _ in range(IMU_PER_CHUNK):
            sample = mk.ImuSample.from_si([0.0, 0.0, -GRAVITY_M_S2], [0.0, 0.0, 0.1], VehicleConfig().imu,
                                          self._imu_k)
            imu_out += mk.encode_message(sample)
            self._imu_k += 1
        # the IMU first on the wire: the bridge must still handle port 1 first
        for sock, data, link in ((self.imu, imu_out, "sitl>bridge.imu"), (self.cmd, cmd_out, "sitl>bridge.cmd")):
            self._jitter()
            if data:
                sock.sendall(data)
            self.coord.sent[link] = self.coord.sent.get(link, 0) + len(data)
        late = bool(companion) and not self.timing.companion_early
        if companion and not late:
            self._send_companion(companion, 0.0)
        self.coord.sent["companion>bridge"] = announce
        self._jitter()
        step = Step(k, (k + 1) * 0.01, self.coord.expect_for("bridge"))
        self.coord.send_step(k, step.t_s)
        if late:
            self._send_companion(companion, self.timing.companion_late_s)
        deadline = time.monotonic() + WAIT_S
        while not self.coord.all_done(k):
            assert "bridge" in self.coord.registered, "the bridge left the lock-step"
            assert time.monotonic() < deadline, f"no DONE {k}"
            self.coord.poll(0.05)
        return step

    def _jitter(self) -> None:
        if self.timing.jitter_s > 0:
            time.sleep(self.rng.uniform(0.0, self.timing.jitter_s))

    def _send_companion(self, datagrams: list[bytes], delay_s: float) -> None:
        assert self.bridge_addr is not None, "the bridge has not sent on endpoint 0 yet"
        addr = self.bridge_addr

        def send() -> None:
            time.sleep(delay_s)
            for d in datagrams:
                self.companion.sendto(d, addr)

        if delay_s > 0:
            t = threading.Thread(target=send, daemon=True)
            t.start()
            self._senders.append(t)
        else:
            send()

    # ------------------------------------------------------------------ what the bridge sent
    def collect(self) -> int:
        """Read port 1 and endpoint 0 up to the counts of the bridge's last DONE; the setpoints among them."""
        assert self.cmd is not None
        sent = self.coord.sent
        want_port1, want_dgrams = sent.get("bridge>sitl", 0), sent.get("bridge>companion", 0)
        deadline = time.monotonic() + WAIT_S
        while len(self._port1) < want_port1 and time.monotonic() < deadline:
            self.cmd.settimeout(0.05)
            try:
                data = self.cmd.recv(65536)
            except TimeoutError:
                continue
            assert data, "the bridge closed MK port 1"
            self._port1 += data
        new = self._port1[len(self.flight.port1):]
        self.flight.port1 = bytes(self._port1)
        while time.monotonic() < deadline and (len(self.flight.companion_rx) < want_dgrams or
                                               select.select([self.companion], [], [], 0)[0]):
            if select.select([self.companion], [], [], 0.05)[0]:
                data, addr = self.companion.recvfrom(65536)
                self.bridge_addr = addr
                self.flight.companion_rx.append(data)
        setpoints = 0
        for frame in self._decoder.feed(bytes(new)):
            if frame.command == "s":
                sp = mk.AttitudeSetpoint.unpack(frame.payload)
                self.flight.setpoints.append(sp)
                self._armed = sp.armed
                setpoints += 1
            elif frame.command == "v":
                self._version_answers += 1
        return setpoints

    def close(self) -> None:
        for t in self._senders:
            t.join(timeout=2.0)
        for s in (self.cmd, self.imu, self.cmd_srv, self.imu_srv, self.companion):
            if s is not None:
                s.close()
        self.coord.close()


#: chunk -> the companion datagrams its STEP announces (sent a step early or late by Timing)
SCRIPT = {20: ["request_version"], 40: ["arm"], 41: ["request_version", "request_version"]}
CHUNKS = 120
PROBE_CHUNK = 20


def fly(tmp_path: Path, timing: Timing, chunks: int = CHUNKS) -> tuple[Flight, BridgeDaemon]:
    sitl = FakeSitl(tmp_path, timing)
    daemon = BridgeDaemon(sitl.config, VehicleConfig())
    errors: list[BaseException] = []
    thread: threading.Thread | None = None
    try:
        daemon.open()
        sitl.accept()

        def run() -> None:
            try:
                daemon.run()
            except LockstepError as exc:
                errors.append(exc)

        thread = threading.Thread(target=run, daemon=True)
        thread.start()
        announced = 0
        for k in range(chunks):
            datagrams = [companion_message(m) for m in SCRIPT.get(k, [])]
            early = [companion_message(m) for m in SCRIPT.get(k + 1, [])] if timing.companion_early else []
            announced += len(datagrams)
            sitl.chunk(k, early if timing.companion_early else datagrams, announced)
            sitl.flight.setpoints_per_step.append(sitl.collect())
            sitl.flight.mavlink_in_after.append(daemon.stats.mavlink_in)
            sitl.flight.done_sent.append({link: n for link, n in sitl.coord.sent.items()
                                          if link.startswith("bridge>")})
            # what the bridge counted is what left, step by step
            assert len(sitl.flight.port1) == sitl.coord.sent["bridge>sitl"]
            assert len(sitl.flight.companion_rx) == sitl.coord.sent["bridge>companion"]
    finally:
        daemon.stop()
        if thread is not None:
            thread.join(timeout=2.0)
        daemon.close()
        sitl.close()
    assert thread is not None and not thread.is_alive(), "the bridge did not stop within 2 s"
    assert not errors, errors
    return sitl.flight, daemon


def test_each_step_is_answered_with_counts_of_what_left_and_one_setpoint_per_chunk(tmp_path):
    flight, daemon = fly(tmp_path, Timing())
    assert len(flight.done_sent) == CHUNKS
    # (a) bridge>sitl = the bytes port 1 received (checked after every DONE in fly), and nothing beyond
    assert flight.done_sent[-1]["bridge>sitl"] == len(flight.port1) > 0
    # (b) exactly one setpoint per 5 IMU samples, in sequence
    assert flight.setpoints_per_step == [1] * CHUNKS
    assert [sp.seq for sp in flight.setpoints] == [k % 256 for k in range(CHUNKS)]
    assert daemon.stats.imu_samples == CHUNKS * IMU_PER_CHUNK and daemon.stats.wall_clock_steps == 0
    # the companion's commands were handled: armed from the step after the one announcing the arm command
    armed = [sp.armed for sp in flight.setpoints]
    assert armed.index(True) == 40 and all(armed[40:])
    # the board answered the version request (port 1 bytes -> bridge) without a wall clock
    assert daemon.autopilot.board_version.startswith("FlightCtrl 2.10a")
    # replies went to the companion, counted: COMMAND_ACK + AUTOPILOT_VERSION per request
    types = [m.get_type() for d in flight.companion_rx
             for m in mavlink.MAVLink(None).parse_buffer(d) or []]
    assert types.count("AUTOPILOT_VERSION") == 3 and types.count("COMMAND_ACK") == 4


def test_a_datagram_that_came_early_waits_for_the_step_that_announces_it(tmp_path):
    """(c) the companion's datagrams arrive a step before their step announces them: held back, not handled."""
    flight, _ = fly(tmp_path, Timing(companion_early=True))
    # the request for chunk 20 was on the bridge's socket during step 19 (sent before STEP 19), not handled
    assert flight.mavlink_in_after[PROBE_CHUNK - 1] == 0
    assert flight.mavlink_in_after[PROBE_CHUNK] == 1
    assert flight.mavlink_in_after[39] == 1 and flight.mavlink_in_after[40] == 2 and flight.mavlink_in_after[41] == 4
    armed = [sp.armed for sp in flight.setpoints]
    assert armed.index(True) == 40


def test_the_same_inputs_at_different_wall_times_give_the_same_bytes(tmp_path):
    """(d) early vs late companion datagrams, short vs long random sleeps (steps well under and well over
    10 ms of wall time, so wall-clock timers would fire differently): byte-identical port 1 and endpoint 0."""
    a, _ = fly(tmp_path / "a", Timing(seed=1, jitter_s=0.0005, companion_early=True))
    b, _ = fly(tmp_path / "b", Timing(seed=2, jitter_s=0.008, companion_late_s=0.03))
    assert a.port1 == b.port1 and len(a.port1) > 0
    assert a.done_sent == b.done_sent
    assert a.companion_rx == b.companion_rx


def test_stop_duration_the_simulation_end_and_a_lost_coordinator(tmp_path):
    """stop() while waiting for a step; --duration in simulated time; the simulation's end message: run()
    returns; the coordinator's connection closed without one: LockstepError."""
    sitl = FakeSitl(tmp_path, Timing())
    daemon = BridgeDaemon(sitl.config, VehicleConfig())
    try:
        daemon.open()
        sitl.accept()
        thread = threading.Thread(target=daemon.run, daemon=True)
        thread.start()
        time.sleep(0.3)  # no STEP yet: the bridge waits, and has sent nothing
        assert sitl.coord.sent == {"bridge>sitl": 0, "bridge>companion": 0}
        t0 = time.monotonic()
        daemon.stop()
        thread.join(timeout=2.0)
        assert not thread.is_alive() and time.monotonic() - t0 < 0.5
    finally:
        daemon.close()
        sitl.close()
    sitl = FakeSitl(tmp_path, Timing())
    daemon = BridgeDaemon(sitl.config, VehicleConfig())
    try:  # --duration is simulated time: the bridge leaves after answering the step that reaches it
        daemon.open()
        sitl.accept()
        thread = threading.Thread(target=daemon.run, kwargs={"duration_s": 0.03}, daemon=True)
        thread.start()
        for k in range(3):
            sitl.coord.send_step(k, (k + 1) * 0.01)
            deadline = time.monotonic() + WAIT_S
            while not sitl.coord.all_done(k) and time.monotonic() < deadline:
                sitl.coord.poll(0.05)
        thread.join(timeout=2.0)
        assert not thread.is_alive() and sitl.coord.all_done(2)
    finally:
        daemon.close()
        sitl.close()
    sitl = FakeSitl(tmp_path, Timing())
    daemon = BridgeDaemon(sitl.config, VehicleConfig())
    try:
        daemon.open()
        sitl.accept()
        sitl.coord.close("duration reached")  # the simulation ended normally
        daemon.run()
    finally:
        daemon.close()
        sitl.close()
    sitl = FakeSitl(tmp_path, Timing())
    daemon = BridgeDaemon(sitl.config, VehicleConfig())
    try:
        daemon.open()
        sitl.accept()
        sitl.coord.close()  # the SITL died
        with pytest.raises(LockstepError, match="closed"):
            daemon.run()
    finally:
        daemon.close()
        sitl.close()


def test_an_announced_datagram_that_never_comes_is_a_lockstep_error(tmp_path, monkeypatch):
    monkeypatch.setattr("firmware_bridge.daemon.DEFAULT_INPUT_TIMEOUT_S", 0.3)
    sitl = FakeSitl(tmp_path, Timing())
    daemon = BridgeDaemon(sitl.config, VehicleConfig())
    errors: list[BaseException] = []
    try:
        daemon.open()
        sitl.accept()

        def run() -> None:
            try:
                daemon.run()
            except LockstepError as exc:
                errors.append(exc)

        thread = threading.Thread(target=run, daemon=True)
        thread.start()
        sitl.coord.sent["companion>bridge"] = 1  # announced, never sent
        sitl.coord.send_step(0, 0.01)
        thread.join(timeout=5.0)
        assert not thread.is_alive()
    finally:
        daemon.close()
        sitl.close()
    assert len(errors) == 1 and "companion>bridge" in str(errors[0]) and "0 of 1" in str(errors[0])


def test_step_inputs_cut_at_the_announced_counts():
    inputs = StepInputs()
    for item in [("mav", 0, b"a"), ("imu", b"12345", 1.0), ("mav", 1, b"gcs"), ("mav", 0, b"b"),
                 ("cmd", b"xy", 2.0), ("mav", 0, b"c")]:
        assert inputs.add(item)
    assert not inputs.add(("link", "cmd", "gone"))
    expect = {"companion>bridge": 2, "sitl>bridge.cmd": 2, "sitl>bridge.imu": 5}
    # canonical order, whatever the arrival order; the third datagram is held back
    assert inputs.take(Step(0, 0.01, expect)) == [("mav", 0, b"a"), ("mav", 0, b"b"), ("mav", 1, b"gcs"),
                                                   ("cmd", b"xy", 2.0), ("imu", b"12345", 1.0)]
    assert inputs.take(Step(1, 0.02, {**expect, "companion>bridge": 3})) == [("mav", 0, b"c")]
    assert inputs.take(Step(2, 0.03, {})) == []  # no counts: what arrived (nothing)
    inputs.add(("imu", b"6", 3.0))
    with pytest.raises(LockstepError, match="6 bytes received, 5 announced"):  # a surplus is not guessed at
        inputs.take(Step(3, 0.04, {**expect, "companion>bridge": 3}))
    with pytest.raises(LockstepError, match="4 datagrams announced"):
        inputs.take(Step(4, 0.05, {"companion>bridge": 4}))


@pytest.mark.parametrize("end_reason, status", [("duration reached", 0), (None, 1)])
def test_cli_lockstep_ends_with_the_simulation_or_exits_1_with_one_line(tmp_path, end_reason, status):
    sitl = FakeSitl(tmp_path, Timing())

    def end_the_simulation() -> None:
        sitl.accept()
        time.sleep(0.2)
        sitl.coord.close(end_reason)

    thread = threading.Thread(target=end_the_simulation, daemon=True)
    thread.start()
    try:   # the CLI in the main thread: it installs signal handlers
        result = CliRunner().invoke(main, ["bridge", "--mk-cmd", sitl.config.mk_cmd_url, "--mk-imu",
                                           sitl.config.mk_imu_url, "--mavlink", sitl.config.mavlink_urls[0],
                                           "--params", str(tmp_path / "p.yaml"), "--lockstep", sitl.coord.url])
        thread.join(timeout=10.0)
    finally:
        sitl.close()
    assert result.exit_code == status, result.output
    lines = [line for line in result.output.splitlines() if line.startswith("quadlink bridge:")]
    if status == 0:
        assert not lines
    else:
        assert len(lines) == 1 and "coordinator" in lines[0]

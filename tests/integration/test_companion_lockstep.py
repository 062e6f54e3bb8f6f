"""The companion daemon as a participant of the deterministic lock-step (quadlink.lockstep), on loopback.

The test thread is the SITL's side: the real :class:`~quadlink.lockstep.Coordinator` (the companion its only
participant), a camera stream of synthetic frames, and two raw UDP sockets standing in for the bridge and the
ground station, whose datagrams the test announces (or holds back) in each STEP as their senders would."""

from __future__ import annotations

import dataclasses
import select
import socket
import threading
import time
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest

from companion.arbiter import ArbiterParams
from companion.cameras import StreamCamera
from companion.config import CompanionConfig, ModeParams, PanScanConfig, TimingConfig
from companion.daemon import Companion
from companion.lockstep_links import AUTOPILOT_IN, AUTOPILOT_OUT, CAMERA_IN, GCS_IN, GCS_OUT, join_lockstep
from perception.odometry import OdometryCounts
from perception.pipeline import ObstacleSectors, PerceptionOutput
from perception.synthetic import pose, qvga_intrinsics, render
from quadlink.camera import CameraStreamServer, RgbdFrame
from quadlink.lockstep import Coordinator, LockstepEnded, LockstepError
from quadlink.mavlink import mavlink
from quadlink.mavlink.connection import open_mavlink
from quadlink.vehicle import CameraConfig

STEP_S = 0.01


def t_of(k: int) -> float:
    """The simulated time at the end of chunk ``k`` (what STEP k carries)."""
    return round((k + 1) * STEP_S, 6)


class StandInPipeline:
    """Stands in for PerceptionPipeline: a fixed scene; records the IMU stamp the daemon had at each frame."""

    def __init__(self) -> None:
        self.frames = 0
        self.daemon: Companion | None = None
        self.imu_stamp_at_frame: list[float | None] = []
        self.odometry_counts = OdometryCounts()

    def on_imu(self, stamp_s: float, gyro: np.ndarray, accel: np.ndarray) -> None:
        pass

    def on_frame(self, frame: RgbdFrame) -> PerceptionOutput:
        self.frames += 1
        assert self.daemon is not None
        self.imu_stamp_at_frame.append(self.daemon.time.imu_stamp_s)
        distances = np.full(72, np.inf)
        return PerceptionOutput(frame.stamp_s, 0.0, 0.0, 0.0, np.zeros(3), np.zeros(3), np.eye(3) * 1e-3,
                                np.array([0.0, 0.0, -1.0]), True, 0.9, np.zeros((0, 3)), np.zeros((0, 3)),
                                ObstacleSectors(frame.stamp_s, distances, 5.0, 0.0, 0.3, 4.0), None, 0.001,
                                odometry_counts=self.odometry_counts)


class Peer:
    """A fake bridge or ground station: a UDP socket talking to one of the daemon's endpoints, counting the
    datagrams it sends and receives; what it receives is kept with the step whose DONE preceded it."""

    def __init__(self, port: int, sysid: int, compid: int) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.setblocking(False)
        self.dest = ("127.0.0.1", port)
        self.codec = mavlink.MAVLink(None, sysid, compid)
        self.parser = mavlink.MAVLink(None)
        self.parser.robust_parsing = True
        self.sent = 0
        self.datagrams = 0
        self.received: list[tuple[int, Any]] = []   # (step, message)
        self.raw: list[tuple[int, bytes]] = []      # (step, datagram)

    def send(self, msg: Any, delay_s: float = 0.0) -> None:
        """Send ``msg`` now, or ``delay_s`` later from another thread (counted now: announced while in flight)."""
        buf = bytes(msg.pack(self.codec))
        self.sent += 1
        if delay_s <= 0:
            self.sock.sendto(buf, self.dest)
        else:
            threading.Timer(delay_s, self.sock.sendto, (buf, self.dest)).start()

    def collect(self, step: int, expected: int, timeout_s: float = 2.0) -> None:
        """Read every datagram that has arrived (waiting, bounded, until ``expected`` have in all)."""
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                data = self.sock.recv(65536)
            except BlockingIOError:
                if self.datagrams >= expected or time.monotonic() > deadline:
                    return
                select.select([self.sock], [], [], 0.01)
                continue
            self.datagrams += 1
            self.raw.append((step, data))
            self.received += [(step, m) for m in self.parser.parse_buffer(data) or [] if m.get_type() != "BAD_DATA"]

    def of_type(self, kind: str) -> list[tuple[int, Any]]:
        return [(k, m) for k, m in self.received if m.get_type() == kind]

    def close(self) -> None:
        self.sock.close()


class LockstepRig:
    """The daemon (its loop in a thread) joined to a coordinator driven step by step from the test thread."""

    def __init__(self) -> None:
        cfg = CompanionConfig(timing=TimingConfig(camera_timeout_s=1.0), pan_scan=PanScanConfig(enabled=False),
                              modes=ModeParams(gcs_timeout_s=0.5, gcs_land_timeout_s=1.5, takeoff_min_s=0.3),
                              arbiter=ArbiterParams(link_timeout_s=0.5))
        cfg = dataclasses.replace(cfg, links=dataclasses.replace(cfg.links, autopilot="udpin:127.0.0.1:0",
                                                                 gcs="udpin:127.0.0.1:0"))
        self.coordinator = Coordinator("127.0.0.1", 0, ("companion",))
        self.server = CameraStreamServer("127.0.0.1", 0)
        ap_link = open_mavlink(cfg.links.autopilot, 1, 191)
        gcs_link = open_mavlink(cfg.links.gcs, 1, 191)
        ap_port, gcs_port = ap_link.port.getsockname()[1], gcs_link.port.getsockname()[1]
        camera = StreamCamera(f"tcp://127.0.0.1:{self.server.port}", R_qc=CameraConfig().R_qc_matrix)
        self.links = join_lockstep(self.coordinator.url, ap_link, gcs_link, camera)
        assert camera.connected, "the camera stream is connected before the hello"
        deadline = time.monotonic() + 5.0
        while not self.coordinator.all_registered():
            assert time.monotonic() < deadline, "the companion did not register"
            self.coordinator.poll(0.05)
        self.pipeline = StandInPipeline()
        self.daemon = Companion(cfg, ap_link, gcs_link, camera, lambda frame: self.pipeline,
                                clock=self.links.client.clock, lockstep=self.links)
        self.pipeline.daemon = self.daemon
        self.bridge = Peer(ap_port, 1, 1)
        self.gcs = Peer(gcs_port, 255, 190)
        self.frames = 0
        self.k = 0
        self.error: BaseException | None = None
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()
        K = qvga_intrinsics()
        rgb, depth = render(pose(np.eye(3), [0.0, 0.0, 0.0]), K, supersample=1)
        self.template = RgbdFrame(0, 0.0, rgb, depth, K, CameraConfig().R_qc_matrix, np.zeros(3))

    def _run(self) -> None:
        try:
            self.daemon.run(self.stop)
        except BaseException as exc:  # noqa: BLE001 - handed to the test
            self.error = exc

    # ------------------------------------------------------------------ what the senders do
    def autopilot_heartbeat(self) -> None:
        self.bridge.send(mavlink.MAVLink_heartbeat_message(
            mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 0,
            mavlink.MAV_STATE_ACTIVE, 3))

    def imu(self, t_s: float) -> None:
        self.bridge.send(mavlink.MAVLink_highres_imu_message(int(t_s * 1e6), 0.0, 0.0, -9.81, 0.0, 0.0, 0.1, 0, 0,
                                                             0, 0, 0, 0, 20.0, 0x3F))

    def imu_chunk(self, k: int) -> None:
        """The bridge's HIGHRES_IMU of chunk ``k`` (500 Hz), as it forwards them during step ``k``."""
        for i in range(1, 6):
            self.imu(t_of(k) - STEP_S + i * 0.002)

    def gcs_heartbeat(self) -> None:
        self.gcs.send(mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0,
                                                        0, 3))

    def publish_frame(self, stamp_s: float) -> None:
        self.frames += 1
        self.server.publish(dataclasses.replace(self.template, seq=self.frames, stamp_s=stamp_s))

    # ------------------------------------------------------------------ the coordinator's side
    def step(self, gcs_announced: int | None = None) -> int:
        """STEP k with every unit sent so far announced (the ground station's: ``gcs_announced`` if given), DONE k
        awaited, the datagrams the daemon sent collected and checked against its DONE's counts. Returns k."""
        k = self.k
        c = self.coordinator
        c.sent[AUTOPILOT_IN] = self.bridge.sent
        c.sent[GCS_IN] = self.gcs.sent if gcs_announced is None else gcs_announced
        c.sent[CAMERA_IN] = self.frames
        c.send_step(k, t_of(k))
        deadline = time.monotonic() + 10.0
        while not c.all_done(k):
            assert self.error is None, f"daemon failed: {self.error!r}"
            assert time.monotonic() < deadline, f"no DONE {k}"
            c.poll(0.05)
        # (a) the DONE's counts are the datagrams that reached the peers, and all of them were sent in the step
        self.bridge.collect(k, c.sent[AUTOPILOT_OUT])
        self.gcs.collect(k, c.sent[GCS_OUT])
        assert self.bridge.datagrams == c.sent[AUTOPILOT_OUT], f"step {k}: DONE says {c.sent[AUTOPILOT_OUT]}"
        assert self.gcs.datagrams == c.sent[GCS_OUT], f"step {k}: DONE says {c.sent[GCS_OUT]}"
        self.k += 1
        return k

    def close(self) -> None:
        self.stop.set()
        self.thread.join(5.0)
        self.daemon.close()
        self.coordinator.close()
        self.server.close()
        self.bridge.close()
        self.gcs.close()


@pytest.fixture
def rig() -> Iterator[LockstepRig]:
    r = LockstepRig()
    yield r
    r.close()


def _own_heartbeats(peer: Peer) -> list[int]:
    """The steps in which ``peer`` received the companion's HEARTBEAT."""
    return [k for k, m in peer.of_type("HEARTBEAT") if m.get_srcComponent() == 191]


def _setpoints(peer: Peer) -> list[tuple[int, Any]]:
    return peer.of_type("SET_POSITION_TARGET_LOCAL_NED")


def test_the_daemon_is_a_function_of_the_steps(rig: LockstepRig) -> None:
    rig.autopilot_heartbeat()
    rig.gcs_heartbeat()
    first = rig.step()
    # (d) the clock is the step's simulated time: the first TIMESYNC requests carry STEP 0's t_s exactly
    ts = rig.bridge.of_type("TIMESYNC")
    assert [(k, m.tc1, m.ts1) for k, m in ts] == [(first, 0, int(t_of(first) * 1e9))]
    gcs_ts = [(k, m.ts1) for k, m in rig.gcs.of_type("TIMESYNC") if m.get_srcComponent() == 191]
    assert gcs_ts == [(first, int(t_of(first) * 1e9))]
    assert rig.bridge.of_type("HEARTBEAT"), "the companion's heartbeat to the autopilot"
    # ... and not yet to the ground station, which has heard nothing of the autopilot (its heartbeat came before
    # the station's first datagram): it waits behind the autopilot's next message (companion.scheduler's
    # HeartbeatBehindAutopilot; mavsdk_server would never find the vehicle otherwise)
    assert not _own_heartbeats(rig.gcs)

    # (b) a ground-station datagram not yet announced waits for the step that announces it
    rig.gcs.send(mavlink.MAVLink_command_long_message(1, 191, mavlink.MAV_CMD_USER_1, 0, 0, 0, 0, 0, 0, 0, 0))
    time.sleep(0.05)   # in the daemon's socket well before the STEP that leaves it out
    held = rig.step(gcs_announced=rig.gcs.sent - 1)
    assert not rig.gcs.of_type("COMMAND_ACK"), "a datagram handled before the step that announces it"
    announced = rig.step()
    acks = rig.gcs.of_type("COMMAND_ACK")
    assert [(k, m.command, m.result) for k, m in acks] == \
        [(announced, mavlink.MAV_CMD_USER_1, mavlink.MAV_RESULT_UNSUPPORTED)]
    assert announced == held + 1
    # every announced datagram is handled in its step, also when a frame is split over several of them
    buf = bytes(mavlink.MAVLink_command_long_message(1, 191, mavlink.MAV_CMD_USER_2, 0, 0, 0, 0, 0, 0, 0, 0
                                                     ).pack(rig.gcs.codec))
    for part in (buf[:5], buf[5:12], buf[12:]):
        rig.gcs.sock.sendto(part, rig.gcs.dest)
        rig.gcs.sent += 1
    time.sleep(0.05)
    split = rig.step()
    assert [(k, m.command) for k, m in rig.gcs.of_type("COMMAND_ACK")][1:] == [(split, mavlink.MAV_CMD_USER_2)]

    # (c) a frame rendered in chunk F, announced in STEP F, is processed in step F + 1: the bridge forwards the IMU
    # of chunk k during its step k, which reaches the companion in step k + 1 (here: sent before STEP k + 1)
    while rig.k < 20:
        rig.imu_chunk(rig.k - 1)
        rig.step()
    F = rig.k
    stamp_s = t_of(F) - 0.005
    rig.imu_chunk(F - 1)
    rig.publish_frame(stamp_s)
    time.sleep(0.05)   # the frame is in the daemon's socket during step F: it must still wait
    assert rig.step() == F and rig.pipeline.frames == 0
    assert not [m for _, m in _setpoints(rig.bridge) if m.time_boot_ms == int(stamp_s * 1e3)]
    rig.imu_chunk(F)
    assert rig.step() == F + 1 and rig.pipeline.frames == 1
    framed = [k for k, m in _setpoints(rig.bridge) if m.time_boot_ms == int(stamp_s * 1e3)]
    assert framed == [F + 1], "the frame's setpoint leaves in the step after the frame's own"
    odo = rig.bridge.of_type("ODOMETRY")
    assert [(k, m.time_usec) for k, m in odo] == [(F + 1, int(stamp_s * 1e6))]
    at_frame = rig.pipeline.imu_stamp_at_frame
    assert at_frame[0] is not None and at_frame[0] >= stamp_s, "the IMU had caught up with the frame"

    # (d) again: the 1 Hz tasks are due on simulated time, whatever the wall time (these steps take ~1 s or less)
    wall0 = time.monotonic()
    while rig.k <= 101:
        rig.imu_chunk(rig.k - 1)
        rig.step()
    ts_steps = [k for k, _ in rig.bridge.of_type("TIMESYNC")]
    assert ts_steps == [0, 100], ts_steps   # t_s 0.01 and 1.01
    assert [m.ts1 for _, m in rig.bridge.of_type("TIMESYNC")] == [int(t_of(0) * 1e9), int(t_of(100) * 1e9)]
    # the one held at step 0 went with the first autopilot message the station received, the one due at step 100
    # (t_s 1.01) with the autopilot's next, each right behind it
    first_ap = min(k for k, m in rig.gcs.received if m.get_srcComponent() == 1)
    assert _own_heartbeats(rig.gcs) == [first_ap, 101], _own_heartbeats(rig.gcs)
    got = [m for _, m in rig.gcs.received]
    assert all(got[i - 1].get_srcComponent() == 1 for i, m in enumerate(got)
               if m.get_type() == "HEARTBEAT" and m.get_srcComponent() == 191)
    assert time.monotonic() - wall0 < 30.0

    # nothing is sent outside a step
    n_bridge, n_gcs = rig.bridge.datagrams, rig.gcs.datagrams
    time.sleep(0.3)
    rig.bridge.collect(rig.k, 0, timeout_s=0.0)
    rig.gcs.collect(rig.k, 0, timeout_s=0.0)
    assert (rig.bridge.datagrams, rig.gcs.datagrams) == (n_bridge, n_gcs)

    # Ctrl-C between steps: out within ~0.2 s, the lock-step left
    t0 = time.monotonic()
    rig.stop.set()
    rig.thread.join(2.0)
    assert not rig.thread.is_alive() and time.monotonic() - t0 < 0.5
    assert rig.error is None


def _fly(rig: LockstepRig, slow: bool) -> tuple[list[tuple[int, bytes]], list[tuple[int, bytes]]]:
    """40 steps of one scripted flight; ``slow``: wall time passes between steps, and the ground station's datagrams
    are still in flight when their STEP is sent. What the daemon sent on both links, by step."""
    for k in range(40):
        if k == 0:
            rig.autopilot_heartbeat()
            rig.gcs_heartbeat()
        else:
            rig.imu_chunk(k - 1)
        if k % 3 == 1:
            rig.publish_frame(t_of(k) - 0.005)
        delay_s = 0.03 if slow else 0.0
        if k % 2 == 0:
            rig.gcs.send(mavlink.MAVLink_manual_control_message(1, 0, 0, 500, 0, 0), delay_s)
        if k == 7:
            rig.gcs.send(mavlink.MAVLink_command_long_message(1, 191, mavlink.MAV_CMD_USER_1, 0, 0, 0, 0, 0, 0, 0, 0),
                         delay_s)
        early = mavlink.MAVLink_command_long_message(1, 191, mavlink.MAV_CMD_USER_2, 0, 0, 0, 0, 0, 0, 0, 0)
        if k == 11 and not slow:   # in the socket a step before the STEP that announces it: held back
            rig.gcs.send(early)
            rig.step(gcs_announced=rig.gcs.sent - 1)
            continue
        if k == 12 and slow:
            rig.gcs.send(early, delay_s)
        if slow:
            time.sleep(0.02)
        rig.step()
    return rig.bridge.raw, rig.gcs.raw


def test_the_same_flight_sends_the_same_bytes_whatever_the_wall_time() -> None:
    runs = []
    for slow in (False, True):
        rig = LockstepRig()
        try:
            runs.append(_fly(rig, slow))
        finally:
            rig.close()
    (bridge_fast, gcs_fast), (bridge_slow, gcs_slow) = runs
    assert len(bridge_fast) >= 20 and len(gcs_fast) >= 40, (len(bridge_fast), len(gcs_fast))
    assert bridge_fast == bridge_slow
    assert gcs_fast == gcs_slow


def test_the_ground_station_reads_the_odometrys_counts(rig: LockstepRig) -> None:
    """A frame the odometry bridged, held, refused or aligned again is counted where a ground station (and the
    tlog the campaign reports read) can see it: NAMED_VALUE_INT ODO_* with the pipeline's last counts, once a
    second of simulated time, and AIR_* with those counted while the vehicle was off the ground."""
    rig.pipeline.odometry_counts = OdometryCounts(fallbacks=1)
    rig.autopilot_heartbeat()
    rig.gcs_heartbeat()
    while rig.k <= 101:
        if rig.k:
            rig.imu_chunk(rig.k - 1)
        if rig.k == 60:   # the counts grew between the two frames, on the ground
            rig.pipeline.odometry_counts = OdometryCounts(fallbacks=3, lost=1, rejected_jumps=2, restarts=4)
        if rig.k in (10, 60):
            rig.publish_frame(t_of(rig.k) - 0.005)
        rig.step()
    assert rig.pipeline.frames >= 1
    named = {}
    for _, m in rig.gcs.of_type("NAMED_VALUE_INT"):
        named[str(m.name)] = m.value
    assert {k: v for k, v in named.items() if k.startswith("ODO_")} == \
        {"ODO_BRIDGE": 3, "ODO_HELD": 1, "ODO_JUMP": 2, "ODO_RESTRT": 4}
    # the vehicle never left the ground (IDLE): none of it happened in the air
    assert {k: v for k, v in named.items() if k.startswith("AIR_")} == \
        {"AIR_BRIDGE": 0, "AIR_HELD": 0, "AIR_JUMP": 0, "AIR_RESTRT": 0}


def test_a_stop_during_a_wait_for_an_announced_datagram_ends_the_loop(rig: LockstepRig) -> None:
    rig.autopilot_heartbeat()
    rig.step()
    rig.coordinator.sent[AUTOPILOT_IN] = rig.bridge.sent + 1   # announced, never sent: the step waits for it
    rig.coordinator.sent[CAMERA_IN] = 0
    rig.coordinator.send_step(rig.k, t_of(rig.k))
    time.sleep(0.3)
    assert rig.thread.is_alive(), "the step waits (bounded) for the announced datagram"
    t0 = time.monotonic()
    rig.stop.set()
    rig.thread.join(2.0)
    assert not rig.thread.is_alive() and time.monotonic() - t0 < 0.5
    assert rig.error is None


def test_the_loop_ends_with_a_lockstep_error_when_the_coordinator_is_lost(rig: LockstepRig) -> None:
    rig.autopilot_heartbeat()
    rig.step()
    rig.coordinator.close()
    rig.thread.join(5.0)
    assert not rig.thread.is_alive()
    assert isinstance(rig.error, LockstepError) and not isinstance(rig.error, LockstepEnded)


def test_the_simulations_normal_end_ends_the_loop_without_an_error(rig: LockstepRig) -> None:
    rig.autopilot_heartbeat()
    rig.step()
    rig.coordinator.close("duration reached")
    rig.thread.join(5.0)
    assert not rig.thread.is_alive()
    assert rig.error is None


def test_cli_exits_with_status_1_when_the_coordinator_goes() -> None:
    from click.testing import CliRunner

    from quadlink.cli import main

    coordinator = Coordinator("127.0.0.1", 0, ("companion",))
    server = CameraStreamServer("127.0.0.1", 0)
    stepped = threading.Event()

    def sitl() -> None:
        deadline = time.monotonic() + 60.0
        while not coordinator.all_registered() and time.monotonic() < deadline:
            coordinator.poll(0.05)
        coordinator.send_step(0, t_of(0))
        while not coordinator.all_done(0) and time.monotonic() < deadline:
            coordinator.poll(0.05)
        stepped.set()
        coordinator.close()   # the simulation ends

    thread = threading.Thread(target=sitl, daemon=True)
    thread.start()
    try:
        result = CliRunner().invoke(main, ["companion", "--lockstep", coordinator.url,
                                           "--camera", f"tcp://127.0.0.1:{server.port}",
                                           "--autopilot", "udpin:127.0.0.1:0", "--gcs", "udpin:127.0.0.1:0",
                                           "--image-port", "0"])
    finally:
        thread.join(5.0)
        coordinator.close()
        server.close()
    assert stepped.is_set()
    assert result.exit_code == 1, result.output
    lines = result.stderr.strip().splitlines()
    assert len(lines) >= 1 and "coordinator closed the connection" in lines[-1]
    assert lines[-1].startswith("quadlink companion:")


def test_cli_refuses_lockstep_without_the_sitl_camera_stream(tmp_path: Any) -> None:
    from click.testing import CliRunner

    from quadlink.cli import main

    result = CliRunner().invoke(main, ["companion", "--lockstep", "tcp://127.0.0.1:9", "--camera", str(tmp_path),
                                       "--autopilot", "udpin:127.0.0.1:0", "--gcs", "udpin:127.0.0.1:0"])
    assert result.exit_code == 2
    assert "--lockstep needs the SITL camera stream" in result.stderr

"""The SITL's pacing (pure, clock as an argument) and its lock-step waits serving the serial ports."""

from __future__ import annotations

import socket
import time

import pytest

from quadlink.camera import CameraStreamClient
from quadlink.mk.messages import (
    AttitudeSetpoint,
    ImuSample,
    Version,
    VersionRequest,
    decode_message,
    encode_message,
)
from quadlink.mk.protocol import FrameDecoder
from sim_sitl.config import SitlConfig
from sim_sitl.pacing import MAX_SETPOINT_CREDIT, RealTimePacer, SetpointGate, wait_serving
from sim_sitl.runner import Sitl, SitlOptions


class FakeClock:
    """A wall clock the test advances (every read costs ``step_s``)."""

    def __init__(self, step_s: float = 0.0) -> None:
        self.t_s = 100.0
        self.step_s = step_s

    def __call__(self) -> float:
        self.t_s += self.step_s
        return self.t_s


# ---------------------------------------------------------------- pure pacing
def test_real_time_pacer_waits_for_the_wall_time_of_each_sim_time():
    pacer = RealTimePacer(speed=2.0)
    pacer.rebase(10.0, 0.0)
    assert pacer.wait_s(1.0, 10.0) == pytest.approx(0.5)  # 1 s of sim at 2x takes 0.5 s of wall
    assert pacer.wait_s(1.0, 10.4) == pytest.approx(0.1)
    assert pacer.wait_s(1.0, 10.7) == 0.0  # 0.2 s late: no wait, no restart
    assert not pacer.fell_behind


def test_real_time_pacer_restarts_instead_of_catching_up_in_a_burst():
    pacer = RealTimePacer(speed=1.0, max_behind_s=0.5)
    pacer.rebase(0.0, 0.0)
    assert pacer.wait_s(1.0, 2.0) == 0.0 and pacer.fell_behind  # 1 s late
    # paced from the restart: the next 10 ms of sim is 10 ms of wall after it, not 1 s earlier
    assert pacer.wait_s(1.01, 2.0) == pytest.approx(0.01)


def test_unpaced_never_waits():
    for speed in (0.0, float("inf")):
        pacer = RealTimePacer(speed=speed)
        assert pacer.unpaced and pacer.wait_s(1e6, 0.0) == 0.0


def test_setpoint_gate_counts_credit_and_starts_once():
    gate = SetpointGate()
    assert not gate.take()
    assert gate.on_setpoints(1) and gate.gated
    assert not gate.on_setpoints(10)  # already gated
    assert gate.credit == MAX_SETPOINT_CREDIT
    assert all(gate.take() for _ in range(MAX_SETPOINT_CREDIT)) and not gate.take()
    gate.release()
    assert not gate.gated


def test_wait_serving_serves_between_tries_and_times_out_on_the_injected_clock():
    clock = FakeClock(step_s=0.01)
    served: list[float] = []
    blocks: list[float] = []

    def ready(block_s: float) -> bool:
        blocks.append(block_s)
        clock.t_s += block_s
        return False

    assert wait_serving(ready, lambda: served.append(clock.t_s), 0.5, clock, lambda: False, slice_s=0.05) is False
    assert len(served) == len(blocks) >= 5  # served before every try
    assert max(blocks) <= 0.05
    clock2 = FakeClock()
    hits = iter([False, False, True])
    assert wait_serving(lambda _s: next(hits), lambda: None, 1.0, clock2, lambda: False) is True
    assert wait_serving(lambda _s: False, lambda: None, 1.0, FakeClock(), lambda: True) is None


# ---------------------------------------------------------------- the real SITL in lock-step
def _drain_imu(sock: socket.socket, dec: FrameDecoder, counters: list[int], seconds: float) -> None:
    sock.settimeout(0.05)
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        try:
            data = sock.recv(65536)
        except TimeoutError:
            continue
        counters += [m.sample_counter for m in map(decode_message, dec.feed(data)) if isinstance(m, ImuSample)]


@pytest.mark.sitl
def test_lockstep_camera_wait_keeps_serving_the_serial_ports():
    """While a camera ack is outstanding the sim time stands still, yet a setpoint sent on port 1 reaches the
    firmware at once, the IMU of the frame's own tick has been delivered on port 2, and a version request
    sent during the wait is answered (on the simulated wire, right after the ack)."""
    # a long lock-step bound: on a loaded machine the test's own pauses must not look like a lost consumer
    opts = SitlOptions(config=SitlConfig(scenario="empty", lockstep_timeout_s=20.0), port1=0, port2=0, camera_port=0,
                       camera=True, truth_url=None, lockstep=True, progress_every_s=60.0)
    sitl = Sitl(opts).start()
    p1 = socket.create_connection(sitl.port1.address, timeout=5)
    p2 = socket.create_connection(sitl.port2.address, timeout=5)
    deadline = time.monotonic() + 10
    while (sitl.port1.tcp_client_count, sitl.port2.tcp_client_count) != (1, 1) and time.monotonic() < deadline:
        time.sleep(0.01)  # both serial clients accepted before the camera (and so the lock-step) starts
    cam = CameraStreamClient(f"tcp://127.0.0.1:{sitl.camera_server.port}")
    try:
        frame = None
        deadline = time.monotonic() + 30
        while frame is None and time.monotonic() < deadline:
            frame = cam.read(timeout_s=1.0)
        assert frame is not None
        # not acked: the SITL is waiting for us; drain port 2 and look at what it delivered meanwhile
        imu: list[int] = []
        dec2 = FrameDecoder()
        _drain_imu(p2, dec2, imu, 0.5)
        t_wait = sitl.sim.t_s
        frame_tick = round(frame.stamp_s / sitl.sim.tick_s)
        assert t_wait == pytest.approx(frame.stamp_s + sitl.sim.tick_s)  # stands still after the frame's tick
        assert imu and imu[-1] == frame_tick % 4096  # the frame's own IMU sample left before the wait
        setpoints_before = sitl.stats.setpoints
        p1.sendall(encode_message(AttitudeSetpoint(0.0, 0.0, 0.0, 0.0, False, 77)) +
                   encode_message(VersionRequest()))
        time.sleep(0.5)
        assert sitl.sim.t_s == t_wait  # still waiting for the ack
        assert sitl.stats.camera_ack_timeouts == 0
        assert sitl.stats.setpoints == setpoints_before + 1  # port 1 was read during the wait
        assert sitl.sim.firmware.command.seq == 77  # and the setpoint reached the firmware
        cam.ack(frame.seq)
        dec1 = FrameDecoder()
        p1.settimeout(0.2)
        version = None
        deadline = time.monotonic() + 10
        while version is None and time.monotonic() < deadline:
            try:
                data = p1.recv(4096)
            except TimeoutError:
                continue
            version = next((m for m in map(decode_message, dec1.feed(data)) if isinstance(m, Version)), None)
        assert version is not None
        assert sitl.sim.t_s > t_wait
    finally:
        p1.close()
        p2.close()
        cam.close()
        sitl.stop()

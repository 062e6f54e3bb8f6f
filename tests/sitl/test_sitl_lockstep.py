"""The SITL as the deterministic lock-step's coordinator (quadlink/lockstep.py, issue 15).

A fake bridge registers, reads exactly the bytes each STEP announces, answers with a setpoint and its byte count.
Checked: no simulated time passes before every participant registered; the steps are 10 ms of simulated time
each; the counts are the bytes that actually arrived; the bridge's setpoint of step k is applied in chunk k + 1
whatever the wall-clock timing (two runs with different delays give identical truth); the run ends with an
``end`` message on its duration; a participant that does not answer fails the run.
"""

from __future__ import annotations

import random
import socket
import threading
import time

import numpy as np
import pytest

from quadlink.lockstep import LockstepClient, LockstepEnded, LockstepError
from quadlink.mk.messages import AttitudeSetpoint, ImuSample, decode_message, encode_message
from quadlink.mk.protocol import FrameDecoder
from sim_sitl.config import SitlConfig
from sim_sitl.runner import DISARMED_END_S, Sitl, SitlOptions

pytestmark = pytest.mark.sitl


def _sitl(duration_s: float = 1.0, participants: tuple[str, ...] = ("bridge",), **kw) -> Sitl:
    opts = SitlOptions(config=SitlConfig(scenario="empty"), port1=0, port2=0, camera_port=0, camera=False,
                       truth_url=None, progress_every_s=60.0, lockstep=True, lockstep_port=0,
                       lockstep_participants=participants, duration_s=duration_s, **kw)
    return Sitl(opts)


def _read_exactly(sock: socket.socket, n: int) -> bytes:
    out = bytearray()
    while len(out) < n:
        chunk = sock.recv(n - len(out))
        if not chunk:
            raise ConnectionError("closed")
        out += chunk
    return bytes(out)


class FakeBridge:
    """Reads each step's announced bytes, answers every 5th IMU sample with a setpoint (thrust ramps up)."""

    def __init__(self, sitl: Sitl, jitter_s: float, seed: int) -> None:
        self.p1 = socket.create_connection(sitl.port1.address, timeout=5)
        self.p2 = socket.create_connection(sitl.port2.address, timeout=5)
        assert sitl.coordinator is not None
        self.client = LockstepClient(sitl.coordinator.url, "bridge")
        self.hover = sitl.vehicle.hover_thrust_fraction
        self.rng = random.Random(seed)
        self.jitter_s = jitter_s
        self.got = {"sitl>bridge.cmd": 0, "sitl>bridge.imu": 0}
        self.sent = 0
        self.steps: list[tuple[int, float]] = []
        self.samples = 0
        self.ended: str | None = None
        self.arm = True
        self.dec = FrameDecoder()

    def run(self) -> None:
        self.client.hello({"bridge>sitl": 0})
        try:
            while True:
                step = self.client.next_step(5.0)
                if step is None:
                    continue
                self.steps.append((step.index, step.t_s))
                time.sleep(self.rng.uniform(0.0, self.jitter_s))
                n1 = step.expect["sitl>bridge.cmd"] - self.got["sitl>bridge.cmd"]
                n2 = step.expect["sitl>bridge.imu"] - self.got["sitl>bridge.imu"]
                _read_exactly(self.p1, n1)
                data = _read_exactly(self.p2, n2)
                self.got["sitl>bridge.cmd"] += n1
                self.got["sitl>bridge.imu"] += n2
                for frame in self.dec.feed(data):
                    if isinstance(decode_message(frame), ImuSample):
                        self.samples += 1
                thrust = self.hover * (1.25 if step.index < 60 else 0.9)
                out = encode_message(AttitudeSetpoint(0.0, 0.02 * (step.index % 7), 0.0, thrust, self.arm,
                                                      step.index % 256))
                if self.rng.random() < 0.5:   # the bytes may land before or after DONE: counted, they wait
                    self.p1.sendall(out)
                    self.sent += len(out)
                    self.client.done({"bridge>sitl": self.sent})
                else:
                    self.sent += len(out)
                    self.client.done({"bridge>sitl": self.sent})
                    time.sleep(self.rng.uniform(0.0, self.jitter_s))
                    self.p1.sendall(out)
        except LockstepEnded as exc:
            self.ended = str(exc)
        finally:
            self.client.close()
            self.p1.close()
            self.p2.close()


def _fly(jitter_s: float, seed: int) -> tuple[Sitl, FakeBridge, np.ndarray]:
    sitl = _sitl(duration_s=1.0)
    thread = threading.Thread(target=sitl.run, daemon=True)
    thread.start()
    try:
        time.sleep(0.3)
        assert sitl.sim.t_s == 0.0   # nobody registered: no simulated time passes
        bridge = FakeBridge(sitl, jitter_s, seed)
        bridge.run()
        thread.join(10.0)
        assert not thread.is_alive()
        state = sitl.sim.world.state
        return sitl, bridge, np.concatenate([state.p_ned_m, state.v_ned_m_s, state.R_ned_q.ravel()])
    finally:
        sitl.stop()


def test_steps_are_chunks_counted_exactly_and_wall_timing_changes_nothing():
    sitl_a, bridge_a, truth_a = _fly(jitter_s=0.0, seed=1)
    sitl_b, bridge_b, truth_b = _fly(jitter_s=0.004, seed=2)
    for sitl, bridge in ((sitl_a, bridge_a), (sitl_b, bridge_b)):
        assert bridge.ended is not None and "duration" in bridge.ended
        assert [i for i, _ in bridge.steps] == list(range(100))
        np.testing.assert_allclose([t for _, t in bridge.steps], 0.01 * np.arange(1, 101), atol=1e-9)
        assert bridge.samples == 500            # every IMU sample of the second, announced and read
        assert sitl.stats.setpoints == 99       # the last step's setpoint is never applied (the run ended)
        assert sitl.sim.firmware.armed
    # the vehicle climbed, and the two runs are the same run, bit for bit
    assert truth_a[2] < -0.05
    assert np.array_equal(truth_a, truth_b)


def test_a_participant_that_does_not_answer_fails_the_run():
    sitl = _sitl(duration_s=5.0, lockstep_done_timeout_s=0.5)
    errors: list[BaseException] = []

    def run() -> None:
        try:
            sitl.run()
        except LockstepError as exc:
            errors.append(exc)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    assert sitl.coordinator is not None
    client = LockstepClient(sitl.coordinator.url, "bridge")
    try:
        client.hello({"bridge>sitl": 0})
        step = None
        while step is None:
            step = client.next_step(2.0)
        thread.join(5.0)      # no DONE: the SITL gives up after 0.5 s
        assert not thread.is_alive()
        assert errors and "not answered" in str(errors[0]) and "bridge" in str(errors[0])
        assert sitl.sim.t_s == pytest.approx(0.01)
    finally:
        client.close()
        sitl.stop()


def _operator_leaving_after(url: str, last_step: int) -> threading.Thread:
    def run() -> None:
        client = LockstepClient(url, "operator")
        client.hello({})
        while True:
            step = client.next_step(5.0)
            if step is None:
                continue
            client.done({})
            if step.index == last_step:
                client.close()   # its last DONE: it leaves at this step
                return

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread


@pytest.mark.parametrize("armed", [True, False])
def test_the_run_ends_on_simulated_time_after_the_operator_left(armed: bool):
    """Armed: ``end_after_operator_s`` after the operator's last step; disarmed: 2 s on the ground after it."""
    sitl = _sitl(duration_s=30.0, participants=("bridge", "operator"), end_after_operator_s=0.5)
    thread = threading.Thread(target=sitl.run, daemon=True)
    thread.start()
    try:
        assert sitl.coordinator is not None
        operator = _operator_leaving_after(sitl.coordinator.url, last_step=9)
        bridge = FakeBridge(sitl, 0.0, 3)
        if not armed:
            bridge.hover = 0.0
            bridge.arm = False
        bridge.run()
        thread.join(10.0)
        operator.join(5.0)
        assert bridge.ended is not None and ("still armed" if armed else "disarmed since") in bridge.ended
        # left after step 9, i.e. at 0.10 s; the checks run before each chunk
        want_s = 0.10 + (0.5 if armed else DISARMED_END_S)
        assert sitl.sim.t_s == pytest.approx(want_s, abs=1e-9)
    finally:
        sitl.stop()

"""The SITL's ports: MK protocol on TCP, serial pacing, IMU stream, lock-step, ground truth."""

from __future__ import annotations

import contextlib
import socket
import time

import numpy as np
import pytest

from quadlink.frames import GRAVITY_M_S2
from quadlink.mk.messages import (
    AttitudeSetpoint,
    BoardStatus,
    Data3D,
    Data3DRequest,
    ExternControl,
    ExternControlAck,
    ImuSample,
    Version,
    VersionRequest,
    decode_message,
    encode_message,
)
from quadlink.mk.protocol import FrameDecoder
from quadlink.vehicle import ImuConfig
from sim_sitl.board import BoardTelemetry, Port1Protocol
from sim_sitl.config import SitlConfig
from sim_sitl.runner import Sitl, SitlOptions
from sim_sitl.serial_line import SerialLine


# ---------------------------------------------------------------- serial line (pure)
def test_serial_line_paces_bytes_at_the_baud_rate():
    line = SerialLine(115200, 10, tx_buffer_bytes=256)
    frame = bytes(range(22))
    assert line.offer(frame, 0.0)
    byte_s = 10 / 115200
    assert line.drain(5.5 * byte_s) == frame[:5]  # 5 whole bytes after 5.5 byte times
    assert line.drain(22 * byte_s + 1e-9) == frame[5:]
    assert line.drain(1.0) == b""
    assert line.stats.frames_sent == 1 and line.stats.bytes_sent == 22


def test_serial_line_drops_frames_that_do_not_fit_and_counts_late_ones():
    line = SerialLine(115200, 10, tx_buffer_bytes=100, late_after_s=0.004)
    accepted = [line.offer(b"x" * 30, 0.0) for _ in range(5)]
    assert accepted == [True, True, True, False, False]
    assert line.stats.frames_dropped == 2 and line.stats.bytes_dropped == 60
    assert line.stats.frames_late == 1  # the third starts 60 bytes = 5.2 ms later
    out = line.drain(1.0)
    assert len(out) == 90


def test_imu_stream_budget_fits_115200_baud_with_no_drops():
    line = SerialLine(115200, 10, 256)
    frame = b"i" * ImuSample.WIRE_BYTES
    received = 0
    for k in range(5000):  # 10 s at 500 Hz
        assert line.offer(frame, k * 0.002)
        received += len(line.drain(k * 0.002 + 0.002))
    assert line.stats.frames_dropped == 0 and line.stats.frames_late == 0
    assert received == pytest.approx(5000 * 22, abs=22)
    assert 500 * 22 / line.bytes_per_s == pytest.approx(0.955, abs=0.001)


def test_overloaded_port_drops_and_reports():
    line = SerialLine(115200, 10, 256)
    frame = b"d" * 94  # DebugData framed, at 200 Hz = 18,800 B/s > 11,520 B/s
    for k in range(1000):
        line.offer(frame, k * 0.005)
        line.drain(k * 0.005)
    assert line.stats.frames_dropped > 300
    sent = line.stats.frames_sent
    assert sent * 94 / 5.0 <= line.bytes_per_s * 1.01  # the wire never carries more than the baud rate


# ---------------------------------------------------------------- port-1 protocol (pure)
def _telem(t_s: float, armed: bool = False) -> BoardTelemetry:
    return BoardTelemetry(t_s, int(t_s / 0.002), armed, 0, False, 12600, 0, 7, 0.1, -0.2, 0.3, 0.5,
                          (1.0, 1.0, 1.0, 1.0))


def _decode(frames: list[bytes]) -> list:
    dec = FrameDecoder()
    return [decode_message(f) for f in dec.feed(b"".join(frames))]


def test_port1_answers_version_and_acknowledges_extern_control():
    proto = Port1Protocol()
    cmds, replies = proto.on_bytes(encode_message(VersionRequest()) + encode_message(ExternControl(frame=42)), 0.0)
    msgs = _decode(replies)
    assert not cmds
    assert isinstance(msgs[0], Version) and msgs[0].proto_major == 11
    assert msgs[1] == ExternControlAck(42)


def test_port1_streams_stop_after_the_mk_timeout_and_status_runs_at_10_hz():
    proto = Port1Protocol(stream_timeout_s=4.0)
    proto.on_bytes(encode_message(Data3DRequest(5)), 0.0)  # every 50 ms
    counts = {"C": 0, "S": 0}
    for k in range(3000):  # 6 s at 500 Hz
        for m in _decode(proto.poll(_telem(k * 0.002))):
            counts[m.COMMAND] += 1
            if isinstance(m, Data3D):
                assert m.roll_rad == pytest.approx(0.1, abs=0.002)
    assert counts["C"] == pytest.approx(4.0 / 0.05, abs=2)  # stopped after 4 s
    assert counts["S"] == pytest.approx(60, abs=1)


def test_port1_status_on_arm_change_and_setpoints_reach_the_firmware():
    proto = Port1Protocol()
    proto.poll(_telem(0.0))
    sp = AttitudeSetpoint(0.1, 0.0, 0.2, 0.5, True, 9)
    cmds, _ = proto.on_bytes(encode_message(sp)[:7], 0.01)
    assert not cmds  # half a frame
    cmds, _ = proto.on_bytes(encode_message(sp)[7:], 0.01)
    assert len(cmds) == 1 and cmds[0].armed and cmds[0].seq == 9 and cmds[0].thrust == pytest.approx(0.5, abs=1e-4)
    msgs = _decode(proto.poll(_telem(0.012, armed=True)))
    assert isinstance(msgs[0], BoardStatus) and msgs[0].armed


# ---------------------------------------------------------------- the running SITL (TCP, pybullet)
def _options(**kw) -> SitlOptions:
    base = dict(config=SitlConfig(scenario="empty"), port1=0, port2=0, camera_port=0, camera=False, truth_url=None,
                progress_every_s=60.0)
    base.update(kw)
    return SitlOptions(**base)


def _read_frames(sock: socket.socket, until, timeout_s: float = 10.0) -> list:
    dec = FrameDecoder()
    msgs: list = []
    deadline = time.monotonic() + timeout_s
    sock.settimeout(0.2)
    while time.monotonic() < deadline and not until(msgs):
        try:
            data = sock.recv(4096)
        except TimeoutError:
            continue
        if not data:
            break
        msgs += [decode_message(f) for f in dec.feed(data)]
    return msgs


@pytest.mark.sitl
def test_sitl_version_reply_status_and_imu_stream_over_tcp():
    sitl = Sitl(_options()).start()
    try:
        p1 = socket.create_connection(sitl.port1.address, timeout=5)
        p2 = socket.create_connection(sitl.port2.address, timeout=5)
        p1.sendall(encode_message(VersionRequest()))
        msgs = _read_frames(p1, lambda m: any(isinstance(x, Version) for x in m)
                            and any(isinstance(x, BoardStatus) for x in m))
        assert any(isinstance(x, Version) for x in msgs)
        status = [x for x in msgs if isinstance(x, BoardStatus)]
        assert status and not status[0].armed and status[0].battery_mv > 12000
        imu = [x for x in _read_frames(p2, lambda m: len(m) >= 300) if isinstance(x, ImuSample)]
        assert len(imu) >= 300
        counters = np.array([s.sample_counter for s in imu])
        assert np.all(np.diff(counters) % 4096 == 1)  # no sample lost
        acc = np.array([s.accel_m_s2(ImuConfig()) for s in imu])
        np.testing.assert_allclose(acc.mean(axis=0), [0.0, 0.0, -GRAVITY_M_S2], atol=0.2)  # at rest, level
        p1.close()
        p2.close()
    finally:
        sitl.stop()


@pytest.mark.sitl
def test_lockstep_waits_for_setpoints_and_flies_them():
    """A client that answers every 5th IMU sample with a setpoint drives sim time exactly."""
    sitl = Sitl(_options(lockstep=True)).start()
    with contextlib.ExitStack() as sockets:   # closed on a failed assert too (a leaked socket fails a later test)
        sockets.callback(sitl.stop)
        p1 = sockets.enter_context(socket.create_connection(sitl.port1.address, timeout=5))
        p2 = sockets.enter_context(socket.create_connection(sitl.port2.address, timeout=5))
        p2.settimeout(3.0)
        dec = FrameDecoder()
        hover = sitl.vehicle.hover_thrust_fraction
        sent = 0
        last_counter = None
        t0 = time.monotonic()
        while sent < 300 and time.monotonic() - t0 < 60:
            for frame in dec.feed(p2.recv(4096)):
                msg = decode_message(frame)
                if not isinstance(msg, ImuSample):
                    continue
                if last_counter is not None:
                    assert (msg.sample_counter - last_counter) % 4096 == 1
                last_counter = msg.sample_counter
                if msg.sample_counter % 5 == 4 and sent < 300:   # one recv may hold several answered samples
                    thrust = hover * 1.3 if sent < 100 else hover
                    p1.sendall(encode_message(AttitudeSetpoint(0.0, 0.0, 0.0, thrust, True, sent % 256)))
                    sent += 1
        assert sent == 300
        time.sleep(0.3)
        # lock-step: sim time did not run away while we were slow; it is within a few chunks of our setpoints
        assert sitl.sim.t_s == pytest.approx(300 * 0.01, abs=0.05)
        assert sitl.stats.lockstep_timeouts == 0
        assert sitl.sim.firmware.armed and sitl.sim.world.state.p_ned_m[2] < sitl.sim.world.start_p_ned_m[2] - 0.3


@pytest.mark.sitl
def test_port1_over_budget_drops_frames_and_reports_them(caplog):
    """Debug + 3D data every 10 ms plus status need ~12.3 kB/s: more than 115200 Bd carries."""
    from quadlink.mk.messages import DebugData, DebugRequest

    sitl = Sitl(_options(progress_every_s=0.5)).start()
    try:
        p1 = socket.create_connection(sitl.port1.address, timeout=5)
        with caplog.at_level("WARNING"):
            p1.sendall(encode_message(DebugRequest(1)) + encode_message(Data3DRequest(1)))
            t0 = time.monotonic()
            msgs = _read_frames(p1, lambda m: time.monotonic() - t0 > 2.0, timeout_s=2.5)
            time.sleep(0.6)
        debug = [m for m in msgs if isinstance(m, DebugData)]
        assert len(debug) > 20
        assert sitl.line1.stats.frames_dropped > 0 and sitl.line1.stats.frames_late > 0
        assert sitl.line1.stats.bytes_sent <= sitl.line1.bytes_per_s * (sitl.sim.t_s + 0.01)
        assert "serial link over budget" in caplog.text
        p1.close()
    finally:
        sitl.stop()

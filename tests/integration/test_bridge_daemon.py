"""The bridge daemon against a fake MK board over loopback TCP, with a pymavlink client over UDP.

The fake board speaks the stack's firmware protocol on two TCP ports (port 1: BoardStatus, Version,
setpoints in; port 2: IMU at 500 Hz) and runs lock-step like the SITL: it sends 10 ms of IMU (5
samples), then waits for one AttitudeSetpoint before the next chunk.
"""

from __future__ import annotations

import socket
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import given
from hypothesis import strategies as st

from companion.journal import JournalWriter as CompanionJournal
from firmware_bridge.daemon import BridgeConfig, BridgeDaemon, _align
from firmware_bridge.journal import SCHEMA, JournalWriter, Kind, decode_input, encode_input, read_events
from firmware_bridge.replay import replay_bridge_journal
from quadlink import journal as core
from quadlink.cli import main
from quadlink.config import to_dict
from quadlink.errors import LinkError
from quadlink.frames import GRAVITY_M_S2
from quadlink.mavlink import mavlink
from quadlink.mavlink.connection import open_mavlink
from quadlink.mavlink.tlog import TlogWriter, read_tlog
from quadlink.mk import messages as mk
from quadlink.mk.protocol import ADDR_FC, FrameDecoder, encode_frame
from quadlink.vehicle import VehicleConfig


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class FakeBoard:
    """Two TCP listeners on ephemeral ports; lock-step IMU chunks answered by setpoints."""

    def __init__(self, chunks: int, garbage: bool = False) -> None:
        self.cmd_srv = socket.create_server(("127.0.0.1", 0))
        self.imu_srv = socket.create_server(("127.0.0.1", 0))
        self.chunks = chunks
        self.garbage = garbage
        self.setpoints: list[mk.AttitudeSetpoint] = []
        self.version_requests = 0
        self.waits_timed_out = 0
        self.imu_cfg = VehicleConfig().imu
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    @property
    def cmd_url(self) -> str:
        return f"socket://127.0.0.1:{self.cmd_srv.getsockname()[1]}"

    @property
    def imu_url(self) -> str:
        return f"socket://127.0.0.1:{self.imu_srv.getsockname()[1]}"

    def _run(self) -> None:
        self.cmd_srv.settimeout(5.0)
        self.imu_srv.settimeout(5.0)
        cmd, _ = self.cmd_srv.accept()
        imu, _ = self.imu_srv.accept()
        cmd.settimeout(0.5)
        decoder = FrameDecoder()
        armed = False
        k = 0
        for chunk in range(self.chunks):
            if self._stop.is_set():
                break
            data = b""
            for _ in range(5):
                sample = mk.ImuSample.from_si([0.0, 0.0, -GRAVITY_M_S2], [0.0, 0.0, 0.1], self.imu_cfg, k)
                data += encode_frame(ADDR_FC, "I", sample.pack())
                k += 1
            if self.garbage and chunk % 20 == 3:
                data += b"#bI==garbage\r" + b"\x00\xff" * 5
            imu.sendall(data)
            if chunk % 10 == 0:
                status = mk.BoardStatus(armed, 0, False, 12000, 0, k * 2, k, 0)
                cmd.sendall(encode_frame(ADDR_FC, "S", status.pack()))
            got = False
            deadline = time.monotonic() + 2.0
            while not got and time.monotonic() < deadline:
                try:
                    raw = cmd.recv(4096)
                except TimeoutError:
                    continue
                if not raw:
                    return
                for frame in decoder.feed(raw):
                    if frame.command == "s":
                        sp = mk.AttitudeSetpoint.unpack(frame.payload)
                        self.setpoints.append(sp)
                        armed = sp.armed
                        got = True
                    elif frame.command == "v":
                        self.version_requests += 1
                        cmd.sendall(encode_frame(ADDR_FC, "V", mk.Version(2, 10, 11, 0, 0).pack()))
            if not got:
                self.waits_timed_out += 1
        self._stop.wait(5.0)
        cmd.close()
        imu.close()

    def close(self) -> None:
        self._stop.set()
        self.thread.join(timeout=5.0)
        self.cmd_srv.close()
        self.imu_srv.close()


@pytest.fixture
def gcs_port():
    return free_udp_port()


def start(board: FakeBoard, gcs_port: int, tmp_path: Path):
    config = BridgeConfig(mk_cmd_url=board.cmd_url, mk_imu_url=board.imu_url,
                          mavlink_urls=(f"udpout:127.0.0.1:{gcs_port}",), params_file=str(tmp_path / "p.yaml"))
    daemon = BridgeDaemon(config, VehicleConfig())
    gcs = open_mavlink(f"udpin:127.0.0.1:{gcs_port}", 255, 190)
    daemon.open()
    thread = threading.Thread(target=daemon.run, kwargs={"duration_s": 30.0}, daemon=True)
    thread.start()
    return daemon, thread, gcs


def stop(daemon, thread, gcs, board) -> None:
    daemon.stop()
    thread.join(timeout=5.0)
    daemon.close()
    gcs.close()
    board.close()


def test_daemon_lockstep_telemetry_params_and_version(gcs_port, tmp_path):
    board = FakeBoard(chunks=300)  # 3 s of board time
    daemon, thread, gcs = start(board, gcs_port, tmp_path)
    try:
        hb = gcs.recv_match(type="HEARTBEAT", blocking=True, timeout=5.0)
        assert hb is not None and hb.get_srcSystem() == 1 and hb.autopilot == mavlink.MAV_AUTOPILOT_PX4
        imu_stamps = []
        deadline = time.monotonic() + 10.0
        while len(imu_stamps) < 200 and time.monotonic() < deadline:
            m = gcs.recv_match(type="HIGHRES_IMU", blocking=True, timeout=1.0)
            if m is not None:
                imu_stamps.append(m.time_usec)
        assert len(imu_stamps) == 200
        assert set(np.diff(imu_stamps)) == {2000}  # board time, one message per sample, in order
        # parameter download over the same link (the bridge answers on the link it was asked on)
        gcs.mav.param_request_list_send(1, 1)
        got = {}
        deadline = time.monotonic() + 5.0
        while len(got) < len(daemon.params) and time.monotonic() < deadline:
            m = gcs.recv_match(type="PARAM_VALUE", blocking=True, timeout=1.0)
            if m is not None:
                got[m.param_id] = m.param_value
        assert len(got) == len(daemon.params)
        gcs.mav.param_set_send(1, 1, b"MIS_TAKEOFF_ALT", 1.7, 9)
        echo = gcs.recv_match(type="PARAM_VALUE", blocking=True, timeout=3.0)
        assert echo is not None and echo.param_id == "MIS_TAKEOFF_ALT" and echo.param_value == pytest.approx(1.7)
        board.thread.join(timeout=15.0)
    finally:
        stop(daemon, thread, gcs, board)
    # lock-step contract: every 10 ms chunk got exactly one setpoint, in sequence
    assert board.waits_timed_out == 0
    assert len(board.setpoints) == 300
    seqs = [sp.seq for sp in board.setpoints]
    assert all((b - a) % 256 == 1 for a, b in zip(seqs, seqs[1:]))
    assert not any(sp.armed for sp in board.setpoints)
    assert board.version_requests >= 1 and daemon.autopilot.board_version.startswith("FlightCtrl 2.10a")
    # persisted
    assert "MIS_TAKEOFF_ALT: 1.7" in (tmp_path / "p.yaml").read_text()


def test_daemon_survives_garbage_on_the_mk_port(gcs_port, tmp_path):
    board = FakeBoard(chunks=200, garbage=True)
    daemon, thread, gcs = start(board, gcs_port, tmp_path)
    try:
        # garbage on the MAVLink side too: random datagrams to the bridge's socket
        gcs.recv_match(type="HEARTBEAT", blocking=True, timeout=5.0)
        rng = np.random.default_rng(7)
        for _ in range(20):
            for address in list(gcs.clients):
                gcs.port.sendto(rng.integers(0, 256, 64, dtype=np.uint8).tobytes() + b"\xfd\x09", address)
        board.thread.join(timeout=15.0)
        status = None
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline:
            status = gcs.recv_match(type="SYS_STATUS", blocking=True, timeout=1.5)
            if status is not None and status.errors_count2 > 0:
                break
    finally:
        stop(daemon, thread, gcs, board)
    assert len(board.setpoints) == 200 and board.waits_timed_out == 0
    assert daemon.autopilot.counters["mk_bad"] >= 5
    assert daemon.autopilot.counters["mavlink_bad"] >= 1  # counted, not fatal: the board kept getting setpoints
    assert status is not None and status.errors_count2 > 0  # reported in SYS_STATUS


def test_missing_port_is_a_link_error(tmp_path):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # nothing listens after close
    config = BridgeConfig(mk_cmd_url=f"socket://127.0.0.1:{port}", params_file=str(tmp_path / "p.yaml"))
    with pytest.raises(LinkError, match="cannot open"):
        BridgeDaemon(config, VehicleConfig()).open()


def test_counter_alignment_unwraps_the_12_bit_counter():
    assert _align(10000, 10000 % 4096) == 10000
    assert _align(10000, (10000 + 3) % 4096) == 10003
    assert _align(8193, 4095) == 8191
    assert _align(0, 5) == 5


def test_a_journaled_bridge_re_runs_bit_for_bit_and_a_changed_reading_is_found(gcs_port, tmp_path):
    """Issue 28: the bridge's input journal (firmware_bridge.journal), free-running against the fake board with a
    ground station's parameter download and change and garbage on both sides: the replay writes every MK setpoint
    and MAVLink frame the flight wrote; a journal with one clock reading changed diverges there."""
    board = FakeBoard(chunks=200, garbage=True)
    config = BridgeConfig(mk_cmd_url=board.cmd_url, mk_imu_url=board.imu_url,
                          mavlink_urls=(f"udpout:127.0.0.1:{gcs_port}",), params_file=str(tmp_path / "p.yaml"))
    path = tmp_path / "bridge.qlbj"
    journal = JournalWriter(path, {"bridge": to_dict(config), "vehicle": to_dict(VehicleConfig()), "params": {}})
    daemon = BridgeDaemon(config, VehicleConfig(), journal=journal)
    gcs = open_mavlink(f"udpin:127.0.0.1:{gcs_port}", 255, 190)
    daemon.open()
    thread = threading.Thread(target=daemon.run, kwargs={"duration_s": 30.0}, daemon=True)
    thread.start()
    try:
        gcs.recv_match(type="HEARTBEAT", blocking=True, timeout=5.0)
        gcs.mav.param_request_list_send(1, 1)
        gcs.mav.param_set_send(1, 1, b"MIS_TAKEOFF_ALT", 1.7, 9)
        for address in list(gcs.clients):
            gcs.port.sendto(b"\xfd\x09garbage" * 4, address)
        board.thread.join(timeout=15.0)
    finally:
        stop(daemon, thread, gcs, board)
        journal.close()
    report = replay_bridge_journal(path)
    assert report.identical, report.summary()
    assert report.by_kind["INPUT"] >= 200 and report.by_kind["HOUSEKEEPING"] > 100
    assert report.writes_compared >= 200 + 1000   # every setpoint, every HIGHRES_IMU at least
    # the same journal with one housekeeping turn's clock reading moved by 5 s
    header, events = read_events(path)
    tampered = tmp_path / "tampered.qlbj"
    writer = core.JournalWriter(tampered, {k: v for k, v in header.items() if k not in ("version", "started_unix_s")},
                                SCHEMA)
    target = None
    for event in events:
        with writer.event(event.kind, event.payload):
            for kind, readings in event.readings.items():
                for i, t in enumerate(readings):
                    moved = target is None and event.index > 500 and event.kind == Kind.HOUSEKEEPING and \
                        kind == Kind.CLOCK and i == 0
                    if moved:
                        target = event.index
                    writer.clock(lambda t=t, moved=moved: t + 5.0 if moved else t, kind)()
            for kind, buf in event.outputs:
                writer.output(kind, buf)
    writer.close()
    assert target is not None
    report = replay_bridge_journal(tampered)
    # found at once or at the next turns (a tick timer set 5 s ahead skips the ticks after it), never before
    assert not report.identical and report.divergence_event is not None, report.summary()
    assert target <= report.divergence_event <= target + 10, (target, report.summary())
    # the command a user runs: 0 identical, 1 a divergence, 2 not a bridge journal (a companion's)
    assert CliRunner().invoke(main, ["replay-bridge", str(path)]).exit_code == 0
    assert CliRunner().invoke(main, ["replay-bridge", str(tampered)]).exit_code == 1
    companion_journal = tmp_path / "companion.qljn"
    CompanionJournal(companion_journal, {}).close()
    wrong = CliRunner().invoke(main, ["replay-bridge", str(companion_journal)])
    assert wrong.exit_code == 2 and "not a bridge journal" in wrong.output


@given(st.one_of(
    st.tuples(st.sampled_from(["imu", "cmd"]), st.binary(max_size=64), st.floats(allow_nan=False)),
    st.tuples(st.just("mav"), st.integers(0, 255), st.binary(max_size=280)),
    st.tuples(st.just("mavbad"), st.integers(0, 255), st.text(max_size=40)),
    st.tuples(st.just("link"), st.sampled_from(["imu", "cmd"]), st.text(max_size=40))))
def test_every_reader_item_survives_the_journal(item):
    assert decode_input(encode_input(item)) == item


def test_the_tlog_holds_what_the_ground_station_link_was_sent_and_nothing_else(tmp_path):
    """``--tlog``: every packet sent on the ground-station link (link 1), byte for byte and in order, as a ground
    station there received it; the companion link's own replies (a parameter read asked on link 0) are not in it."""
    board = FakeBoard(chunks=150)
    companion = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    companion.bind(("127.0.0.1", 0))
    ground = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    ground.bind(("127.0.0.1", 0))
    config = BridgeConfig(mk_cmd_url=board.cmd_url, mk_imu_url=board.imu_url,
                          mavlink_urls=(f"udpout:127.0.0.1:{companion.getsockname()[1]}",
                                        f"udpout:127.0.0.1:{ground.getsockname()[1]}"),
                          params_file=str(tmp_path / "p.yaml"))
    tlog = TlogWriter(tmp_path / "bridge.tlog")
    daemon = BridgeDaemon(config, VehicleConfig(), tlog=tlog)
    received: dict[str, list[bytes]] = {"companion": [], "ground": []}
    done = threading.Event()

    def read(name: str, sock: socket.socket) -> None:   # read as it comes: a socket's buffer holds ~0.5 s of it
        sock.settimeout(0.1)
        while not done.is_set():
            try:
                received[name].append(sock.recv(65536))
            except TimeoutError:
                continue

    readers = [threading.Thread(target=read, args=(n, s), daemon=True)
               for n, s in (("companion", companion), ("ground", ground))]
    for r in readers:
        r.start()
    daemon.open()
    thread = threading.Thread(target=daemon.run, kwargs={"duration_s": 30.0}, daemon=True)
    thread.start()
    try:
        deadline = time.monotonic() + 5.0
        while not received["companion"] and time.monotonic() < deadline:
            time.sleep(0.01)
        ask = mavlink.MAVLink(None, 255, 190)
        companion.sendto(ask.param_request_read_encode(1, 1, b"MIS_TAKEOFF_ALT", -1).pack(ask),
                         ("127.0.0.1", daemon.mavlinks[0].port.getsockname()[1]))
        board.thread.join(timeout=15.0)
        time.sleep(0.3)   # the last datagrams in flight
    finally:
        daemon.stop()
        thread.join(timeout=5.0)
        daemon.close()
        tlog.close()
        done.set()
        for r in readers:
            r.join(timeout=2.0)
        companion.close()
        ground.close()
        board.close()
    logged = [bytes(m.get_msgbuf()) for _, m in read_tlog(tmp_path / "bridge.tlog")]
    assert len(logged) > 700 and tlog.failed is None   # 1.5 s of board time: 750 HIGHRES_IMU alone
    assert logged == received["ground"]
    answered = [m for d in received["companion"] for m in mavlink.MAVLink(None).parse_buffer(d) or []
                if m.get_type() == "PARAM_VALUE"]
    assert [m.param_id for m in answered] == ["MIS_TAKEOFF_ALT"]   # asked on link 0, answered there only
    assert not any(b"MIS_TAKEOFF_ALT" in p for p in logged)

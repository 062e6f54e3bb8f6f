"""The netem proxies over real loopback sockets: a pymavlink heartbeat stream, replies, a TCP stream."""

from __future__ import annotations

import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from harness.netem import Impairment, start_proxy
from quadlink.mavlink import mavlink

pytestmark = pytest.mark.integration

ONE_WAY_MS = 100.0
JITTER_MS = 10.0
N_HEARTBEATS = 60
PERIOD_S = 0.02


def _heartbeat(mav: mavlink.MAVLink) -> bytes:
    data = mav.heartbeat_encode(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0).pack(mav)
    mav.seq = (mav.seq + 1) % 256            # what MAVLink.send does after packing
    return bytes(data)


def _receive(sock: socket.socket, parser: mavlink.MAVLink, until_s: float) -> list[tuple[float, int, tuple]]:
    """(arrival time, MAVLink sequence, sender) of every heartbeat received before ``until_s``."""
    out = []
    while time.monotonic() < until_s:
        sock.settimeout(max(until_s - time.monotonic(), 0.001))
        try:
            data, addr = sock.recvfrom(4096)
        except TimeoutError:
            break
        t = time.monotonic()
        for msg in parser.parse_buffer(data) or []:
            if msg.get_type() == "HEARTBEAT":
                out.append((t, msg.get_seq(), addr))
    return out


def test_udp_proxy_delays_a_heartbeat_stream_and_routes_replies_back() -> None:
    target = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)       # the companion's udpin port
    target.bind(("127.0.0.1", 0))
    client = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)       # the ground station (udpout)
    client.bind(("127.0.0.1", 0))
    proxy = start_proxy("udp", 0, target.getsockname()[1], Impairment(delay_ms=ONE_WAY_MS, jitter_ms=JITTER_MS),
                        seed=5)
    try:
        gcs = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
        sent: dict[int, float] = {}
        received: list[tuple[float, int, tuple]] = []
        rx = threading.Thread(target=lambda: received.extend(
            _receive(target, mavlink.MAVLink(None), time.monotonic() + N_HEARTBEATS * PERIOD_S + 1.0)))
        rx.start()
        for _ in range(N_HEARTBEATS):
            msg = _heartbeat(gcs)
            sent[msg[4]] = time.monotonic()       # MAVLink 2 header byte 4 = sequence
            client.sendto(msg, proxy.listen_address)
            time.sleep(PERIOD_S)
        rx.join(timeout=5.0)
        delays_ms = np.array([(t - sent[seq]) * 1e3 for t, seq, _ in received])
        assert len(delays_ms) == N_HEARTBEATS                          # no loss configured: all arrive
        assert [seq for _, seq, _ in received] == sorted(sent)            # and in order (no reorder configured)
        assert np.mean(delays_ms) == pytest.approx(ONE_WAY_MS, abs=8.0)
        assert np.min(delays_ms) > ONE_WAY_MS - 4 * JITTER_MS
        # the companion answers from its port: the proxy routes the reply to the last sender, delayed
        vehicle = mavlink.MAVLink(None, srcSystem=1, srcComponent=191)
        t_reply = time.monotonic()
        target.sendto(_heartbeat(vehicle), received[-1][2])            # to where the stream came from
        back = _receive(client, mavlink.MAVLink(None), time.monotonic() + 1.0)
        assert len(back) == 1
        assert (back[0][0] - t_reply) * 1e3 == pytest.approx(ONE_WAY_MS, abs=4 * JITTER_MS)
        assert proxy.uplink.stats.released == N_HEARTBEATS and proxy.downlink.stats.released == 1
    finally:
        proxy.close()
        target.close()
        client.close()


def test_tcp_proxy_delays_chunks_and_keeps_the_bytes() -> None:
    server = socket.create_server(("127.0.0.1", 0))
    proxy = start_proxy("tcp", 0, server.getsockname()[1], Impairment(delay_ms=80.0, loss=0.5), seed=1)
    try:
        c = socket.create_connection(proxy.listen_address, timeout=5.0)
        server.settimeout(5.0)
        s, _ = server.accept()
        payload = bytes(np.random.default_rng(0).integers(0, 256, 200_000, dtype=np.uint8))
        t0 = time.monotonic()
        c.sendall(payload)
        got = b""
        s.settimeout(5.0)
        first_s = None
        while len(got) < len(payload):
            chunk = s.recv(65536)
            assert chunk
            first_s = first_s or time.monotonic()
            got += chunk
        assert got == payload                                           # loss does not apply to TCP
        assert first_s is not None and (first_s - t0) * 1e3 == pytest.approx(80.0, abs=30.0)
        s.sendall(b"ack")                                               # the other direction, delayed too
        t1 = time.monotonic()
        assert c.recv(16) == b"ack" and (time.monotonic() - t1) * 1e3 == pytest.approx(80.0, abs=30.0)
        c.close()
        assert s.recv(16) == b""                                        # end of stream passed on
        s.close()
    finally:
        proxy.close()
        server.close()


def test_cli_starts_forwards_and_stops_on_interrupt() -> None:
    target = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    target.bind(("127.0.0.1", 0))
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    probe.bind(("127.0.0.1", 0))
    listen_port = probe.getsockname()[1]
    probe.close()                                                       # a free port for the CLI
    proc = subprocess.Popen([sys.executable, "-m", "quadlink.cli", "netem", "--listen", f"udp:127.0.0.1:{listen_port}",
                             "--to", f"udp:127.0.0.1:{target.getsockname()[1]}", "--delay-ms", "50",
                             "--seed", "1", "--log-period-s", "0.5"],
                            stderr=subprocess.PIPE, text=True)
    try:
        client = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        target.settimeout(0.2)
        data = None
        for _ in range(50):                                             # until the CLI is up
            client.sendto(b"ping", ("127.0.0.1", listen_port))
            try:
                data, _ = target.recvfrom(16)
                break
            except TimeoutError:
                continue
        assert data == b"ping"
        time.sleep(0.8)
        proc.send_signal(2)                                             # Ctrl-C
        _, err = proc.communicate(timeout=30)   # a loaded machine: the interpreter's exit alone can take seconds
        assert proc.returncode == 0, err
        assert "up: " in err and "netem: stopped" in err
        client.close()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()   # reaped and its pipes closed: no unraisable warning in a later test
        target.close()
    bad = subprocess.run([sys.executable, "-m", "quadlink.cli", "netem", "--listen", "udp:127.0.0.1:1",
                          "--to", "tcp:127.0.0.1:2"], capture_output=True, text=True, timeout=30)
    assert bad.returncode == 2 and "--listen is udp but --to is tcp" in bad.stderr

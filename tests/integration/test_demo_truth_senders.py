"""The demo's judge listens for the SITL's ground truth on a UDP port; a second SITL sending its truth there (a test's
on the demo's default ports once did) interleaves another vehicle into the track. The recorder notes every sender,
and more than one voids the flight's judgement (harness.demo.cli raises JudgementVoid) instead of judging a
track of two vehicles."""

from __future__ import annotations

import socket
import time

from harness.demo.recorder import Recorder
from harness.ports import free_port
from quadlink.mavlink import mavlink


def _send(sock: socket.socket, port: int, t_ms: int, x: float) -> None:
    enc = mavlink.MAVLink(None, 250, 1)
    sock.sendto(enc.local_position_ned_encode(t_ms, x, 0.0, -1.0, 0.0, 0.0, 0.0).pack(enc), ("127.0.0.1", port))


def _record(senders: int) -> Recorder:
    port = free_port(socket.SOCK_DGRAM)
    rec = Recorder()
    rec.watch("truth", f"udpin:127.0.0.1:{port}", is_truth=True)
    socks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(senders)]
    try:
        for k in range(20):
            for i, s in enumerate(socks):
                _send(s, port, 1000 + 20 * k, float(i))
            time.sleep(0.01)
        deadline = time.monotonic() + 5.0
        while rec.counts["truth"] < 20 * senders and time.monotonic() < deadline:
            time.sleep(0.05)
    finally:
        rec.stop()
        for s in socks:
            s.close()
    return rec


def test_one_truth_sender_is_judged_and_a_second_is_noticed() -> None:
    one = _record(1)
    assert one.counts["truth"] == 20 and len(one.truth_senders) == 1
    two = _record(2)
    assert two.counts["truth"] == 40 and len(two.truth_senders) == 2

"""UDP impairment proxy for MAVLink: ``listen`` <-> ``target`` through two :class:`ImpairmentModel` s.

A MAVLink peer (the ground station, ``udpout:``) sends to the proxy's listen port; the proxy forwards to
the target (the companion's ``udpin:`` port) from its own socket, and whatever the target sends back to
that socket goes to the *last* sender seen on the listen port, as a MAVLink UDP server answers its last
client. Each direction has its own model and random stream (both from one seed), so a run is reproducible.
Datagrams from anyone but the target on the target-side socket are ignored (every port is hostile).

One thread owns both sockets and the clock; ``select`` waits until the next release or a packet, at
most ``POLL_S`` (the stop check).
"""

from __future__ import annotations

import logging
import select
import socket
import threading
import time
from collections.abc import Callable

import numpy as np

from harness.netem.model import DelayLine, Impairment, ImpairmentModel, ImpairmentStats
from quadlink.errors import LinkError

log = logging.getLogger(__name__)

POLL_S = 0.05
MAX_DATAGRAM = 65535
MAX_DRAIN = 256   # datagrams read per socket per wake-up (a flood cannot starve the releases)


def stats_line(name: str, s: ImpairmentStats) -> str:
    return (f"{name}: {s.packets_in} in ({s.bytes_in} B), {s.released} out, lost {s.dropped_loss}, "
            f"queue drops {s.dropped_queue}, reordered {s.reordered}, mean delay {s.mean_delay_s * 1e3:.1f} ms")


class UdpProxy:
    """``start()`` runs the proxy in a thread; ``close()`` stops it (also a context manager)."""

    def __init__(self, listen: tuple[str, int], target: tuple[str, int], uplink: Impairment,
                 downlink: Impairment | None = None, seed: int | None = None,
                 clock: Callable[[], float] = time.monotonic, log_period_s: float = 5.0) -> None:
        rng_up, rng_down = (np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(2))
        self.uplink = ImpairmentModel(uplink, rng_up)                            # listen -> target
        self.downlink = ImpairmentModel(downlink if downlink is not None else uplink, rng_down)  # back
        try:
            self.target = (socket.gethostbyname(target[0]), target[1])
        except OSError as exc:
            raise LinkError(f"netem: cannot resolve {target[0]}: {exc}") from exc
        self.clock, self.log_period_s = clock, log_period_s
        self.client: tuple[str, int] | None = None
        self.send_errors = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        try:
            self._listen = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            self._listen.bind(listen)
            self._out = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            self._out.bind((listen[0], 0))
        except OSError as exc:
            self._close_sockets()
            raise LinkError(f"netem: cannot bind udp:{listen[0]}:{listen[1]}: {exc}") from exc
        for s in (self._listen, self._out):
            s.setblocking(False)
        self.listen_address: tuple[str, int] = self._listen.getsockname()

    # ---------------------------------------------------------------- lifecycle
    def start(self) -> UdpProxy:
        self._thread = threading.Thread(target=self.run, name="netem-udp", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self._close_sockets()

    def __enter__(self) -> UdpProxy:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _close_sockets(self) -> None:
        for name in ("_listen", "_out"):
            s = getattr(self, name, None)
            if s is not None:
                s.close()

    # ---------------------------------------------------------------- loop
    def run(self) -> None:
        """Forward until ``close()`` (or the caller's KeyboardInterrupt when run in the foreground)."""
        up_line: DelayLine[bytes] = DelayLine()
        down_line: DelayLine[bytes] = DelayLine()
        log.info("netem udp %s:%d <-> %s:%d", *self.listen_address, *self.target)
        next_log = self.clock() + self.log_period_s
        while not self._stop.is_set():
            due = [t for t in (up_line.next_release_s(), down_line.next_release_s()) if t is not None]
            timeout = POLL_S if not due else min(max(min(due) - self.clock(), 0.0), POLL_S)
            readable, _, _ = select.select([self._listen, self._out], [], [], timeout)
            if self._listen in readable:
                self._drain(self._listen, self.uplink, up_line, from_target=False)
            if self._out in readable:
                self._drain(self._out, self.downlink, down_line, from_target=True)
            now = self.clock()
            for data in up_line.pop_due(now):
                self._send(self._out, data, self.target)
            for data in down_line.pop_due(now):
                if self.client is not None:
                    self._send(self._listen, data, self.client)
            if now >= next_log:
                next_log = now + self.log_period_s
                log.info("%s; %s", stats_line("up", self.uplink.stats), stats_line("down", self.downlink.stats))

    def _drain(self, sock: socket.socket, model: ImpairmentModel, line: DelayLine[bytes], from_target: bool) -> None:
        for _ in range(MAX_DRAIN):
            try:
                data, addr = sock.recvfrom(MAX_DATAGRAM)
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:      # e.g. ICMP port unreachable from an earlier send on Linux
                log.debug("netem: receive error %s", exc)
                return
            if from_target:
                if addr[:2] != self.target:
                    continue
            else:
                self.client = addr[:2]
            release = model.submit(self.clock(), len(data))
            if release is not None:
                line.push(release, data)

    def _send(self, sock: socket.socket, data: bytes, addr: tuple[str, int]) -> None:
        try:
            sock.sendto(data, addr)
        except OSError as exc:          # target not up yet, buffer full: a lost datagram, as on a real link
            self.send_errors += 1
            log.debug("netem: send to %s:%d failed: %s", *addr, exc)

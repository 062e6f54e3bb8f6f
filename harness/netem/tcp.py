"""TCP impairment proxy for byte streams (the operator image stream): delay, jitter and rate on chunks.

Each accepted connection gets its own connection to the target and, per direction, a reader that
stamps every chunk it receives with a release time from an :class:`ImpairmentModel` and a writer that
sends it at that time. The bytes keep their order (the model is FIFO with ``reorder = 0``).

**Loss and reordering do not apply to TCP**: a byte stream cannot lose or swap bytes without breaking
the stream; on a real network TCP retransmits, so loss shows up as stalls (head-of-line blocking), not
as missing data. The proxy refuses ``loss``/``reorder`` for TCP; to see retransmission stalls, impair a
real interface with ``tc netem`` (README). Chunks are what one ``recv`` returned (at most ``CHUNK_BYTES``),
so the delay applies per chunk and the rate limit to the bytes.

Back-pressure: at most ``QUEUE_CHUNKS`` chunks wait per direction; a full queue stops the reader, so a
rate-limited link slows the sender down as TCP would, instead of buffering without bound.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import select
import socket
import threading
import time
from collections.abc import Callable

import numpy as np

from harness.netem.model import Impairment, ImpairmentModel
from harness.netem.udp import stats_line
from quadlink.errors import ConfigError, LinkError

log = logging.getLogger(__name__)

CHUNK_BYTES = 16384
QUEUE_CHUNKS = 32
POLL_S = 0.1


def check_stream_impairment(imp: Impairment) -> None:
    if imp.loss > 0 or imp.reorder > 0:
        raise ConfigError("netem: --loss and --reorder do not apply to a TCP byte stream (TCP retransmits; "
                          "use tc netem on a real interface to see its stalls)")


class _Pipe:
    """One direction of one connection: reader thread -> bounded queue -> writer thread."""

    def __init__(self, name: str, src: socket.socket, dst: socket.socket, model: ImpairmentModel,
                 clock: Callable[[], float], stop: threading.Event, on_done: Callable[[], None]) -> None:
        self.name, self.src, self.dst, self.model = name, src, dst, model
        self.clock, self.stop, self.on_done = clock, stop, on_done
        self.q: queue.Queue[tuple[float, bytes] | None] = queue.Queue(maxsize=QUEUE_CHUNKS)
        self.threads = [threading.Thread(target=self._read, name=f"netem-{name}-r", daemon=True),
                        threading.Thread(target=self._write, name=f"netem-{name}-w", daemon=True)]
        for t in self.threads:
            t.start()

    def _put(self, item: tuple[float, bytes] | None) -> bool:
        while not self.stop.is_set():
            try:
                self.q.put(item, timeout=POLL_S)
                return True
            except queue.Full:
                continue
        return False

    def _read(self) -> None:
        try:
            while not self.stop.is_set():
                readable, _, _ = select.select([self.src], [], [], POLL_S)
                if not readable:
                    continue
                data = self.src.recv(CHUNK_BYTES)
                if not data:
                    break
                release = self.model.submit(self.clock(), len(data))
                if release is not None and not self._put((release, data)):
                    return
        except (OSError, ValueError) as exc:   # ValueError: select on a socket closed by the other side
            log.debug("netem tcp %s: read ended: %s", self.name, exc)
        self._put(None)

    def _write(self) -> None:
        try:
            while not self.stop.is_set():
                try:
                    item = self.q.get(timeout=POLL_S)
                except queue.Empty:
                    continue
                if item is None:
                    with contextlib.suppress(OSError):
                        self.dst.shutdown(socket.SHUT_WR)   # pass the end of stream on, after the data
                    return
                release, data = item
                wait = release - self.clock()
                if wait > 0 and self.stop.wait(wait):
                    return
                self.dst.sendall(data)
        except OSError as exc:
            log.debug("netem tcp %s: write ended: %s", self.name, exc)
        finally:
            self.on_done()


class TcpProxy:
    """Accepts on ``listen``, connects each client to ``target``; ``start()`` / ``close()``."""

    def __init__(self, listen: tuple[str, int], target: tuple[str, int], uplink: Impairment,
                 downlink: Impairment | None = None, seed: int | None = None,
                 clock: Callable[[], float] = time.monotonic, log_period_s: float = 5.0,
                 connect_timeout_s: float = 5.0) -> None:
        self.up_cfg = uplink
        self.down_cfg = downlink if downlink is not None else uplink
        check_stream_impairment(self.up_cfg)
        check_stream_impairment(self.down_cfg)
        self.target, self.clock, self.log_period_s = target, clock, log_period_s
        self.connect_timeout_s = connect_timeout_s
        self._seeds = np.random.SeedSequence(seed)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()
        self.connections: list[tuple[socket.socket, socket.socket, ImpairmentModel, ImpairmentModel]] = []
        self._pipes: list[_Pipe] = []
        try:
            self._server = socket.create_server(listen, reuse_port=False)
        except OSError as exc:
            raise LinkError(f"netem: cannot listen on tcp:{listen[0]}:{listen[1]}: {exc}") from exc
        self.listen_address: tuple[str, int] = self._server.getsockname()[:2]

    def start(self) -> TcpProxy:
        self._thread = threading.Thread(target=self.run, name="netem-tcp", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        with self._lock:
            for a, b, _, _ in self.connections:
                a.close()
                b.close()
            pipes = list(self._pipes)
        for p in pipes:
            for t in p.threads:
                t.join(timeout=1.0)
        self._server.close()

    def __enter__(self) -> TcpProxy:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def run(self) -> None:
        log.info("netem tcp %s:%d -> %s:%d (delay/jitter/rate per chunk; no loss on TCP)",
                 *self.listen_address, *self.target)
        next_log = self.clock() + self.log_period_s
        while not self._stop.is_set():
            readable, _, _ = select.select([self._server], [], [], POLL_S)
            if readable:
                self._accept()
            if self.clock() >= next_log:
                next_log = self.clock() + self.log_period_s
                with self._lock:
                    for i, (_, _, up, down) in enumerate(self.connections):
                        log.info("connection %d: %s; %s", i, stats_line("up", up.stats),
                                 stats_line("down", down.stats))

    def _accept(self) -> None:
        try:
            client, addr = self._server.accept()
        except OSError:
            return
        try:
            server = socket.create_connection(self.target, timeout=self.connect_timeout_s)
        except OSError as exc:
            log.warning("netem tcp: %s:%d connected but target %s:%d refused: %s", *addr[:2], *self.target, exc)
            client.close()
            return
        server.settimeout(None)
        for s in (client, server):
            s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        rng_up, rng_down = (np.random.default_rng(s) for s in self._seeds.spawn(2))
        up, down = ImpairmentModel(self.up_cfg, rng_up), ImpairmentModel(self.down_cfg, rng_down)
        closing = {"n": 0}

        def on_done() -> None:         # both directions finished (or one failed): close the pair
            with self._lock:
                closing["n"] += 1
                if closing["n"] == 2:
                    client.close()
                    server.close()

        with self._lock:
            self.connections.append((client, server, up, down))
            n = len(self.connections)
            self._pipes.append(_Pipe(f"{n}-up", client, server, up, self.clock, self._stop, on_done))
            self._pipes.append(_Pipe(f"{n}-down", server, client, down, self.clock, self._stop, on_done))
        log.info("netem tcp: connection %d from %s:%d", n, *addr[:2])

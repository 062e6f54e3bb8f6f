"""The bridge process's links and the threads that read them (the daemon's I/O edge).

:class:`StreamHolder` is an MK serial/TCP byte stream that its reader may reopen after a link error; writes go
to the current stream. :class:`LinkReaders` runs one thread per link (MK port 1, MK port 2, each MAVLink
endpoint): each only reads, with a timeout, and puts what it got on the daemon's queue, so the daemon's main
thread does all decoding, control and writing (:mod:`firmware_bridge.daemon`). Every wait has a timeout and
ends when the daemon's stop event is set.

What leaves is counted for the deterministic lock-step (:mod:`quadlink.lockstep`), whose participants report
how many units they have sent on each link: :attr:`StreamHolder.bytes_written` (MK port 1) and
:class:`SentDatagrams` (a MAVLink endpoint).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Any

from quadlink.errors import LinkError
from quadlink.links import ByteStream

log = logging.getLogger("firmware_bridge.daemon")

MK_READ_SIZE = 4096
MAVLINK_READ_SIZE = 65535
READ_TIMEOUT_S = 0.1  # every read and select waits at most this, so a stop is seen within it


class StreamHolder:
    """A byte stream that a reader thread may reopen after a link error; writes go to the current one."""

    def __init__(self, url: str, opener: Callable[[str], ByteStream]) -> None:
        self.url = url
        self._opener = opener
        self._lock = threading.Lock()
        self.stream: ByteStream | None = opener(url)
        # bytes handed to a stream whose write succeeded, over every (re)opened stream: the lock-step's count
        # of what this process sent on the link (only the daemon's main thread writes)
        self.bytes_written = 0

    def write(self, data: bytes) -> bool:
        with self._lock:
            stream = self.stream
        if stream is None:
            return False
        try:
            stream.write(data)
        except LinkError as exc:
            log.warning("%s", exc)
            return False
        self.bytes_written += len(data)
        return True

    def reopen(self) -> bool:
        try:
            stream = self._opener(self.url)
        except LinkError:
            return False
        with self._lock:
            self.stream = stream
        return True

    def drop(self) -> None:
        with self._lock:
            stream, self.stream = self.stream, None
        if stream is not None:
            stream.close()


class LinkReaders:
    """The reader threads. What they put on the queue (``put``):

    * ``("cmd" | "imu", bytes, read_wall_s)``: MK bytes and the wall time they were read;
    * ``("link", "cmd" | "imu", text)``: an MK link error, or ``"<url>: reconnected"``;
    * ``("mav", index, bytes)``: raw MAVLink bytes from endpoint ``index``;
    * ``("mavbad", index, text)``: a MAVLink endpoint's read error.
    """

    def __init__(self, put: Callable[[tuple[Any, ...]], None], stop: threading.Event, clock: Callable[[], float],
                 reconnect_interval_s: float) -> None:
        self._put = put
        self._stop = stop
        self._clock = clock
        self._reconnect_interval_s = reconnect_interval_s

    def start(self, cmd: StreamHolder, imu: StreamHolder, mavlinks: list[Any]) -> list[threading.Thread]:
        """One daemon thread per link, started; the caller joins them after setting ``stop``."""
        threads = [threading.Thread(target=self.read_mk, args=("cmd", cmd), daemon=True, name="mk-cmd"),
                   threading.Thread(target=self.read_mk, args=("imu", imu), daemon=True, name="mk-imu")]
        for i, conn in enumerate(mavlinks):
            threads.append(threading.Thread(target=self.read_mavlink, args=(i, conn), daemon=True,
                                            name=f"mavlink-{i}"))
        for t in threads:
            t.start()
        return threads

    def read_mk(self, kind: str, holder: StreamHolder) -> None:
        while not self._stop.is_set():
            stream = holder.stream
            if stream is None:
                if self._stop.wait(self._reconnect_interval_s):
                    return
                if holder.reopen():
                    self._put(("link", kind, f"{holder.url}: reconnected"))
                continue
            try:
                data = stream.read(MK_READ_SIZE, READ_TIMEOUT_S)
            except LinkError as exc:
                self._put(("link", kind, str(exc)))
                holder.drop()
                continue
            if data:
                self._put((kind, data, self._clock()))

    def read_mavlink(self, index: int, conn: Any) -> None:
        # Raw bytes only: pymavlink's MAVLink object is not thread-safe (a parse in this thread while the
        # main thread packs a message loses messages), so all parsing and packing happen in the main thread.
        while not self._stop.is_set():
            try:
                if not conn.select(READ_TIMEOUT_S):
                    continue
                data = conn.recv(MAVLINK_READ_SIZE)
            except (OSError, ValueError) as exc:  # a dead socket or a closed serial port
                self._put(("mavbad", index, str(exc)))
                self._stop.wait(READ_TIMEOUT_S)
                continue
            if data:
                self._put(("mav", index, bytes(data)))


class SentDatagrams:
    """Counts the datagrams a pymavlink endpoint sends (the lock-step's ``bridge>companion``).

    Only ``write`` is wrapped: the endpoint's reader thread calls ``recv``, and the datagrams received are
    counted off the daemon's queue by the main thread instead (:class:`firmware_bridge.step_inputs.StepInputs`).
    One ``write`` is one datagram (``mav.send`` writes a packet at a time), unless nothing leaves: a ``udpin``
    endpoint that has no client yet sends nothing. pymavlink 2.4's ``mavudp`` keeps a ``udpin``'s peers in
    ``clients`` (``last_address`` stays None on a server socket).
    """

    def __init__(self, conn: Any) -> None:
        self.conn = conn
        self.count = 0
        self._write = conn.write
        conn.write = self.write

    def write(self, buf: bytes) -> Any:
        conn = self.conn
        has_peer = not getattr(conn, "udp_server", False) or bool(getattr(conn, "clients", None)) \
            or getattr(conn, "last_address", None) is not None
        result = self._write(buf)
        if has_peer:
            self.count += 1
        return result

"""The local camera stream over TCP (SITL -> companion, companion -> operator view): a server that publishes
camera records (:mod:`quadlink.camera_record`) to every client, and a client that reads them.

One direction carries records, the other acknowledgements::

    ack     = uint32 LE seq   (consumer -> producer, after the frame has been processed)

A producer in lock-step waits for the acks (:meth:`CameraStreamServer.wait_acks`) so simulated time never
outruns the consumers.
"""

from __future__ import annotations

import logging
import socket
import struct
import threading
import time
from collections.abc import Callable

from quadlink.camera_frame import RgbdFrame
from quadlink.camera_record import RecordDecoder, encode_record
from quadlink.errors import LinkError, ProtocolError

__all__ = ["CameraStreamClient", "CameraStreamServer", "parse_tcp_url"]

log = logging.getLogger(__name__)

_ACK = struct.Struct("<I")


class _Client:
    def __init__(self, sock: socket.socket, address: str) -> None:
        self.sock = sock
        self.address = address
        self.last_ack = -1
        self.alive = True


class CameraStreamServer:
    """Publishes frames to every connected client; collects their acks for lock-step.

    ``publish`` sends with a bounded wait: a client that cannot take a frame within
    ``send_timeout_s`` is disconnected (logged), so one stuck viewer cannot stall the producer.
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 5762, send_timeout_s: float = 2.0) -> None:
        self._listener = socket.create_server((host, port), reuse_port=False)
        self._listener.settimeout(0.2)
        self.host, self.port = self._listener.getsockname()[:2]
        self._send_timeout_s = send_timeout_s
        self._clients: list[_Client] = []
        self._cond = threading.Condition()
        self._closed = False
        self.frames_published = 0
        self._accept_thread = threading.Thread(target=self._accept_loop, name="camera-accept", daemon=True)
        self._accept_thread.start()
        log.info("camera stream on tcp://%s:%d", self.host, self.port)

    @property
    def client_count(self) -> int:
        with self._cond:
            return sum(c.alive for c in self._clients)

    def _accept_loop(self) -> None:
        while not self._closed:
            try:
                sock, addr = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            sock.settimeout(self._send_timeout_s)
            client = _Client(sock, f"{addr[0]}:{addr[1]}")
            with self._cond:
                self._clients.append(client)
                self._cond.notify_all()
            log.info("camera stream client %s connected", client.address)
            threading.Thread(target=self._ack_loop, args=(client,), name="camera-acks", daemon=True).start()

    def _ack_loop(self, client: _Client) -> None:
        buf = b""
        while client.alive and not self._closed:
            try:
                chunk = client.sock.recv(64)
            except TimeoutError:
                continue
            except OSError:
                chunk = b""
            if not chunk:
                break
            buf += chunk
            while len(buf) >= _ACK.size:
                (seq,) = _ACK.unpack_from(buf)
                buf = buf[_ACK.size:]
                with self._cond:
                    client.last_ack = max(client.last_ack, seq)
                    self._cond.notify_all()
        self._drop(client, "disconnected")

    def _drop(self, client: _Client, reason: str) -> None:
        with self._cond:
            if not client.alive:
                return
            client.alive = False
            self._clients = [c for c in self._clients if c is not client]
            self._cond.notify_all()
        try:
            client.sock.close()
        except OSError:
            pass
        log.info("camera stream client %s %s", client.address, reason)

    def publish(self, frame: RgbdFrame, rgb_jpeg: bool = False) -> int:
        """Send the frame to every client; returns how many received it."""
        return self.publish_record(encode_record(frame, rgb_jpeg=rgb_jpeg))

    def publish_record(self, record: bytes) -> int:
        """Send an already encoded record (:func:`encode_record`) to every client."""
        with self._cond:
            clients = list(self._clients)
        sent = 0
        for client in clients:
            try:
                client.sock.sendall(record)
                sent += 1
            except OSError as exc:
                self._drop(client, f"dropped ({exc})")
        self.frames_published += 1
        return sent

    def wait_acks(self, seq: int, timeout_s: float) -> bool:
        """Block until every connected client acked ``seq`` (or left); False on timeout."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while any(c.alive and c.last_ack < seq for c in self._clients):
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return False
                self._cond.wait(remaining)
        return True

    def wait_for_client(self, timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while not any(c.alive for c in self._clients):
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return False
                self._cond.wait(remaining)
        return True

    def close(self) -> None:
        self._closed = True
        try:
            self._listener.close()
        except OSError:
            pass
        with self._cond:
            clients = list(self._clients)
        for client in clients:
            self._drop(client, "closed")
        self._accept_thread.join(timeout=1.0)


def parse_tcp_url(url: str) -> tuple[str, int]:
    """``tcp://HOST:PORT`` -> (HOST, PORT); LinkError otherwise."""
    if not url.startswith("tcp://"):
        raise LinkError(f"{url}: camera stream URL must look like tcp://HOST:PORT")
    host, sep, port = url[len("tcp://"):].rpartition(":")
    if not sep or not port.isdigit():
        raise LinkError(f"{url}: camera stream URL must look like tcp://HOST:PORT")
    return host, int(port)


class CameraStreamClient:
    """Reads frames from a :class:`CameraStreamServer`; acks each processed frame.

    Connects lazily and reconnects after errors, so a consumer started before the producer
    just waits (``read`` returns None until frames flow).
    """

    def __init__(self, url: str = "tcp://127.0.0.1:5762", clock: Callable[[], float] = time.monotonic) -> None:
        self.url = url
        self.host, self.port = parse_tcp_url(url)
        self._clock = clock
        self._sock: socket.socket | None = None
        self._decoder = RecordDecoder()
        # one receive buffer for the stream's life: a fresh 256 kB bytes object per recv costs an mmap and its
        # page faults each time (about as much CPU as decoding the frame)
        self._rx = memoryview(bytearray(1 << 18))
        self._pending: list[RgbdFrame] = []
        self.frames_received = 0
        self.frames_skipped = 0
        self.errors = 0

    def _connect(self) -> bool:
        try:
            sock = socket.create_connection((self.host, self.port), timeout=0.5)
        except OSError:
            return False
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._sock = sock
        self._decoder = RecordDecoder()
        log.info("camera stream %s connected", self.url)
        return True

    def _disconnect(self, reason: str) -> None:
        if self._sock is not None:
            log.warning("camera stream %s: %s; reconnecting", self.url, reason)
            try:
                self._sock.close()
            except OSError:
                pass
        self._sock = None

    @property
    def connected(self) -> bool:
        return self._sock is not None

    def read(self, timeout_s: float, newest: bool = False) -> RgbdFrame | None:
        """The next frame, or None if none arrived within ``timeout_s``. ``newest``: the newest frame already
        received (whatever else is waiting in the socket is read too), the older ones dropped and counted in
        ``frames_skipped``: a consumer that fell behind processes the present, never a backlog."""
        frame = self._read_next(timeout_s)
        if frame is None or not newest:
            return frame
        self._drain()
        if self._pending:
            self.frames_skipped += len(self._pending)
            self.frames_received += len(self._pending)
            frame = self._pending[-1]
            self._pending.clear()
        return frame

    def _drain(self) -> None:
        """Decode whatever the socket holds now, without waiting."""
        sock = self._sock
        if sock is None:
            return
        sock.settimeout(0.0)
        try:
            while True:
                try:
                    n = sock.recv_into(self._rx)
                except (BlockingIOError, TimeoutError):
                    return
                if not n:
                    self._disconnect("closed by the producer")
                    return
                self._pending.extend(self._decoder.feed(self._rx[:n]))
        except ProtocolError as exc:
            self.errors += 1
            self._disconnect(str(exc))
        except OSError as exc:
            self._disconnect(str(exc))

    def _read_next(self, timeout_s: float) -> RgbdFrame | None:
        deadline = self._clock() + timeout_s
        while not self._pending:
            remaining = deadline - self._clock()
            if remaining <= 0:
                return None
            if self._sock is None and not self._connect():
                time.sleep(min(0.1, max(remaining, 0.0)))
                continue
            assert self._sock is not None
            self._sock.settimeout(max(min(remaining, 0.5), 1e-3))
            try:
                n = self._sock.recv_into(self._rx)
            except TimeoutError:
                continue
            except OSError as exc:
                self._disconnect(str(exc))
                continue
            if not n:
                self._disconnect("closed by the producer")
                continue
            try:
                self._pending.extend(self._decoder.feed(self._rx[:n]))
            except ProtocolError as exc:
                self.errors += 1
                self._disconnect(str(exc))
        self.frames_received += 1
        return self._pending.pop(0)

    def ack(self, seq: int) -> None:
        if self._sock is None:
            return
        try:
            self._sock.sendall(_ACK.pack(seq & 0xFFFFFFFF))
        except OSError as exc:
            self._disconnect(f"ack failed: {exc}")

    def close(self) -> None:
        if self._sock is not None:
            try:
                self._sock.close()
            except OSError:
                pass
            self._sock = None

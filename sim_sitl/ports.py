"""The SITL's endpoints (the only sockets of the SITL): the two MK serial ports, the camera stream, ground truth.

A :class:`SerialPort` is a serial port's far end: a TCP listener (and optionally a pty) whose clients all
share the line, served with non-blocking sockets. :class:`SitlPorts` owns the four endpoints and waits on
the serial ports' descriptors (``poll``); it never steps the simulation and never reads a clock.
"""

from __future__ import annotations

import logging
import os
import select
import socket
import tty
from dataclasses import dataclass

from quadlink.camera import CameraStreamServer
from quadlink.errors import LinkError
from sim_sitl.truth import UdpTruthSink

log = logging.getLogger(__name__)

MAX_CLIENT_BACKLOG_BYTES = 1 << 18


class _Conn:
    def __init__(self, sock: socket.socket | None, fd: int, name: str) -> None:
        self.sock = sock
        self.fd = fd
        self.name = name
        self.out = bytearray()
        self.alive = True

    def fileno(self) -> int:
        return self.fd


class SerialPort:
    """A serial port's far end: TCP listener (+ optional pty), all clients share the line."""

    def __init__(self, label: str, host: str, port: int, use_pty: bool) -> None:
        self.label = label
        try:
            self.listener = socket.create_server((host, port))
        except OSError as exc:
            raise LinkError(f"{label}: cannot listen on tcp {host}:{port}: {exc}") from exc
        self.listener.setblocking(False)
        self.address = self.listener.getsockname()[:2]
        self.conns: list[_Conn] = []
        self.pty_path: str | None = None
        self._pty_slave: int | None = None
        self.bytes_dropped = 0
        if use_pty:
            master, slave = os.openpty()
            tty.setraw(slave)
            os.set_blocking(master, False)
            self._pty_slave = slave
            self.pty_path = os.ttyname(slave)
            self.conns.append(_Conn(None, master, f"pty {self.pty_path}"))

    @property
    def url(self) -> str:
        return f"socket://{self.address[0]}:{self.address[1]}"

    @property
    def tcp_client_count(self) -> int:
        return sum(1 for c in self.conns if c.sock is not None and c.alive)

    @property
    def has_peer(self) -> bool:
        """A TCP client is connected or the pty is open (a pty peer cannot be detected)."""
        return self.tcp_client_count > 0 or self.pty_path is not None

    def accept(self) -> None:
        while True:
            try:
                sock, addr = self.listener.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                return
            sock.setblocking(False)
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self.conns.append(_Conn(sock, sock.fileno(), f"{addr[0]}:{addr[1]}"))
            log.info("%s: client %s connected", self.label, f"{addr[0]}:{addr[1]}")

    def write(self, data: bytes) -> None:
        """Queue ``data`` for every client and send what the sockets take now."""
        for c in self.conns:
            if not c.alive:
                continue
            c.out += data
            self._flush(c)

    def flush(self) -> None:
        """Send what is still queued for slow clients (also while the simulation waits)."""
        for c in self.conns:
            if c.alive and c.out:
                self._flush(c)

    def _flush(self, c: _Conn) -> None:
        if not c.out:
            return
        try:
            n = c.sock.send(c.out) if c.sock is not None else os.write(c.fd, c.out)
            del c.out[:n]
        except (BlockingIOError, InterruptedError):
            pass
        except OSError as exc:
            if c.sock is not None:
                self._drop(c, f"send failed: {exc}")
            else:
                c.out.clear()  # pty with nobody reading: bytes fall on the floor as on a wire
        if len(c.out) > MAX_CLIENT_BACKLOG_BYTES:
            if c.sock is not None:
                self._drop(c, "not reading (backlog full)")
            else:
                self.bytes_dropped += len(c.out)
                c.out.clear()

    def _drop(self, c: _Conn, why: str) -> None:
        c.alive = False
        log.info("%s: client %s disconnected (%s)", self.label, c.name, why)
        if c.sock is not None:
            c.sock.close()

    def read_all(self, readable: set[int] | None = None) -> bytes:
        """Bytes from every client (only those in ``readable`` when given, as reported by select)."""
        data = bytearray()
        for c in self.conns:
            if not c.alive or (readable is not None and c.fd not in readable):
                continue
            while True:
                try:
                    chunk = c.sock.recv(4096) if c.sock is not None else os.read(c.fd, 4096)
                except (BlockingIOError, InterruptedError):
                    break
                except OSError as exc:
                    if c.sock is not None:
                        self._drop(c, str(exc))
                    break
                if not chunk:
                    if c.sock is not None:
                        self._drop(c, "closed by peer")
                    break
                data += chunk
        self.conns = [c for c in self.conns if c.alive]
        return bytes(data)

    def fds(self) -> list[int]:
        return [self.listener.fileno()] + [c.fd for c in self.conns if c.alive]

    def close(self) -> None:
        for c in self.conns:
            if c.sock is not None:
                c.sock.close()
            else:
                os.close(c.fd)
        self.conns = []
        if self._pty_slave is not None:
            os.close(self._pty_slave)
            self._pty_slave = None
        self.listener.close()


@dataclass(frozen=True)
class SerialInput:
    """What the MK ports' clients sent since the last poll (port 2 is the IMU port: its input is discarded)."""

    port1: bytes = b""
    port2_bytes: int = 0


class SitlPorts:
    """The SITL's endpoints: MK port 1 (commands/telemetry), MK port 2 (IMU), camera stream, truth sink."""

    def __init__(self, host: str, port1: int, port2: int, use_pty: bool, camera_port: int | None,
                 truth_url: str | None) -> None:
        self.camera: CameraStreamServer | None = None
        self.truth: UdpTruthSink | None = None
        self._serial: list[SerialPort] = []
        try:
            self.port1 = SerialPort("port 1", host, port1, use_pty)
            self._serial.append(self.port1)
            self.port2 = SerialPort("port 2", host, port2, use_pty)
            self._serial.append(self.port2)
            if camera_port is not None:
                try:
                    self.camera = CameraStreamServer(host, camera_port)
                except OSError as exc:
                    raise LinkError(f"camera stream: cannot listen on tcp {host}:{camera_port}: {exc}") from exc
            if truth_url:
                self.truth = UdpTruthSink(truth_url)
        except BaseException:
            self.close()
            raise

    @property
    def endpoints(self) -> dict[str, str]:
        ep = {"port1": self.port1.url, "port2": self.port2.url}
        if self.port1.pty_path:
            ep["port1_pty"] = self.port1.pty_path
            ep["port2_pty"] = self.port2.pty_path or ""
        if self.camera is not None:
            ep["camera"] = f"tcp://{self.camera.host}:{self.camera.port}"
        if self.truth is not None:
            ep["truth"] = self.truth.url
        return ep

    @property
    def camera_client_count(self) -> int:
        return self.camera.client_count if self.camera is not None else 0

    def write_serial(self, port1_bytes: bytes, port2_bytes: bytes) -> None:
        if port2_bytes:
            self.port2.write(port2_bytes)
        if port1_bytes:
            self.port1.write(port1_bytes)

    def poll(self, timeout_s: float = 0.0) -> SerialInput:
        """Wait up to ``timeout_s`` for serial input; accept clients, flush backlogs, read what arrived."""
        for port in self._serial:
            port.flush()
        fds = [fd for port in self._serial for fd in port.fds()]
        if not fds:  # closed
            return SerialInput()
        try:
            readable = set(select.select(fds, [], [], max(0.0, timeout_s))[0])
        except (OSError, ValueError):  # a descriptor closed under us: look at everything once
            readable = set(fds)
        if not readable:
            return SerialInput()
        for port in self._serial:
            if port.listener.fileno() in readable:
                port.accept()
        discarded = self.port2.read_all(readable)
        return SerialInput(self.port1.read_all(readable), len(discarded))

    def close(self) -> None:
        for port in self._serial:
            port.close()
        self._serial = []
        if self.camera is not None:
            self.camera.close()
            self.camera = None
        if self.truth is not None:
            self.truth.close()
            self.truth = None

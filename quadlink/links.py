"""Byte-stream links chosen by URL (STYLE.md rule 6): the MK board's serial ports, real or simulated.

========================  ==============================================================
URL                       link
========================  ==============================================================
``/dev/ttyUSB0:115200``   serial device at the given baud (8N1); ``/dev/ttyUSB0`` = 115200
``socket://HOST:PORT``    TCP client (the SITL's ports; pyserial's URL syntax)
``pty``                   a new pseudo-terminal; ``.name`` is the slave path for serial users
========================  ==============================================================

MAVLink endpoints use pymavlink's own URL syntax instead: see :mod:`quadlink.mavlink.connection`.
"""

from __future__ import annotations

import os
import select
import socket
import termios
import tty
from typing import Protocol

import serial

from quadlink.errors import LinkError

DEFAULT_BAUD = 115200


class ByteStream(Protocol):
    """A bidirectional byte stream with bounded waits."""

    name: str

    def read(self, max_bytes: int, timeout_s: float) -> bytes:
        """Up to ``max_bytes`` bytes; ``b''`` when nothing arrived within ``timeout_s``."""
        ...

    def write(self, data: bytes) -> None: ...

    def close(self) -> None: ...


class SerialStream:
    """A pyserial port: a device or a ``socket://`` URL."""

    def __init__(self, port: serial.SerialBase, name: str) -> None:
        self._port = port
        self.name = name

    def read(self, max_bytes: int, timeout_s: float) -> bytes:
        try:
            self._port.timeout = timeout_s
            first = self._port.read(1)
            if not first:
                return b""
            waiting = self._port.in_waiting
            rest = self._port.read(min(waiting, max_bytes - 1)) if waiting and max_bytes > 1 else b""
            return first + rest
        except (serial.SerialException, OSError) as exc:
            raise LinkError(f"{self.name}: read failed: {exc}") from exc

    def write(self, data: bytes) -> None:
        try:
            self._port.write(data)
        except (serial.SerialException, OSError) as exc:
            raise LinkError(f"{self.name}: write failed: {exc}") from exc

    def close(self) -> None:
        self._port.close()


class TcpStream:
    """A TCP client (``socket://HOST:PORT``, the URL form pyserial users know)."""

    def __init__(self, url: str) -> None:
        host, sep, port = url[len("socket://"):].rpartition(":")
        if not sep or not port.isdigit():
            raise LinkError(f"{url}: expected socket://HOST:PORT")
        try:
            self._sock = socket.create_connection((host, int(port)), timeout=2.0)
        except OSError as exc:
            raise LinkError(f"{url}: cannot open: {exc}") from exc
        self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.name = url

    def read(self, max_bytes: int, timeout_s: float) -> bytes:
        try:
            self._sock.settimeout(max(timeout_s, 1e-4))
            data = self._sock.recv(max_bytes)
        except TimeoutError:
            return b""
        except OSError as exc:
            raise LinkError(f"{self.name}: read failed: {exc}") from exc
        if not data:
            raise LinkError(f"{self.name}: connection closed by the peer")
        return data

    def write(self, data: bytes) -> None:
        try:
            self._sock.settimeout(2.0)
            self._sock.sendall(data)
        except OSError as exc:
            raise LinkError(f"{self.name}: write failed: {exc}") from exc

    def close(self) -> None:
        try:
            self._sock.close()
        except OSError:
            pass


class PtyStream:
    """The master side of a new pseudo-terminal; a serial-port user opens :attr:`name`."""

    def __init__(self) -> None:
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        attrs = termios.tcgetattr(self._slave)
        attrs[3] &= ~termios.ECHO
        termios.tcsetattr(self._slave, termios.TCSANOW, attrs)
        self.name = os.ttyname(self._slave)

    def read(self, max_bytes: int, timeout_s: float) -> bytes:
        ready, _, _ = select.select([self._master], [], [], timeout_s)
        if not ready:
            return b""
        try:
            return os.read(self._master, max_bytes)
        except OSError as exc:  # EIO once the slave side is gone
            raise LinkError(f"{self.name}: read failed: {exc}") from exc

    def write(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            _, ready, _ = select.select([], [self._master], [], 1.0)
            if not ready:
                raise LinkError(f"{self.name}: write timed out (reader not draining)")
            view = view[os.write(self._master, view):]

    def close(self) -> None:
        for fd in (self._master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass


def parse_serial_url(url: str) -> tuple[str, int]:
    """``/dev/ttyUSB0:57600`` -> (``/dev/ttyUSB0``, 57600); no baud -> 115200."""
    device, sep, baud_text = url.rpartition(":")
    if sep and baud_text.isdigit():
        return device, int(baud_text)
    return url, DEFAULT_BAUD


def open_stream(url: str) -> ByteStream:
    """Open the byte stream named by ``url`` (see module doc); :class:`LinkError` says why not."""
    if url == "pty" or url.startswith("pty:"):
        return PtyStream()
    try:
        if url.startswith("socket://"):
            return TcpStream(url)
        if "://" in url:
            raise LinkError(f"{url}: unsupported link URL (use /dev/DEVICE[:BAUD], socket://HOST:PORT or pty)")
        device, baud = parse_serial_url(url)
        return SerialStream(serial.Serial(device, baudrate=baud, timeout=0.1), url)
    except (serial.SerialException, OSError, ValueError) as exc:
        raise LinkError(f"{url}: cannot open: {exc}") from exc

"""Byte-stream links by URL: pty, socket:// and the errors users see."""

from __future__ import annotations

import socket
import threading

import pytest
import serial

from quadlink.errors import LinkError
from quadlink.links import open_stream, parse_serial_url


def test_pty_carries_bytes_both_ways_to_a_serial_user() -> None:
    link = open_stream("pty")
    try:
        user = serial.Serial(link.name, 115200, timeout=1.0)
        user.write(b"#bv@x\r")
        received = b""
        while len(received) < 6:
            chunk = link.read(64, 1.0)
            assert chunk, "pty delivered nothing"
            received += chunk
        assert received == b"#bv@x\r"
        link.write(b"\x00\x01binary\xff")
        assert user.read(9) == b"\x00\x01binary\xff"
        assert link.read(64, 0.05) == b""  # timeout, no data
        user.close()
    finally:
        link.close()


def test_socket_url_reaches_a_tcp_server() -> None:
    server = socket.create_server(("127.0.0.1", 0))
    port = server.getsockname()[1]

    def serve() -> None:
        conn, _ = server.accept()
        conn.sendall(conn.recv(16).upper())
        conn.close()

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    link = open_stream(f"socket://127.0.0.1:{port}")
    try:
        link.write(b"hello")
        data = b""
        while len(data) < 5:
            data += link.read(16, 1.0)
        assert data == b"HELLO"
    finally:
        link.close()
        server.close()
        thread.join(timeout=1)


def test_errors_name_the_url() -> None:
    with pytest.raises(LinkError, match="/dev/ttyNOSUCH"):
        open_stream("/dev/ttyNOSUCH:115200")
    with pytest.raises(LinkError, match="unsupported link URL"):
        open_stream("http://127.0.0.1:1")
    closed = socket.create_server(("127.0.0.1", 0))
    port = closed.getsockname()[1]
    closed.close()
    with pytest.raises(LinkError, match="cannot open"):
        open_stream(f"socket://127.0.0.1:{port}")


def test_parse_serial_url() -> None:
    assert parse_serial_url("/dev/ttyUSB0:57600") == ("/dev/ttyUSB0", 57600)
    assert parse_serial_url("/dev/ttyUSB0") == ("/dev/ttyUSB0", 115200)

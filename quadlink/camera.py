"""RGB-D frames and the local camera stream (SITL -> companion, companion -> operator view).

Wire format (TCP, one direction of records, the other of acknowledgements)::

    record  = b"QLCF" | uint32 LE header_len | header (UTF-8 JSON) | rgb bytes | depth bytes
    header  = {"seq", "stamp_s", "width", "height", "intrinsics": {fx, fy, cx, cy},
               "R_qc": 3x3 rows, "p_qc_m": [x, y, z],
               "rgb_encoding": "rgb8" | "jpeg", "rgb_bytes": n, "depth_encoding": "mm_u16le" | "none",
               "depth_bytes": n, "meta": {...}}
    ack     = uint32 LE seq   (consumer -> producer, after the frame has been processed)

Colour is RGB8 row-major (or JPEG); depth is uint16 little-endian millimetres, 0 = invalid. A
producer in lock-step waits for the acks (:meth:`CameraStreamServer.wait_acks`) so simulated time never
outruns the consumers.
"""

from __future__ import annotations

import json
import logging
import math
import socket
import struct
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from quadlink.errors import LinkError, ProtocolError

log = logging.getLogger(__name__)

MAGIC = b"QLCF"
_PREFIX = struct.Struct("<4sI")
_ACK = struct.Struct("<I")
MAX_HEADER_BYTES = 1 << 20
MAX_PAYLOAD_BYTES = 64 << 20


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics in pixels for an image of ``width`` x ``height``."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @classmethod
    def from_fov(cls, width: int, height: int, hfov_deg: float, vfov_deg: float) -> CameraIntrinsics:
        fx = (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
        fy = (height / 2.0) / math.tan(math.radians(vfov_deg) / 2.0)
        return cls(fx, fy, (width - 1) / 2.0, (height - 1) / 2.0, width, height)

    def matrix(self) -> NDArray[np.float64]:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def scaled(self, factor: float) -> CameraIntrinsics:
        """Intrinsics of the image resized by ``factor`` (pyramid levels)."""
        return CameraIntrinsics(self.fx * factor, self.fy * factor, (self.cx + 0.5) * factor - 0.5,
                                (self.cy + 0.5) * factor - 0.5, round(self.width * factor),
                                round(self.height * factor))


@dataclass(frozen=True)
class RgbdFrame:
    """One RGB-D frame. ``depth_m`` is float32 metres with 0 for invalid; ``R_qc`` maps camera to body."""

    seq: int
    stamp_s: float
    rgb: NDArray[np.uint8]
    depth_m: NDArray[np.float32] | None
    intrinsics: CameraIntrinsics
    R_qc: NDArray[np.float64] = field(default_factory=lambda: np.eye(3))
    p_qc_m: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    meta: dict[str, Any] = field(default_factory=dict)


def encode_record(frame: RgbdFrame, rgb_jpeg: bool = False, jpeg_quality: int = 85) -> bytes:
    """Serialise a frame into one stream record (see module doc)."""
    if rgb_jpeg:
        ok, buf = cv2.imencode(".jpg", cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2BGR),
                               [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality])
        if not ok:
            raise ProtocolError("JPEG encoding of the colour image failed")
        rgb_bytes = buf.tobytes()
    else:
        rgb_bytes = np.ascontiguousarray(frame.rgb, dtype=np.uint8).tobytes()
    if frame.depth_m is not None:
        depth_mm = np.clip(np.nan_to_num(frame.depth_m, nan=0.0) * 1000.0 + 0.5, 0, 65535).astype("<u2")
        depth_bytes = depth_mm.tobytes()
    else:
        depth_bytes = b""
    k = frame.intrinsics
    header = {
        "seq": int(frame.seq),
        "stamp_s": float(frame.stamp_s),
        "width": int(k.width),
        "height": int(k.height),
        "intrinsics": {"fx": k.fx, "fy": k.fy, "cx": k.cx, "cy": k.cy},
        "R_qc": np.asarray(frame.R_qc, dtype=float).tolist(),
        "p_qc_m": np.asarray(frame.p_qc_m, dtype=float).tolist(),
        "rgb_encoding": "jpeg" if rgb_jpeg else "rgb8",
        "rgb_bytes": len(rgb_bytes),
        "depth_encoding": "mm_u16le" if depth_bytes else "none",
        "depth_bytes": len(depth_bytes),
        "meta": frame.meta,
    }
    header_bytes = json.dumps(header, separators=(",", ":")).encode()
    return _PREFIX.pack(MAGIC, len(header_bytes)) + header_bytes + rgb_bytes + depth_bytes


def _decode_body(header: dict[str, Any], buf: bytearray, offset: int) -> RgbdFrame:
    """The frame whose images start at ``offset`` in ``buf`` (colour, then depth): each image is copied out of
    the buffer once, straight into its own array (the caller then drops the record from the buffer)."""
    width, height = int(header["width"]), int(header["height"])
    rgb_n, depth_n = int(header["rgb_bytes"]), int(header["depth_bytes"])
    if header["rgb_encoding"] == "jpeg":
        bgr = cv2.imdecode(np.frombuffer(buf, np.uint8, rgb_n, offset), cv2.IMREAD_COLOR)
        if bgr is None:
            raise ProtocolError("corrupt JPEG colour image in camera record")
        rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
    elif header["rgb_encoding"] == "rgb8":
        rgb = np.frombuffer(buf, np.uint8, rgb_n, offset).reshape(height, width, 3).copy()
    else:
        raise ProtocolError(f"unknown rgb_encoding {header['rgb_encoding']!r}")
    depth: NDArray[np.float32] | None = None
    if header.get("depth_encoding") == "mm_u16le":
        depth = np.frombuffer(buf, "<u2", depth_n // 2, offset + rgb_n).reshape(height, width).astype(np.float32)
        depth *= np.float32(1e-3)
    k = header["intrinsics"]
    return RgbdFrame(
        seq=int(header["seq"]),
        stamp_s=float(header["stamp_s"]),
        rgb=np.asarray(rgb, dtype=np.uint8),
        depth_m=depth,
        intrinsics=CameraIntrinsics(float(k["fx"]), float(k["fy"]), float(k["cx"]), float(k["cy"]), width, height),
        R_qc=np.asarray(header["R_qc"], dtype=float),
        p_qc_m=np.asarray(header["p_qc_m"], dtype=float),
        meta=dict(header.get("meta") or {}),
    )


class RecordDecoder:
    """Streaming decoder of camera records: feed bytes, get whole frames.

    A corrupt record raises :class:`ProtocolError` (the stream has lost its framing; the caller
    reconnects). Sizes are bounded so a bad header cannot make it allocate without limit.
    """

    def __init__(self) -> None:
        self._buf = bytearray()

    @property
    def pending_bytes(self) -> int:
        """Bytes held of a record not complete yet."""
        return len(self._buf)

    def feed(self, data: bytes | bytearray | memoryview) -> list[RgbdFrame]:
        self._buf += data
        frames = []
        while len(self._buf) >= _PREFIX.size:
            magic, header_len = _PREFIX.unpack_from(self._buf)
            if magic != MAGIC or header_len > MAX_HEADER_BYTES:
                self._buf.clear()
                raise ProtocolError("camera stream lost framing (bad magic or header length)")
            if len(self._buf) < _PREFIX.size + header_len:
                break
            try:
                header = json.loads(bytes(self._buf[_PREFIX.size:_PREFIX.size + header_len]))
                rgb_n, depth_n = int(header["rgb_bytes"]), int(header["depth_bytes"])
            except (ValueError, KeyError, TypeError) as exc:
                self._buf.clear()
                raise ProtocolError(f"corrupt camera record header: {exc}") from exc
            if rgb_n + depth_n > MAX_PAYLOAD_BYTES:
                self._buf.clear()
                raise ProtocolError("camera record larger than the allowed maximum")
            start = _PREFIX.size + header_len
            end = start + rgb_n + depth_n
            if len(self._buf) < end:
                break
            try:
                frame = _decode_body(header, self._buf, start)
            except (ValueError, KeyError, TypeError) as exc:
                raise ProtocolError(f"corrupt camera record: {exc}") from exc
            finally:
                del self._buf[:end]   # no view of the buffer outlives _decode_body (its arrays are copies)
            frames.append(frame)
        return frames


class FrameRecordWriter:
    """Appends frames to a file as camera-stream records (the wire format above, one after another), so a
    flight's camera can be replayed later (:func:`read_frame_recording`). Depth is stored as the stream
    carries it (uint16 mm), colour raw: about 380 kB per QVGA frame."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._f = open(self.path, "wb")   # noqa: SIM115 - held open for the whole run
        self.frames = 0

    def write(self, frame: RgbdFrame) -> None:
        self._f.write(encode_record(frame))
        self.frames += 1

    def close(self) -> None:
        self._f.close()


def read_frame_recording(path: str | Path, chunk_bytes: int = 1 << 20) -> Iterator[RgbdFrame]:
    """The frames of a file written by :class:`FrameRecordWriter` (or a raw dump of a camera stream).

    A truncated last record (the writer was killed) ends the iteration with a warning; a corrupt one
    raises :class:`ProtocolError`."""
    decoder = RecordDecoder()
    with open(path, "rb") as f:
        while chunk := f.read(chunk_bytes):
            yield from decoder.feed(chunk)
    if decoder.pending_bytes:
        log.warning("%s: %d bytes of an incomplete last record ignored", path, decoder.pending_bytes)


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

    def read(self, timeout_s: float) -> RgbdFrame | None:
        """The next frame, or None if none arrived within ``timeout_s``."""
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

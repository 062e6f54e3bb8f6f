"""The operator image stream (companion -> ground-station view) that can never block the flight loop.

The loop hands a frame over with :meth:`OperatorImagePublisher.publish`: a non-blocking put into a
bounded queue (a full queue drops its oldest frame). One publisher thread encodes the record (JPEG colour,
:class:`quadlink.operator_image.OperatorImageMeta` as ``meta``) and writes it to every viewer with
non-blocking sends through a selector:

* a viewer still busy with an earlier record skips the new one (frames are dropped, per viewer); the
  kernel's send buffer per viewer is bounded too (``send_buffer_bytes``), so at most a few frames queue;
* a viewer that has taken no byte for ``stall_timeout_s`` while a record waits for it is disconnected.

The viewers' acks (the camera stream's return direction) are read and discarded: this stream is not
lock-stepped. Issue 16: a client that connected and never read made the old blocking sender stall the
companion's loop until the vehicle landed.
"""

from __future__ import annotations

import logging
import selectors
import socket
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

from quadlink.camera import RgbdFrame, encode_record
from quadlink.errors import ProtocolError
from quadlink.operator_image import OperatorImageMeta

log = logging.getLogger(__name__)


@dataclass
class PublisherStats:
    offered: int = 0
    dropped_in_queue: int = 0       # overwritten before the publisher thread took them
    sent: int = 0                   # records fully handed to a viewer's socket
    skipped_busy: int = 0           # (viewer, frame) pairs dropped because the viewer was still busy
    disconnected_stalled: int = 0
    invalid_meta: int = 0


class _Viewer:
    def __init__(self, sock: socket.socket, address: str, now_s: float) -> None:
        self.sock = sock
        self.address = address
        self.out = memoryview(b"")
        self.progress_s = now_s   # last time it took bytes (or had nothing pending)


class OperatorImagePublisher:
    """Listens on ``host:port`` for viewers (:class:`quadlink.camera.CameraStreamClient`)."""

    def __init__(self, host: str = "127.0.0.1", port: int = 5770, queue_frames: int = 2,
                 stall_timeout_s: float = 1.0, jpeg_quality: int = 85, send_buffer_bytes: int = 128 * 1024,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self._listener = socket.create_server((host, port))
        self._listener.setblocking(False)
        self.host, self.port = self._listener.getsockname()[:2]
        self._stall_timeout_s = stall_timeout_s
        self._jpeg_quality = jpeg_quality
        self._send_buffer_bytes = send_buffer_bytes
        self._clock = clock
        self._queue: deque[tuple[RgbdFrame, OperatorImageMeta]] = deque(maxlen=queue_frames)
        self._lock = threading.Lock()
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        self._selector = selectors.DefaultSelector()
        self._selector.register(self._listener, selectors.EVENT_READ, "accept")
        self._selector.register(self._wake_r, selectors.EVENT_READ, "wake")
        self._viewers: list[_Viewer] = []
        self._viewer_count = 0
        self._closed = threading.Event()
        self.stats = PublisherStats()
        self._thread = threading.Thread(target=self._run, name="operator-images", daemon=True)
        self._thread.start()
        log.info("operator image stream on tcp://%s:%d", self.host, self.port)

    @property
    def client_count(self) -> int:
        return self._viewer_count

    def publish(self, frame: RgbdFrame, meta: OperatorImageMeta) -> None:
        """Hand a frame over (never blocks; the frame's own ``meta`` is replaced by ``meta``)."""
        with self._lock:
            if len(self._queue) == self._queue.maxlen:
                self.stats.dropped_in_queue += 1
            self._queue.append((frame, meta))
            self.stats.offered += 1
        try:
            self._wake_w.send(b"\0")
        except (BlockingIOError, OSError):
            pass   # a wake-up is already pending (or we are closing)

    # ---------------------------------------------------------------- the publisher thread
    def _run(self) -> None:
        while not self._closed.is_set():
            for key, events in self._selector.select(timeout=0.1):
                if key.data == "accept":
                    self._accept()
                elif key.data == "wake":
                    try:
                        while self._wake_r.recv(4096):
                            pass
                    except (BlockingIOError, OSError):
                        pass
                else:
                    viewer: _Viewer = key.data
                    if events & selectors.EVENT_READ:
                        self._read_acks(viewer)
                    if events & selectors.EVENT_WRITE and viewer in self._viewers:
                        self._flush(viewer)
            self._take_frames()
            self._drop_stalled()

    def _accept(self) -> None:
        try:
            sock, addr = self._listener.accept()
        except (BlockingIOError, OSError):
            return
        sock.setblocking(False)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        # a bounded kernel queue too: a few frames at most wait there (latency), the rest are dropped here
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, self._send_buffer_bytes)
        viewer = _Viewer(sock, f"{addr[0]}:{addr[1]}", self._clock())
        self._viewers.append(viewer)
        self._viewer_count = len(self._viewers)
        self._selector.register(sock, selectors.EVENT_READ, viewer)
        log.info("operator view %s connected", viewer.address)

    def _read_acks(self, viewer: _Viewer) -> None:
        try:
            data = viewer.sock.recv(4096)
        except BlockingIOError:
            return
        except OSError as exc:
            self._drop(viewer, f"dropped ({exc})")
            return
        if not data:
            self._drop(viewer, "disconnected")

    def _take_frames(self) -> None:
        with self._lock:
            items = list(self._queue)
            self._queue.clear()
        if not items or not self._viewers:
            return
        frame, meta = items[-1]   # the newest: older ones would only add latency
        self.stats.dropped_in_queue += len(items) - 1
        try:
            OperatorImageMeta.from_wire(meta.to_wire())   # what goes on the wire must decode
        except ProtocolError as exc:
            self.stats.invalid_meta += 1
            log.warning("operator image %d not sent: %s", frame.seq, exc)
            return
        image = RgbdFrame(frame.seq, frame.stamp_s, frame.rgb, None, frame.intrinsics, frame.R_qc, frame.p_qc_m,
                          meta.to_wire())
        try:
            record = memoryview(encode_record(image, rgb_jpeg=True, jpeg_quality=self._jpeg_quality, with_mount=True))
        except ProtocolError as exc:
            log.warning("operator image %d not encoded: %s", frame.seq, exc)
            return
        now = self._clock()
        for viewer in list(self._viewers):
            if viewer.out:
                self.stats.skipped_busy += 1
                continue
            viewer.out = record
            viewer.progress_s = now
            self._flush(viewer)

    def _flush(self, viewer: _Viewer) -> None:
        try:
            n = viewer.sock.send(viewer.out)
        except BlockingIOError:
            n = 0
        except OSError as exc:
            self._drop(viewer, f"dropped ({exc})")
            return
        if n:
            viewer.out = viewer.out[n:]
            viewer.progress_s = self._clock()
        if not viewer.out:
            self.stats.sent += 1
        events = selectors.EVENT_READ | (selectors.EVENT_WRITE if viewer.out else 0)
        self._selector.modify(viewer.sock, events, viewer)

    def _drop_stalled(self) -> None:
        now = self._clock()
        for viewer in list(self._viewers):
            if viewer.out and now - viewer.progress_s > self._stall_timeout_s:
                self.stats.disconnected_stalled += 1
                self._drop(viewer, f"stalled for {self._stall_timeout_s:.1f} s: disconnected")

    def _drop(self, viewer: _Viewer, reason: str) -> None:
        if viewer not in self._viewers:
            return
        self._viewers.remove(viewer)
        self._viewer_count = len(self._viewers)
        try:
            self._selector.unregister(viewer.sock)
        except (KeyError, ValueError):
            pass
        try:
            viewer.sock.close()
        except OSError:
            pass
        log.info("operator view %s %s", viewer.address, reason)

    def close(self) -> None:
        self._closed.set()
        try:
            self._wake_w.send(b"\0")
        except OSError:
            pass
        self._thread.join(timeout=2.0)
        for viewer in list(self._viewers):
            self._drop(viewer, "closed")
        self._selector.close()
        for s in (self._listener, self._wake_r, self._wake_w):
            try:
                s.close()
            except OSError:
                pass

"""Camera inputs of the daemon behind one small interface: ``read(timeout_s)``, ``ack(seq)``, ``close()``.

* :class:`StreamCamera` — the SITL camera stream (``tcp://HOST:PORT``); acks each processed frame, which
  is what lets a lock-step SITL wait for the companion.
* :class:`TumReplayCamera` — a TUM RGB-D folder replayed at its recorded pace (wall clock), stamps
  shifted to start at zero.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from quadlink.camera import CameraStreamClient, RgbdFrame
from quadlink.errors import LinkError

log = logging.getLogger(__name__)


class CameraInput(Protocol):
    def read(self, timeout_s: float) -> RgbdFrame | None: ...

    def ack(self, seq: int) -> None: ...

    def close(self) -> None: ...

    @property
    def connected(self) -> bool: ...


class StreamCamera:
    """The SITL camera stream; reconnection attempts throttled so a missing producer costs nothing."""

    def __init__(self, url: str, clock: Callable[[], float] = time.monotonic, retry_s: float = 0.5) -> None:
        self.url = url
        self._client = CameraStreamClient(url)
        self._clock = clock
        self._retry_s = retry_s
        self._next_try_s = 0.0

    @property
    def connected(self) -> bool:
        return self._client.connected

    def read(self, timeout_s: float) -> RgbdFrame | None:
        if not self._client.connected:
            now = self._clock()
            if now < self._next_try_s:
                time.sleep(timeout_s)
                return None
            self._next_try_s = now + self._retry_s
        return self._client.read(timeout_s)

    def ack(self, seq: int) -> None:
        self._client.ack(seq)

    def close(self) -> None:
        self._client.close()


class TumReplayCamera:
    """A TUM-format folder replayed at recorded pace; ``loop`` restarts it at the end."""

    def __init__(self, folder: str | Path, clock: Callable[[], float] = time.monotonic, loop: bool = False,
                 resize_to: tuple[int, int] | None = (320, 240), R_qc: NDArray[np.float64] | None = None,
                 p_qc_m: NDArray[np.float64] | None = None) -> None:
        from perception.sources import SourceUnavailable, TumFolderSource

        try:
            self._source = TumFolderSource(folder, resize_to=resize_to)
        except SourceUnavailable as exc:
            raise LinkError(f"camera {folder}: {exc}") from exc
        self._clock = clock
        self._loop = loop
        self._iter: Iterator[RgbdFrame] = self._source.frames()
        self._t0_wall: float | None = None
        self._t0_stamp = self._source.stamps()[0]
        self._pending: RgbdFrame | None = None
        self._seq = 0
        self._R_qc = np.eye(3) if R_qc is None else np.asarray(R_qc, dtype=float)
        self._p_qc_m = np.zeros(3) if p_qc_m is None else np.asarray(p_qc_m, dtype=float)
        self.finished = False
        log.info("camera: replaying %d frames of %s", len(self._source), folder)

    @property
    def connected(self) -> bool:
        return not self.finished

    def read(self, timeout_s: float) -> RgbdFrame | None:
        if self._pending is None:
            try:
                self._pending = next(self._iter)
            except StopIteration:
                if not self._loop:
                    self.finished = True
                    time.sleep(timeout_s)
                    return None
                self._iter = self._source.frames()
                self._t0_wall = None
                return None
        now = self._clock()
        if self._t0_wall is None:
            self._t0_wall = now
        due = self._t0_wall + (self._pending.stamp_s - self._t0_stamp)
        if due - now > timeout_s:
            time.sleep(timeout_s)
            return None
        if due > now:
            time.sleep(due - now)
        f = self._pending
        self._pending = None
        self._seq += 1
        return RgbdFrame(self._seq, f.stamp_s - self._t0_stamp, f.rgb, f.depth_m, f.intrinsics, self._R_qc,
                         self._p_qc_m, f.meta)

    def ack(self, seq: int) -> None:
        return None

    def close(self) -> None:
        self._source.close()


def open_camera(url: str, clock: Callable[[], float] = time.monotonic, R_qc: NDArray[np.float64] | None = None,
                p_qc_m: NDArray[np.float64] | None = None) -> CameraInput:
    """``tcp://HOST:PORT`` (stream) or a TUM folder path (replay, with the mount ``R_qc``, ``p_qc_m``)."""
    if url.startswith("tcp://"):
        return StreamCamera(url, clock)
    if Path(url).is_dir():
        return TumReplayCamera(url, clock, R_qc=R_qc, p_qc_m=p_qc_m)
    raise LinkError(f"{url}: camera must be tcp://HOST:PORT (the SITL stream) or a TUM-format folder")

"""A TUM RGB-D folder replayed as a camera, at its recorded pace on the injected clock."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from companion.cameras.base import CameraUnavailable
from quadlink.camera import RgbdFrame
from quadlink.datasets.tum import DatasetUnavailable, TumSequence

log = logging.getLogger(__name__)


class TumReplayCamera:
    """A TUM-format folder replayed at recorded pace (stamps shifted to start at zero); ``loop`` restarts it."""

    def __init__(self, folder: str | Path, clock: Callable[[], float] = time.monotonic, loop: bool = False,
                 resize_to: tuple[int, int] | None = (320, 240), R_qc: NDArray[np.float64] | None = None,
                 p_qc_m: NDArray[np.float64] | None = None, sleep: Callable[[float], None] = time.sleep) -> None:
        try:
            self._source = TumSequence(folder, resize_to=resize_to)
        except DatasetUnavailable as exc:
            raise CameraUnavailable(f"camera {folder}: {exc}") from exc
        self._clock = clock
        self._sleep = sleep
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
                    self._sleep(timeout_s)
                    return None
                self._iter = self._source.frames()
                self._t0_wall = None
                return None
        now = self._clock()
        if self._t0_wall is None:
            self._t0_wall = now
        due = self._t0_wall + (self._pending.stamp_s - self._t0_stamp)
        if due - now > timeout_s:
            self._sleep(timeout_s)
            return None
        if due > now:
            self._sleep(due - now)
        f = self._pending
        self._pending = None
        self._seq += 1
        return RgbdFrame(self._seq, f.stamp_s - self._t0_stamp, f.rgb, f.depth_m, f.intrinsics, self._R_qc,
                         self._p_qc_m, f.meta)

    def ack(self, seq: int) -> None:
        return None

    def close(self) -> None:
        return None

"""``tcp://HOST:PORT``: the SITL camera stream (:mod:`quadlink.camera`); each processed frame is acked.

The stream carries what a real driver gives (images, depth, stamps, intrinsics): the mount every frame is placed
with is this vehicle's calibration (``configs/vehicle.yaml`` ``camera.R_qc``/``p_qc_m``), as for a RealSense or an
OpenNI device; any mount in a record is ignored."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from quadlink.camera import CameraStreamClient, RgbdFrame


class StreamCamera:
    """The SITL camera stream; reconnection attempts throttled so a missing producer costs nothing."""

    def __init__(self, url: str, clock: Callable[[], float] = time.monotonic, retry_s: float = 0.5,
                 R_qc: NDArray[np.float64] | None = None, p_qc_m: NDArray[np.float64] | None = None) -> None:
        self.url = url
        self.R_qc = np.eye(3) if R_qc is None else np.asarray(R_qc, dtype=float)
        self.p_qc_m = np.zeros(3) if p_qc_m is None else np.asarray(p_qc_m, dtype=float)
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
        frame = self._client.read(timeout_s, newest=True)   # a backlog (a starved companion) is skipped, not flown
        if frame is None:
            return None
        return dataclasses.replace(frame, R_qc=self.R_qc, p_qc_m=self.p_qc_m)

    def ack(self, seq: int) -> None:
        self._client.ack(seq)

    def close(self) -> None:
        self._client.close()

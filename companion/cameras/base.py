"""The one camera interface of the stack: what the companion daemon reads frames from.

Every camera (the SITL stream, a TUM replay, a RealSense, an OpenNI2 device) implements
:class:`CameraInput`: ``read(timeout_s)`` returns the next :class:`~quadlink.camera.RgbdFrame` or None
after at most ``timeout_s`` (no read blocks longer), ``ack(seq)`` tells the producer the frame has been
processed (what lets a lock-step SITL wait; a no-op for real sensors), ``connected`` says whether frames
can come, ``close()`` releases the device or link.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from quadlink.camera import CameraIntrinsics, RgbdFrame
from quadlink.errors import LinkError


class CameraUnavailable(LinkError):
    """A camera cannot be opened: missing SDK, device, folder or a bad URL (one line, for the CLI)."""


class CameraInput(Protocol):
    def read(self, timeout_s: float) -> RgbdFrame | None: ...

    def ack(self, seq: int) -> None: ...

    def close(self) -> None: ...

    @property
    def connected(self) -> bool: ...


class DeviceCamera:
    """What the live sensors share: the mount given by the vehicle config, a frame counter, no acks."""

    def __init__(self, R_qc: NDArray[np.float64] | None, p_qc_m: NDArray[np.float64] | None) -> None:
        self.R_qc = np.eye(3) if R_qc is None else np.asarray(R_qc, dtype=float)
        self.p_qc_m = np.zeros(3) if p_qc_m is None else np.asarray(p_qc_m, dtype=float)
        self._seq = 0
        self._running = True

    @property
    def connected(self) -> bool:
        return self._running

    def _frame(self, stamp_s: float, rgb: NDArray[np.uint8], depth_m: NDArray[np.float32],
               intrinsics: CameraIntrinsics) -> RgbdFrame:
        frame = RgbdFrame(self._seq, stamp_s, rgb, depth_m, intrinsics, self.R_qc, self.p_qc_m)
        self._seq += 1
        return frame

    def ack(self, seq: int) -> None:
        return None  # a real sensor does not wait for its consumer

    def close(self) -> None:
        if self._running:
            self._running = False
            self._stop()

    def _stop(self) -> None:
        raise NotImplementedError

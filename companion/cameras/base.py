"""The one camera interface of the stack: what the companion daemon reads frames from.

Every camera (the SITL stream, a TUM replay, a RealSense, an OpenNI2 device) implements
:class:`CameraInput`: ``read(timeout_s)`` returns the next :class:`~quadlink.camera.RgbdFrame` or None
after at most ``timeout_s`` (no read blocks longer), ``ack(seq)`` tells the producer the frame has been
processed (what lets a lock-step SITL wait; a no-op for real sensors), ``connected`` says whether frames
can come, ``close()`` releases the device or link.
"""

from __future__ import annotations

from typing import Protocol

from quadlink.camera import RgbdFrame
from quadlink.errors import LinkError


class CameraUnavailable(LinkError):
    """A camera cannot be opened: missing SDK, device, folder or a bad URL (one line, for the CLI)."""


class CameraInput(Protocol):
    def read(self, timeout_s: float) -> RgbdFrame | None: ...

    def ack(self, seq: int) -> None: ...

    def close(self) -> None: ...

    @property
    def connected(self) -> bool: ...

"""What the companion records besides the tlog (which :class:`companion.outbound.Outbox` writes): every camera
frame received (``--record-frames``, a :class:`quadlink.camera.FrameRecordWriter`), for replay.

A full disk (any write error) stops the recording, never the flight loop.
"""

from __future__ import annotations

import logging
from typing import Any

from quadlink.camera import RgbdFrame

log = logging.getLogger("companion.daemon")


class FrameRecording:
    """``writer``: where the frames go (None: no recording)."""

    def __init__(self, writer: Any | None) -> None:
        self._writer = writer

    def write(self, frame: RgbdFrame) -> None:
        if self._writer is None:
            return
        try:
            self._writer.write(frame)
        except OSError as exc:
            log.error("frame recording stopped: %s", exc)
            self._writer = None

    def close(self) -> None:
        if self._writer is not None:
            self._writer.close()

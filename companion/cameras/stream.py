"""``tcp://HOST:PORT``: the SITL camera stream (:mod:`quadlink.camera`); each processed frame is acked."""

from __future__ import annotations

import time
from collections.abc import Callable

from quadlink.camera import CameraStreamClient, RgbdFrame


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

"""Device timestamps -> the companion's clock (``camera_stamps: local``), pure.

A camera stamps frames with its own clock (RealSense: the hardware clock, ms; OpenNI2: µs since the stream
started). The companion's stamps are its monotonic clock, which the TIMESYNC offset turns into autopilot
time. A frame arrives some transport latency after its device stamp, never before it, so the offset
``local - device`` is estimated as the smallest ``arrival - device`` seen (the least-delayed frame bounds
the latency from below), forgotten slowly (``drift_s_per_s``) so that a relative clock drift cannot leave it
stale; a device clock that jumps (a restart, a replug) resets the estimate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass
class DeviceClockMap:
    """``to_local(device_s, arrival_s)``: the frame's device stamp on the local clock (both in s)."""

    drift_s_per_s: float = 1e-4     # the offset estimate creeps up this fast (covers a 100 ppm drift)
    jump_s: float = 1.0             # a device/arrival disagreement this large from the estimate: reset
    _offset_s: float | None = None
    _last_device_s: float = -math.inf
    _last_arrival_s: float = -math.inf

    def to_local(self, device_s: float, arrival_s: float) -> float:
        raw = arrival_s - device_s
        if self._offset_s is not None:
            crept = self._offset_s + self.drift_s_per_s * max(arrival_s - self._last_arrival_s, 0.0)
            restarted = device_s < self._last_device_s or abs(raw - crept) > self.jump_s
            self._offset_s = raw if restarted else min(crept, raw)
        else:
            self._offset_s = raw
        self._last_device_s, self._last_arrival_s = device_s, arrival_s
        return device_s + self._offset_s

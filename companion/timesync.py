"""TIMESYNC (MAVLink time synchronisation) offset estimation, pure: times are arguments in ns.

The companion sends ``TIMESYNC(tc1=0, ts1=local_ns)``; the autopilot answers
``TIMESYNC(tc1=remote_ns, ts1=local_ns)``. With the round trip ``rtt = now - ts1`` the remote clock at
the middle of the round trip gives ``offset = tc1 - (ts1 + now) / 2``. The estimate keeps the sample of
smallest round trip among the recent ones (least queueing error) and ignores round trips above a bound.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field


@dataclass
class TimeSync:
    max_rtt_ns: int = 50_000_000
    window: int = 10
    _samples: deque[tuple[int, int]] = field(default_factory=lambda: deque(maxlen=10))
    offset_ns: int | None = None
    rtt_ns: int | None = None

    def on_response(self, tc1_ns: int, ts1_ns: int, now_ns: int) -> bool:
        """Use one answer to our request; True if it was usable."""
        rtt = now_ns - ts1_ns
        if tc1_ns <= 0 or rtt < 0 or rtt > self.max_rtt_ns:
            return False
        self._samples.append((rtt, tc1_ns - (ts1_ns + now_ns) // 2))
        self.rtt_ns, self.offset_ns = min(self._samples)
        return True

    def to_remote_s(self, local_s: float) -> float | None:
        """A local-clock time in the autopilot's clock, or None before the first exchange."""
        return None if self.offset_ns is None else local_s + self.offset_ns * 1e-9

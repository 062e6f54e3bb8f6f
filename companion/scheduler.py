"""The daemon's deadlines (pure: the time is an argument, from the daemon's one injected clock).

:class:`Deadlines` keeps named periodic tasks (heartbeat, TIMESYNC, fallback setpoints, progress log on
wall time); :class:`StampTicker` paces a task on the autopilot's stamps (TELEOP_FEEDBACK on the IMU clock,
aligned to multiples of its period so its rate holds whatever the IMU rate).
"""

from __future__ import annotations

import math


class Deadlines:
    """Named periodic deadlines; :meth:`due` is true once per period and re-arms the task."""

    def __init__(self) -> None:
        self._next_s: dict[str, float] = {}

    def due(self, name: str, now_s: float, period_s: float) -> bool:
        if now_s < self._next_s.get(name, -math.inf):
            return False
        self._next_s[name] = now_s + period_s
        return True

    def arm(self, name: str, at_s: float) -> None:
        """First occurrence of ``name`` no earlier than ``at_s``."""
        self._next_s[name] = at_s


class StampTicker:
    """True at the first stamp past each multiple of ``period_s``; a stamp a second behind re-arms it (a
    restarted producer rewinds time)."""

    def __init__(self, period_s: float) -> None:
        self.period_s = period_s
        self._next_s = 0.0

    def due(self, stamp_s: float) -> bool:
        if stamp_s >= self._next_s or stamp_s < self._next_s - 1.0:
            # the epsilon: a stamp on a boundary that rounds just below it must not fire again 2 ms later
            self._next_s = (math.floor(stamp_s / self.period_s + 1e-6) + 1) * self.period_s
            return True
        return False

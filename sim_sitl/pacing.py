"""How simulated time is paced against the wall clock (pure: the clock's readings are arguments).

Two regimes, chosen per 10 ms chunk by the runner:

- **real time** (``speed`` x the wall clock, :class:`RealTimePacer`): each chunk ends at a wall-clock
  target; a SITL that falls more than ``max_behind_s`` behind restarts its origin instead of catching up
  in a burst.
- **lock-step** (:class:`SetpointGate`): once a port-1 client sends setpoints, sim time advances one chunk
  per setpoint (a little credit absorbs jitter); the camera's acks gate each frame. The waits themselves
  are :func:`wait_serving`, which keeps the caller's ports served while it waits.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

MAX_SETPOINT_CREDIT = 3  # setpoints taken ahead of the chunks they pay for
SERVE_SLICE_S = 0.002  # longest a lock-step wait blocks before it serves the serial ports again


@dataclass
class RealTimePacer:
    """Wall-clock target of each sim time at ``speed`` x real time (``speed`` <= 0 or inf: unpaced)."""

    speed: float = 1.0
    max_behind_s: float = 0.5
    wall0_s: float = 0.0
    sim0_s: float = 0.0
    fell_behind: bool = False  # set once, when the first restart happened (the runner warns once)

    @property
    def unpaced(self) -> bool:
        return self.speed <= 0 or math.isinf(self.speed)

    def rebase(self, wall_s: float, sim_t_s: float) -> None:
        """Pace from here (consumers left the lock-step, or the SITL fell behind)."""
        self.wall0_s, self.sim0_s = wall_s, sim_t_s

    def wait_s(self, sim_t_s: float, wall_s: float) -> float:
        """How long to wait at wall time ``wall_s`` before sim time ``sim_t_s`` is due (0 if late)."""
        if self.unpaced:
            return 0.0
        target = self.wall0_s + (sim_t_s - self.sim0_s) / self.speed
        if target - wall_s < -self.max_behind_s:  # cannot keep up: do not try to catch up in a burst
            self.fell_behind = True
            self.rebase(wall_s, sim_t_s)
            return 0.0
        return max(0.0, target - wall_s)


@dataclass
class SetpointGate:
    """Lock-step on setpoints: one per chunk once a port-1 client sends them."""

    gated: bool = False
    credit: int = 0

    def on_setpoints(self, n: int) -> bool:
        """Count ``n`` setpoints just received; True when this starts the gating."""
        if n <= 0:
            return False
        self.credit = min(self.credit + n, MAX_SETPOINT_CREDIT)
        started = not self.gated
        self.gated = True
        return started

    def take(self) -> bool:
        """Spend one setpoint on the next chunk; False if none is there yet."""
        if self.credit <= 0:
            return False
        self.credit -= 1
        return True

    def release(self) -> None:
        """Run free until setpoints resume (client gone, or a timeout)."""
        self.gated = False


def wait_serving(ready: Callable[[float], bool], serve: Callable[[], object], timeout_s: float,
                 clock: Callable[[], float], stopped: Callable[[], bool],
                 slice_s: float = SERVE_SLICE_S) -> bool | None:
    """Wait until ``ready(block_s)`` (which may block up to ``block_s``) while calling ``serve()`` between tries.

    Returns True when ready, False on timeout (``timeout_s`` of ``clock`` time), None when ``stopped()``.
    """
    deadline = clock() + timeout_s
    while True:
        serve()
        if stopped():
            return None
        remaining = deadline - clock()
        if ready(min(max(remaining, 0.0), slice_s)):
            return True
        if remaining <= 0:
            return False

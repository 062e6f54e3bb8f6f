"""What keeps the companion's one loop alive through any one bad message (pure; the clock is injected).

* :class:`ErrorCounter` — an unexpected exception in one message's handling (a pack error, struct.error,
  OverflowError, a bug) is counted by where it happened and logged, the first at once and then at most
  once per period, so a flood of bad messages neither ends the loop nor the log (issue 16).
* :class:`RateLimit` — at most one event per key per period (refusal STATUSTEXTs to a sender that
  streams at 50 Hz).
* :func:`non_finite_fields` — the last check before a message goes to the autopilot: every float field
  finite, except the NaNs MAVLink defines as meaning something (a command's unused params, ODOMETRY's
  "covariance unknown").
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from typing import Any

from quadlink.mavlink.command_params import COMMAND_PARAMS, nan_means_unused

log = logging.getLogger("companion.daemon")

#: ODOMETRY covariance arrays whose first element NaN means "unknown" (MAVLink's convention)
_COVARIANCE_FIELDS = frozenset({"pose_covariance", "velocity_covariance"})


class ErrorCounter:
    """Counts unexpected exceptions by ``where``; logs the first of each and then one per ``period_s``."""

    def __init__(self, clock: Callable[[], float], period_s: float = 5.0) -> None:
        self._clock = clock
        self._period_s = period_s
        self.by_where: dict[str, int] = {}
        self._next_log_s: dict[str, float] = {}
        self._unlogged: dict[str, int] = {}

    @property
    def total(self) -> int:
        return sum(self.by_where.values())

    def record(self, where: str, exc: BaseException) -> None:
        self.by_where[where] = self.by_where.get(where, 0) + 1
        now = self._clock()
        if now < self._next_log_s.get(where, -math.inf):
            self._unlogged[where] = self._unlogged.get(where, 0) + 1
            return
        self._next_log_s[where] = now + self._period_s
        skipped = self._unlogged.pop(where, 0)
        log.error("%s: %s: %s (loop continues; %d such errors so far%s)", where, type(exc).__name__, exc,
                  self.by_where[where], f", {skipped} not logged" if skipped else "", exc_info=exc)


class RateLimit:
    """``allow(key)`` is True at most once per ``period_s`` for each key."""

    def __init__(self, clock: Callable[[], float], period_s: float = 2.0) -> None:
        self._clock = clock
        self._period_s = period_s
        self._next_s: dict[Any, float] = {}

    def allow(self, key: Any) -> bool:
        now = self._clock()
        if now < self._next_s.get(key, -math.inf):
            return False
        self._next_s[key] = now + self._period_s
        return True


def _bad_float(value: float) -> bool:
    return not math.isfinite(value)


def _unused_nan(msg: Any, name: str, value: float, any_command: bool) -> bool:
    """A NaN command param MAVLink reads as "unused": per the command table, or for any command the table does
    not know when ``any_command`` (forwarded traffic: the autopilot's own table decides)."""
    if not (name.startswith("param") and math.isnan(value)):
        return False
    if any_command and int(msg.command) not in COMMAND_PARAMS:
        return True
    return nan_means_unused(msg.command, int(name[5:]) - 1)


def non_finite_fields(msg: Any, any_command: bool = False) -> list[str]:
    """Names of ``msg``'s float fields holding a non-finite value that MAVLink gives no meaning to.
    ``any_command``: a NaN param of a command not in quadlink's table counts as unused (forwarded commands)."""
    kind = msg.get_type()
    bad: list[str] = []
    for name in msg.get_fieldnames():
        value = getattr(msg, name)
        if isinstance(value, float):
            if _bad_float(value) and not (kind in ("COMMAND_LONG", "COMMAND_INT")
                                          and _unused_nan(msg, name, value, any_command)):
                bad.append(name)
        elif isinstance(value, (list, tuple)) and value and isinstance(value[0], float):
            start = 1 if kind == "ODOMETRY" and name in _COVARIANCE_FIELDS and math.isnan(value[0]) else 0
            if any(_bad_float(v) for v in value[start:]):
                bad.append(name)
    return bad

"""The daemon's deadlines (pure: the time is an argument, from the daemon's one injected clock).

:class:`PeriodicTasks` says which of the daemon's periodic tasks (:class:`Task`: heartbeat, TIMESYNC, the
command-age figures, fallback setpoints, feedback without IMU, progress log) are due on wall time, over
:class:`Deadlines`, named periodic deadlines; :class:`StampTicker` paces a task on the autopilot's stamps
(TELEOP_FEEDBACK on the IMU clock, aligned to multiples of its period so its rate holds whatever the IMU rate).
"""

from __future__ import annotations

import enum
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


class Task(enum.Enum):
    """The daemon's periodic tasks, in the order they run when due together."""

    HEARTBEAT = "heartbeat"          # the companion's HEARTBEAT to the autopilot and the ground stations
    TIMESYNC = "timesync"            # a TIMESYNC request to the autopilot
    GCS_TIMESYNC = "gcs_timesync"    # a TIMESYNC request to the ground stations (the clock of their commands)
    COMMAND_AGE = "command_age"      # the command-age figures to the ground stations
    FALLBACK = "fallback"            # a setpoint from the last map while the camera is silent
    FEEDBACK = "feedback"            # TELEOP_FEEDBACK on wall time while the IMU is silent
    PROGRESS = "progress"            # the progress log line


class PeriodicTasks:
    """``periods_s``: every :class:`Task`'s period (s, wall time); the first progress line is due one period
    after ``start_s``, the other tasks at the first :meth:`due`."""

    def __init__(self, periods_s: dict[Task, float], start_s: float) -> None:
        self.periods_s = periods_s
        self._deadlines = Deadlines()
        self._deadlines.arm(Task.PROGRESS.value, start_s + periods_s[Task.PROGRESS])

    def due(self, now_s: float, camera_silent: bool, imu_silent: bool) -> list[Task]:
        """The tasks due at ``now_s``, in order, each re-armed: FALLBACK only while the camera is silent, FEEDBACK
        only while the IMU is (otherwise the IMU's stamps pace it); a task not run is not re-armed."""
        when = {Task.FALLBACK: camera_silent, Task.FEEDBACK: imu_silent}
        return [task for task in Task
                if when.get(task, True) and self._deadlines.due(task.value, now_s, self.periods_s[task])]


class HeartbeatBehindAutopilot:
    """When the companion's own HEARTBEAT goes to the ground stations: right behind an autopilot message it
    forwards them, never ahead of the autopilot.

    mavsdk_server (the classic API's, v4.0.5) declares a vehicle found once, at the first HEARTBEAT it hears, and
    only if it has heard the autopilot (compid 1) by then: a station that hears the companion's heartbeat first
    never opens its gRPC port, whatever it hears later. A station hears the companion from the moment its first
    datagram arrives, so while the autopilot is heard the due heartbeat is held until the next autopilot message is
    forwarded and sent in the same turn, behind it, to the same stations; the autopilot silent for ``lost_s``
    (or never heard), it goes alone, so a station still sees the companion of a vehicle whose autopilot is gone.
    The daemon reports forwarded messages without a clock reading (500 a second); a turn's time marks them."""

    def __init__(self, lost_s: float = 1.5) -> None:
        self.lost_s = lost_s
        self._heard_s: float | None = None
        self._forwarded = False
        self._held = False

    def forwarded(self) -> bool:
        """An autopilot message went to the ground stations: True when the held heartbeat goes now, behind it."""
        self._forwarded = True
        held, self._held = self._held, False
        return held

    def due(self, now_s: float) -> bool:
        """The heartbeat is due at ``now_s``: True when it goes now (the autopilot not heard), False when held."""
        self._mark(now_s)
        self._held = self._autopilot_heard(now_s)
        return not self._held

    def expired(self, now_s: float) -> bool:
        """True once, when a held heartbeat is to go alone (the autopilot fell silent while it waited)."""
        self._mark(now_s)
        if self._held and not self._autopilot_heard(now_s):
            self._held = False
            return True
        return False

    def _mark(self, now_s: float) -> None:
        if self._forwarded:
            self._heard_s, self._forwarded = now_s, False

    def _autopilot_heard(self, now_s: float) -> bool:
        return self._heard_s is not None and now_s - self._heard_s <= self.lost_s

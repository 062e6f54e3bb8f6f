"""Commands have an age (issue 18): the send time of each ground-station command, and which ones are too old.

Pure: no clock, no I/O; the daemon passes its monotonic clock ``now_s`` and, per sender, the TIMESYNC
offset it keeps with that sender (:class:`quadlink.mavlink.timesync.TimesyncEstimator`, peer minus local).

The stamp: a sender that knows the dialect sends ``COMMAND_STAMP(time_usec)`` immediately before the
command it stamps (the next packet of the same system and component, sequence number + 1 mod 256), its
own clock at the send. In our clock the command was sent at ``time_usec - offset``; its age at arrival is
``now - sent``. What becomes of a command (:class:`Verdict`):

* **ACCEPTED** — stamped and younger than ``max_command_age_s``, or from a sender that never stamps
  (QGroundControl's joystick, MAVSDK/MAVProxy scripted setpoints cannot carry a stamp: their age is taken
  as 0 at arrival, i.e. *arrival time*; their liveness still times out), or stamped before the first
  TIMESYNC exchange with that sender (arrival time too, counted as ``unsynced``).
* **STALE** — older than ``max_command_age_s`` (a delayed link): dropped.
* **UNPAIRED** — from a sender that stamped within ``stamp_memory_s`` but without its stamp (the stamp was
  lost): its age is unknown, dropped.
* **FUTURE** — sent more than ``max_future_s`` in our future (a bad clock estimate): dropped.
* **SUPERSEDED** — stamped before the newest accepted command of its sender (reordered on the link;
  compared in the sender's clock): dropped, a newer command is already in force.

Only accepted commands reach the motion source (the mode machine's link liveness and the operator input,
or the motion arbiter): over a sustained delay above the age, or a sustained loss, no command is accepted,
the vehicle holds after the mode machine's ``gcs_timeout_s`` (from the last accepted arrival) and lands
after ``gcs_land_timeout_s``; :meth:`CommandAgeFilter.fresh` tells whether the command in force is still
younger than the age (the daemon zeroes the operator input when not: within the age of its send time).
"""

from __future__ import annotations

import enum
import math
from collections import deque
from dataclasses import dataclass

Sender = tuple[int, int]   # (system id, component id)


class Verdict(enum.Enum):
    ACCEPTED = "accepted"
    STALE = "stale"
    UNPAIRED = "unpaired"
    FUTURE = "future"
    SUPERSEDED = "superseded"


@dataclass(frozen=True)
class CommandAgeParams:
    max_command_age_s: float = 0.5     # older commands are dropped (configs: links.max_command_age_s)
    max_future_s: float = 0.1          # a stamp this far ahead of our clock is a bad estimate: dropped
    stamp_memory_s: float = 5.0        # a sender that stamped within this long is a stamping sender

    def __post_init__(self) -> None:
        if not (self.max_command_age_s > 0 and self.max_future_s >= 0 and self.stamp_memory_s > 0):
            raise ValueError("command age: max_command_age_s and stamp_memory_s > 0, max_future_s >= 0")


@dataclass(frozen=True)
class CommandAge:
    """The filter's judgement of one command."""

    verdict: Verdict
    sent_s: float          # send time in our clock (the arrival time for an unstamped or unsynced command)
    age_s: float           # now - sent_s at arrival (0 for an arrival-time command)
    stamped: bool          # it came with its COMMAND_STAMP

    @property
    def accepted(self) -> bool:
        return self.verdict == Verdict.ACCEPTED


@dataclass(frozen=True)
class _Stamp:
    seq: int
    time_s: float          # sender's clock
    msgid: int
    arrival_s: float


@dataclass
class CommandAgeCounts:
    accepted: int = 0
    stamped: int = 0
    arrival_time: int = 0   # accepted with the arrival time (unstamped sender)
    unsynced: int = 0       # accepted with the arrival time (stamped, no TIMESYNC estimate yet)
    stale: int = 0
    unpaired: int = 0
    future: int = 0
    superseded: int = 0

    @property
    def dropped(self) -> int:
        return self.stale + self.unpaired + self.future + self.superseded


class CommandAgeFilter:
    """Ages the commands of every sender; feed it the stamps and the commands in arrival order."""

    def __init__(self, params: CommandAgeParams, history: int = 500) -> None:
        self.params = params
        self.counts = CommandAgeCounts()
        self.recent_age_s: deque[float] = deque(maxlen=history)   # ages of stamped commands (all verdicts)
        self._pending: dict[Sender, _Stamp] = {}
        self._last_stamp_s: dict[Sender, float] = {}
        self._newest_stamp_by_sender: dict[Sender, float] = {}   # newest accepted stamp, sender's clock
        self.newest_sent_s: float | None = None                  # send time of the command in force

    def on_stamp(self, sender: Sender, seq: int, time_usec: int, command_msgid: int, now_s: float) -> None:
        """A COMMAND_STAMP (packet sequence ``seq``) arrived at ``now_s``."""
        self._pending[sender] = _Stamp(seq % 256, time_usec * 1e-6, command_msgid, now_s)
        self._last_stamp_s[sender] = now_s

    def on_command(self, sender: Sender, seq: int, msgid: int, now_s: float,
                   peer_offset_s: float | None) -> CommandAge:
        """A command (packet sequence ``seq``, message id ``msgid``) arrived at ``now_s``; ``peer_offset_s`` is
        the sender's clock minus ours (TIMESYNC), None before the first exchange."""
        p = self.params
        stamp = self._pending.pop(sender, None)
        paired = stamp is not None and stamp.seq == (seq - 1) % 256 and stamp.msgid == msgid
        if not paired:
            last = self._last_stamp_s.get(sender)
            if last is not None and now_s - last <= p.stamp_memory_s:
                self.counts.unpaired += 1
                return CommandAge(Verdict.UNPAIRED, math.nan, math.nan, False)
            return self._accept(sender, CommandAge(Verdict.ACCEPTED, now_s, 0.0, False), "arrival_time")
        assert stamp is not None
        newest = self._newest_stamp_by_sender.get(sender)       # compared in the sender's clock: no offset error
        if newest is not None and stamp.time_s < newest:
            self.counts.superseded += 1
            return CommandAge(Verdict.SUPERSEDED, math.nan, math.nan, True)
        if peer_offset_s is None:
            self._newest_stamp_by_sender[sender] = stamp.time_s
            return self._accept(sender, CommandAge(Verdict.ACCEPTED, now_s, 0.0, True), "unsynced")
        sent_s = stamp.time_s - peer_offset_s
        age_s = now_s - sent_s
        self.recent_age_s.append(age_s)
        if age_s > p.max_command_age_s:
            self.counts.stale += 1
            return CommandAge(Verdict.STALE, sent_s, age_s, True)
        if age_s < -p.max_future_s:
            self.counts.future += 1
            return CommandAge(Verdict.FUTURE, sent_s, age_s, True)
        self._newest_stamp_by_sender[sender] = stamp.time_s
        return self._accept(sender, CommandAge(Verdict.ACCEPTED, sent_s, age_s, True), "stamped")

    def _accept(self, sender: Sender, age: CommandAge, kind: str) -> CommandAge:
        self.counts.accepted += 1
        setattr(self.counts, kind, getattr(self.counts, kind) + 1)
        if self.newest_sent_s is None or age.sent_s > self.newest_sent_s:
            self.newest_sent_s = age.sent_s
        return age

    def fresh(self, now_s: float) -> bool:
        """The command in force is younger than ``max_command_age_s`` (False before any)."""
        return self.newest_sent_s is not None and now_s - self.newest_sent_s <= self.params.max_command_age_s

    def age_percentile_s(self, q: float) -> float:
        """Percentile ``q`` (0-100) of the recent stamped commands' ages; NaN before any."""
        if not self.recent_age_s:
            return math.nan
        values = sorted(self.recent_age_s)
        k = min(max(q, 0.0), 100.0) / 100.0 * (len(values) - 1)
        lo, hi = math.floor(k), math.ceil(k)
        return values[lo] + (values[hi] - values[lo]) * (k - lo)

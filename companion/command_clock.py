"""The ground stations' command clock (issue 18): TIMESYNC with each sender, and the age of its commands.

The companion is the clock the ground stations' commands are aged against: it answers their TIMESYNC
requests with its clock, keeps one estimator of each sender's clock offset (:class:`GcsCommandClock` keeps at
most ``max_senders``: every port is hostile), and judges each command by its COMMAND_STAMP
(:mod:`companion.command_age`). The figures go to the ground station as NAMED_VALUE_INT / NAMED_VALUE_FLOAT
(``CMD_OK``, ``CMD_DROP``, ``CMD_STALE``, ``CMD_UNPAIR``, ``CMD_AGE50``, ``CMD_AGE99``; the demo report reads
them from the tlog).

Pure: the time, ``now_s`` (the daemon's monotonic clock), is an argument; replies are returned.
"""

from __future__ import annotations

import math
from typing import Any

from companion.command_age import CommandAge, CommandAgeFilter, CommandAgeParams, Sender
from quadlink.mavlink import mavlink
from quadlink.mavlink.timesync import NS, TimesyncConfig, TimesyncEstimator, answer_fields, is_request

MAX_GCS_SENDERS = 16        # TIMESYNC estimators kept for ground-station senders


def sender_of(msg: Any) -> Sender:
    return msg.get_srcSystem(), msg.get_srcComponent()


class GcsCommandClock:
    """``max_command_age_s``: older commands are dropped; ``timesync_max_rtt_s``: a TIMESYNC round trip above
    this is a stalled sample. ``sync`` (per sender) and ``age`` (the filter) are readable state."""

    def __init__(self, max_command_age_s: float, timesync_max_rtt_s: float, max_senders: int = MAX_GCS_SENDERS) -> None:
        self.sync: dict[Sender, TimesyncEstimator] = {}
        self._sync_cfg = TimesyncConfig(max_rtt_s=timesync_max_rtt_s)
        self._max_senders = max_senders
        self.age = CommandAgeFilter(CommandAgeParams(max_command_age_s=max_command_age_s))

    def on_timesync(self, msg: Any, now_s: float) -> Any | None:
        """A ground station's TIMESYNC: the answer to its request (our clock), or None (its answer to ours
        taken into its sender's offset)."""
        now_ns = int(now_s * NS)
        if is_request(msg.tc1):   # a ground station measuring its round trip to us
            return mavlink.MAVLink_timesync_message(*answer_fields(msg.ts1, now_ns))
        sender = sender_of(msg)
        sync = self.sync.get(sender)
        if sync is None:
            if len(self.sync) >= self._max_senders:
                return None
            sync = self.sync[sender] = TimesyncEstimator(self._sync_cfg)
        sync.on_response(msg.tc1, msg.ts1, now_ns)
        return None

    def on_stamp(self, msg: Any, now_s: float) -> None:
        """A COMMAND_STAMP: the send time of its sender's next command."""
        self.age.on_stamp(sender_of(msg), msg.get_seq(), msg.time_usec, msg.command_msgid, now_s)

    def on_command(self, msg: Any, now_s: float) -> CommandAge:
        """The age of the command ``msg`` arriving at ``now_s``, in its sender's clock offset when known."""
        sender = sender_of(msg)
        sync = self.sync.get(sender)
        offset_s = None if sync is None or sync.offset_ns is None else sync.offset_ns / NS
        return self.age.on_command(sender, msg.get_seq(), msg.get_msgId(), now_s, offset_s)

    def report(self, time_boot_ms: int) -> list[Any]:
        """The figures so far as NAMED_VALUE_* messages stamped ``time_boot_ms`` (the percentiles once known)."""
        c = self.age.counts
        out: list[Any] = [mavlink.MAVLink_named_value_int_message(time_boot_ms, name.encode(), value)
                          for name, value in (("CMD_OK", c.accepted), ("CMD_DROP", c.dropped),
                                              ("CMD_STALE", c.stale), ("CMD_UNPAIR", c.unpaired))]
        for name, q in (("CMD_AGE50", 50.0), ("CMD_AGE99", 99.0)):
            age = self.age.age_percentile_s(q)
            if math.isfinite(age):
                out.append(mavlink.MAVLink_named_value_float_message(time_boot_ms, name.encode(), age))
        return out

    def summary(self) -> str:
        """One line for the progress log."""
        c = self.age.counts
        return (f"commands {c.accepted} ok / {c.dropped} dropped (stale {c.stale}, unpaired {c.unpaired}), age p50 "
                f"{self.age.age_percentile_s(50) * 1e3:.0f} p99 {self.age.age_percentile_s(99) * 1e3:.0f} ms")

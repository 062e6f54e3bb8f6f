"""MAVLink TIMESYNC: clock offset and round trip to a peer, pure (times are arguments, in ns).

One implementation for every side of the stack (the companion with its autopilot, the ground station
with the companion). The exchange (MAVLink common.xml, TIMESYNC): the syncing side sends
``TIMESYNC(tc1=0, ts1=local_ns)``; the peer answers ``TIMESYNC(tc1=peer_ns, ts1=<echoed>)``. At the
answer's arrival ``now``, ``rtt = now - ts1`` and, assuming a symmetric path, the peer's clock at the
middle of the round trip gives the sample ``offset = tc1 - (ts1 + now) / 2`` (peer minus local).

The estimator follows the structure of PX4's timesync (facts only, written afresh):

* **round-trip gate**: samples with ``rtt > max_rtt_s`` are rejected (their offset error can be up to
  rtt / 2). PX4 uses 10 ms on a serial link; a ground link through the internet needs far more, so the
  bound is configuration (the autopilot link keeps 50 ms).
* **outliers**: once an estimate exists, a sample whose offset deviates from it by more than
  ``max_deviation_s`` is rejected; ``max_consecutive_outliers`` in a row mean the peer's clock jumped
  (a reboot) and the estimator restarts from the next sample.
* **offset filter**: the offset of the accepted sample with the *smallest round trip* among the last
  ``window`` (least queueing asymmetry: under jitter the shortest round trip is the least biased),
  rather than PX4's exponential average (which averages the asymmetry in).
* **round-trip filter**: an exponential average of the accepted round trips (``rtt_filtered_s``, gain
  ``rtt_gain``) for display, plus the recent samples (``recent_rtt_s``) for percentiles.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

NS = 1_000_000_000


@dataclass(frozen=True)
class TimesyncConfig:
    max_rtt_s: float = 2.0               # round trips above this are rejected (ground link over a WAN)
    max_deviation_s: float = 0.1         # offset jump that marks a sample as an outlier
    max_consecutive_outliers: int = 5    # this many in a row: the peer clock jumped; restart
    window: int = 10                     # accepted samples the min-round-trip offset is taken from
    rtt_gain: float = 0.2                # exponential average of the round trip
    history: int = 200                   # recent round trips kept for percentiles

    def __post_init__(self) -> None:
        if not (self.max_rtt_s > 0 and self.max_deviation_s > 0 and 0 < self.rtt_gain <= 1):
            raise ValueError("timesync: max_rtt_s, max_deviation_s > 0 and rtt_gain in (0, 1]")
        if min(self.max_consecutive_outliers, self.window, self.history) < 1:
            raise ValueError("timesync: max_consecutive_outliers, window and history must be >= 1")


def request_fields(now_ns: int) -> tuple[int, int]:
    """(tc1, ts1) of a request sent at ``now_ns``: ``mav.timesync_send(*request_fields(now))``."""
    return 0, now_ns


def answer_fields(request_ts1_ns: int, now_ns: int) -> tuple[int, int]:
    """(tc1, ts1) of the answer to a request (``tc1 == 0``) received at ``now_ns``: our clock, ts1 echoed."""
    return now_ns, request_ts1_ns


def is_request(tc1_ns: int) -> bool:
    return tc1_ns == 0


class TimesyncEstimator:
    """Offset (peer minus local clock) and round trip from TIMESYNC answers to our requests."""

    def __init__(self, cfg: TimesyncConfig | None = None) -> None:
        self.cfg = cfg or TimesyncConfig()
        self._window: deque[tuple[int, int]] = deque(maxlen=self.cfg.window)   # (rtt_ns, offset_ns)
        self.recent_rtt_s: deque[float] = deque(maxlen=self.cfg.history)
        self.offset_ns: int | None = None
        self.rtt_ns: int | None = None               # round trip of the sample the offset comes from
        self.last_rtt_s: float | None = None
        self.rtt_filtered_s: float | None = None
        self.accepted = self.rejected_rtt = self.rejected_outliers = self.resets = 0
        self._outliers_in_row = 0

    def on_response(self, tc1_ns: int, ts1_ns: int, now_ns: int) -> bool:
        """Use one answer to our request (``tc1`` the peer's clock, ``ts1`` our echoed stamp); True if used."""
        rtt_ns = now_ns - ts1_ns
        if tc1_ns <= 0 or rtt_ns < 0 or rtt_ns > self.cfg.max_rtt_s * NS:
            self.rejected_rtt += 1
            return False
        sample_ns = tc1_ns - (ts1_ns + now_ns) // 2
        if self.offset_ns is not None and abs(sample_ns - self.offset_ns) > self.cfg.max_deviation_s * NS:
            self._outliers_in_row += 1
            self.rejected_outliers += 1
            if self._outliers_in_row >= self.cfg.max_consecutive_outliers:
                self.reset()
                self.resets += 1
            return False
        self._outliers_in_row = 0
        self.accepted += 1
        rtt_s = rtt_ns / NS
        self.last_rtt_s = rtt_s
        self.recent_rtt_s.append(rtt_s)
        g = self.cfg.rtt_gain
        self.rtt_filtered_s = rtt_s if self.rtt_filtered_s is None else (1 - g) * self.rtt_filtered_s + g * rtt_s
        self._window.append((rtt_ns, sample_ns))
        self.rtt_ns, self.offset_ns = min(self._window)
        return True

    def reset(self) -> None:
        """Forget the estimate (the round-trip history stays: it is still the link's)."""
        self._window.clear()
        self.offset_ns = self.rtt_ns = None
        self._outliers_in_row = 0

    def to_remote_s(self, local_s: float) -> float | None:
        """A local-clock time in the peer's clock, or None before the first exchange."""
        return None if self.offset_ns is None else local_s + self.offset_ns / NS

    def to_local_s(self, remote_s: float) -> float | None:
        """A peer-clock time (e.g. a command's send stamp) in our clock, or None before the first exchange."""
        return None if self.offset_ns is None else remote_s - self.offset_ns / NS

    def rtt_percentile_s(self, q: float) -> float:
        """Percentile ``q`` (0-100) of the recent round trips; NaN before the first one."""
        if not self.recent_rtt_s:
            return math.nan
        values = sorted(self.recent_rtt_s)
        k = min(max(q, 0.0), 100.0) / 100.0 * (len(values) - 1)
        lo, hi = math.floor(k), math.ceil(k)
        return values[lo] + (values[hi] - values[lo]) * (k - lo)

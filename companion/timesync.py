"""TIMESYNC with the autopilot: the shared estimator (quadlink.mavlink.timesync) with this link's bounds.

The autopilot is on a local serial/UDP link, so a round trip above 50 ms is a stalled sample.
"""

from __future__ import annotations

from quadlink.mavlink.timesync import TimesyncConfig, TimesyncEstimator


class TimeSync(TimesyncEstimator):
    def __init__(self, max_rtt_ns: int = 50_000_000, window: int = 10) -> None:
        super().__init__(TimesyncConfig(max_rtt_s=max_rtt_ns * 1e-9, window=window))

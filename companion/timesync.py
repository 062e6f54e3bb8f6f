"""TIMESYNC with the autopilot: the shared estimator (quadlink.mavlink.timesync) with this link's bounds.

The autopilot is on a local serial/UDP link, so a round trip above 50 ms is a stalled sample.
"""

from __future__ import annotations

import logging
from typing import Any

from quadlink.mavlink import mavlink
from quadlink.mavlink.timesync import TimesyncConfig, TimesyncEstimator

log = logging.getLogger("companion.daemon")


class TimeSync(TimesyncEstimator):
    def __init__(self, max_rtt_ns: int = 50_000_000, window: int = 10) -> None:
        super().__init__(TimesyncConfig(max_rtt_s=max_rtt_ns * 1e-9, window=window))

    def on_message(self, msg: Any, now_s: float) -> Any | None:
        """The autopilot's TIMESYNC at ``now_s`` (our monotonic clock): the answer to its request (our clock),
        or None (its answer to ours, taken into the estimate)."""
        now_ns = int(now_s * 1e9)
        if msg.tc1 == 0:
            return mavlink.MAVLink_timesync_message(now_ns, msg.ts1)
        if self.on_response(msg.tc1, msg.ts1, now_ns):
            log.debug("timesync offset %.3f ms rtt %.3f ms", self.offset_ns * 1e-6,  # type: ignore[operator]
                      self.rtt_ns * 1e-6)  # type: ignore[operator]
        return None


class AutopilotTime:
    """The autopilot's time (s; SITL: simulated time) as the companion knows it: it stamps everything that
    describes the vehicle (setpoints, odometry, feedback). Known from the last IMU sample and the last camera
    frame, each with the monotonic wall time it arrived (``*_wall_s``); a camera that stamps in the companion's
    clock (``camera_stamps == "local"``) is mapped through the autopilot's TIMESYNC (``timesync``)."""

    def __init__(self, timesync: TimeSync, camera_stamps: str, start_wall_s: float) -> None:
        self.timesync = timesync
        self._camera_local = camera_stamps == "local"
        self._start_wall_s = start_wall_s
        self.imu_stamp_s: float | None = None
        self.imu_wall_s: float | None = None
        self.frame_stamp_s: float | None = None
        self.frame_wall_s: float | None = None

    def on_imu(self, stamp_s: float, wall_s: float) -> None:
        self.imu_stamp_s, self.imu_wall_s = stamp_s, wall_s

    def on_frame(self, camera_stamp_s: float, wall_s: float) -> float:
        """A camera frame stamped ``camera_stamp_s`` arrived at ``wall_s``: its stamp in the autopilot's time."""
        stamp = camera_stamp_s
        if self._camera_local:
            remote = self.timesync.to_remote_s(camera_stamp_s)
            stamp = camera_stamp_s if remote is None else remote
        self.frame_stamp_s, self.frame_wall_s = stamp, wall_s
        return stamp

    def estimate_s(self, wall_s: float) -> float:
        """The autopilot's time at ``wall_s`` without a fresh sample: the last IMU or frame stamp plus the wall
        time since (before either, the wall time since the start)."""
        if self.imu_stamp_s is not None and self.imu_wall_s is not None:
            return self.imu_stamp_s + (wall_s - self.imu_wall_s)
        if self.frame_stamp_s is not None and self.frame_wall_s is not None:
            return self.frame_stamp_s + (wall_s - self.frame_wall_s)
        return wall_s - self._start_wall_s

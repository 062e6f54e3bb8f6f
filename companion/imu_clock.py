"""The autopilot's IMU as the companion's fast clock (pure: times are arguments).

* :func:`imu_sample`: a HIGHRES_IMU checked before anything uses it (finite values, a sane stamp).
* :class:`ImuClock` paces TELEOP_FEEDBACK on the IMU's stamps at ``feedback_rate_hz`` while samples arrive,
  and says when they have stopped (:meth:`ImuClock.silent`: the daemon's scheduler then paces it on wall
  time); it also holds the policy of the daemon's bounded wait for the IMU to catch up with a camera frame
  (the daemon drains the link while it waits): wait only when the IMU flows, and stop waiting for good once
  the waits keep timing out (a producer that emits the IMU later than the frames on this setup: the attitude
  filter extrapolates the last few ms rather than every frame waiting).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion.scheduler import StampTicker

log = logging.getLogger("companion.daemon")

IMU_SILENT_S = 0.1          # no HIGHRES_IMU for this long: feedback paced on wall time instead
IMU_LAG_LIMIT = 30          # consecutive IMU-wait timeouts after which the daemon stops waiting
IMU_WAIT_MAX_GAP_S = 0.2    # a frame this far ahead of the last IMU sample: the IMU is not flowing, no wait
MAX_STAMP_US = 2**53        # an autopilot boot time beyond this (285 years, and float64's exact integers) is garbage


@dataclass(frozen=True)
class ImuSample:
    """One HIGHRES_IMU sample: its stamp (s, the autopilot's time), gyro (rad/s) and accelerometer (m/s^2) in Q."""

    stamp_s: float
    gyro_q_rad_s: NDArray[np.float64]
    accel_q_m_s2: NDArray[np.float64]


def imu_sample(msg: Any) -> ImuSample | None:
    """The sample of a HIGHRES_IMU, or None when a value is not finite or the stamp is garbage."""
    values = (msg.xgyro, msg.ygyro, msg.zgyro, msg.xacc, msg.yacc, msg.zacc)
    if not all(map(math.isfinite, values)) or msg.time_usec > MAX_STAMP_US:   # scalar checks: cheaper at 500 Hz
        return None   # (fuzzing found: a uint64 stamp near 2**64 made the feedback's time_usec overflow when packed)
    return ImuSample(msg.time_usec * 1e-6, np.array(values[:3]), np.array(values[3:]))


class ImuClock:
    """``feedback_rate_hz``: TELEOP_FEEDBACK's rate; ``imu_wait_s``: the longest wait for the IMU on one frame;
    ``imu_slack_s``: how far the IMU may lag a frame's stamp without a wait."""

    def __init__(self, feedback_rate_hz: float, imu_wait_s: float, imu_slack_s: float) -> None:
        self._feedback = StampTicker(1.0 / feedback_rate_hz)
        self.imu_wait_s, self.imu_slack_s = imu_wait_s, imu_slack_s
        self._wait_misses = 0

    def feedback_due(self, stamp_s: float) -> bool:
        """A TELEOP_FEEDBACK is due at this IMU stamp."""
        return self._feedback.due(stamp_s)

    @staticmethod
    def silent(now_s: float, imu_wall_s: float | None) -> bool:
        """No IMU sample has arrived (wall time ``imu_wall_s``) for :data:`IMU_SILENT_S` at ``now_s``."""
        return imu_wall_s is None or now_s - imu_wall_s > IMU_SILENT_S

    def should_wait(self, frame_stamp_s: float, imu_stamp_s: float | None) -> bool:
        """Wait (up to ``imu_wait_s``) for the IMU to reach a frame stamped ``frame_stamp_s``? Only while it
        flows, and not once the waits have kept timing out."""
        return imu_stamp_s is not None and not frame_stamp_s - imu_stamp_s > IMU_WAIT_MAX_GAP_S and \
            self._wait_misses < IMU_LAG_LIMIT

    def caught_up(self, frame_stamp_s: float, imu_stamp_s: float | None) -> bool:
        """The IMU has reached the frame (within the slack): the wait ends."""
        return imu_stamp_s is not None and not imu_stamp_s < frame_stamp_s - self.imu_slack_s   # (NaN: no wait)

    def on_wait_timeout(self) -> None:
        self._wait_misses += 1
        if self._wait_misses == IMU_LAG_LIMIT:
            log.info("IMU lags the camera frames by more than %.0f ms: not waiting for it any more",
                     self.imu_slack_s * 1e3)

    def on_caught_up(self) -> None:
        self._wait_misses = 0

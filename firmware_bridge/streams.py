"""Telemetry stream scheduling: which message is due when, and SET_MESSAGE_INTERVAL (pure, time as argument).

An interval of 0 means "every source sample" (HIGHRES_IMU per IMU sample), a negative one "off".
SET_MESSAGE_INTERVAL is validated at the boundary (issue 16): ``interval_us`` -1 = off, 0 = default,
otherwise it must be finite and at most :data:`MAX_INTERVAL_S`; anything else is DENIED and changes
nothing. HEARTBEAT can never be silenced or slowed below :data:`HEARTBEAT_MAX_INTERVAL_S` (GCSs time the
link out on it).
"""

from __future__ import annotations

import math

from quadlink.mavlink import mavlink

STREAM_DEFAULT_INTERVAL_S: dict[int, float] = {
    mavlink.MAVLINK_MSG_ID_HEARTBEAT: 1.0,
    mavlink.MAVLINK_MSG_ID_SYS_STATUS: 1.0,
    mavlink.MAVLINK_MSG_ID_SYSTEM_TIME: 1.0,
    mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 1.0,
    mavlink.MAVLINK_MSG_ID_ATTITUDE: 0.02,
    mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: -1.0,  # off unless requested
    mavlink.MAVLINK_MSG_ID_HIGHRES_IMU: 0.0,  # 0: every IMU sample
    mavlink.MAVLINK_MSG_ID_BATTERY_STATUS: -1.0,
    mavlink.MAVLINK_MSG_ID_ALTITUDE: 0.05,   # the barometer-fused height (the companion's ceiling takes it)
}
IMU_STREAMS = (mavlink.MAVLINK_MSG_ID_HIGHRES_IMU, mavlink.MAVLINK_MSG_ID_ATTITUDE,
               mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION)
MAX_INTERVAL_S = 60.0  # the slowest stream a SET_MESSAGE_INTERVAL may ask for
HEARTBEAT_MAX_INTERVAL_S = 1.0  # MAVLink's 1 Hz heartbeat: faster on request, never slower
REQUESTED_DEFAULT_S = 1.0  # "default" (0 us) for a stream that is off by default
REQUESTED_DEFAULT_IMU_S = 0.02
US_PER_S = 1e6


class StreamScheduler:
    """Per-message intervals and phase-keeping due checks."""

    def __init__(self) -> None:
        self.interval_s: dict[int, float] = dict(STREAM_DEFAULT_INTERVAL_S)
        self._last_s: dict[int, float] = {}

    def due(self, msg_id: int, now_s: float) -> bool:
        """Whether ``msg_id`` should be sent at ``now_s`` (and, if so, it counts as sent)."""
        interval = self.interval_s.get(msg_id, -1.0)
        if interval < 0:
            return False
        last = self._last_s.get(msg_id)
        if last is not None and now_s - last < interval - 1e-6 and now_s >= last:
            return False
        # keep the phase (no drift) unless we fell far behind
        self._last_s[msg_id] = now_s if last is None or now_s - last > 2 * interval or now_s < last \
            else last + interval
        return True

    def set_interval(self, msg_id: float, interval_us: float) -> int:
        """MAV_CMD_SET_MESSAGE_INTERVAL (param1 message id, param2 interval in us) -> its MAV_RESULT."""
        if not math.isfinite(msg_id) or not float(msg_id).is_integer() or int(msg_id) not in self.interval_s:
            return mavlink.MAV_RESULT_UNSUPPORTED
        mid = int(msg_id)
        if not math.isfinite(interval_us):
            return mavlink.MAV_RESULT_DENIED
        if interval_us == -1.0:
            interval_s = -1.0
        elif interval_us == 0.0:
            interval_s = STREAM_DEFAULT_INTERVAL_S[mid]
            if interval_s < 0:
                interval_s = REQUESTED_DEFAULT_IMU_S if mid in IMU_STREAMS else REQUESTED_DEFAULT_S
        elif 0.0 < interval_us <= MAX_INTERVAL_S * US_PER_S:
            interval_s = interval_us / US_PER_S
        else:
            return mavlink.MAV_RESULT_DENIED  # other negatives, absurdly long intervals
        if mid == mavlink.MAVLINK_MSG_ID_HEARTBEAT and not 0.0 <= interval_s <= HEARTBEAT_MAX_INTERVAL_S:
            return mavlink.MAV_RESULT_DENIED  # never silence or slow the heartbeat
        self.interval_s[mid] = interval_s
        return mavlink.MAV_RESULT_ACCEPTED

"""The bridge's attitude estimate: ``quadlink.attitude.AttitudeFilter`` (Mahony, with gyro-bias
estimation) on the board's 500 Hz IMU, plus a heading offset.

One implementation of the filter math lives in ``perception`` (STYLE.md: no copies across packages);
this adapter adds what the bridge needs: the filter's time constant as a parameter (``BRG_ATT_TAU``,
proportional gain 1/tau), Euler angles and body rates for ATTITUDE, and a yaw re-anchored to the
companion's odometry heading (:meth:`set_yaw`), so LOCAL_NED setpoints are rotated with the
companion's heading while yaw between odometry messages follows the gyro, and a tilt pulled toward the
odometry's (:meth:`BridgeAttitude.correct_tilt`, ``BRG_ATT_ODOM_TAU``) while it comes.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from quadlink.attitude import AttitudeConfig, AttitudeFilter
from quadlink.frames import wrap_pi

ODOM_TILT_HOLD_S = 0.3     # after an odometry tilt, the accelerometer's correction waits this long (its loss)
ODOM_TILT_MAX_DT_S = 0.1   # an odometry interval counts at most this much (a gap does not snap the tilt)


@dataclass(frozen=True)
class AttitudeEstimate:
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    rollspeed_rad_s: float  # body rates (FRD): low-passed, bias-corrected gyro
    pitchspeed_rad_s: float
    yawspeed_rad_s: float


class BridgeAttitude:
    def __init__(self, tau_s: float = 1.0) -> None:
        self._filter = AttitudeFilter(AttitudeConfig(kp_rad_s=1.0 / tau_s))
        self._yaw_offset_rad = 0.0
        self._estimate = AttitudeEstimate(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        self._last_tilt_s: float | None = None

    def set_tau(self, tau_s: float) -> None:
        self._filter.config = dataclasses.replace(self._filter.config, kp_rad_s=1.0 / tau_s)

    def update(self, stamp_s: float, gyro_q_rad_s: np.ndarray, accel_q_m_s2: np.ndarray) -> AttitudeEstimate:
        """One IMU sample at board time ``stamp_s``: body rates (rad/s) and specific force (m/s^2), FRD."""
        self._filter.update(stamp_s, gyro_q_rad_s, accel_q_m_s2)
        e = self._filter.estimate(stamp_s)
        w = e.omega_q_rad_s
        self._estimate = AttitudeEstimate(e.roll_rad, e.pitch_rad, wrap_pi(e.yaw_gyro_rad + self._yaw_offset_rad),
                                          float(w[0]), float(w[1]), float(w[2]))
        return self._estimate

    def correct_tilt(self, stamp_s: float, roll_rad: float, pitch_rad: float, tau_s: float) -> bool:
        """Pull the tilt toward a visual odometry's roll and pitch with time constant ``tau_s`` (per message: the
        share of the interval since the last one), the accelerometer's correction held off meanwhile (for
        ODOM_TILT_HOLD_S after each): the accelerometer gives gravity's direction only when the vehicle does not
        accelerate; in a multirotor's accelerating flight it gives the thrust axis, and a 1 s filter on it pulls the
        tilt toward level by several degrees in a push or a brake. False if not applied (``tau_s`` <= 0, a
        reference far off or not finite, before the first IMU sample)."""
        if tau_s <= 0.0:
            return False
        dt = ODOM_TILT_MAX_DT_S if self._last_tilt_s is None else min(max(stamp_s - self._last_tilt_s, 0.0),
                                                                          ODOM_TILT_MAX_DT_S)
        applied = self._filter.correct_tilt(stamp_s, roll_rad, pitch_rad, dt / tau_s, ODOM_TILT_HOLD_S, dt)
        if applied:
            self._last_tilt_s = stamp_s
            e = self._filter.estimate(stamp_s)
            self._estimate = dataclasses.replace(self._estimate, roll_rad=e.roll_rad, pitch_rad=e.pitch_rad)
        return applied

    def set_yaw(self, yaw_rad: float) -> None:
        """Re-anchor the heading (the odometry's yaw is the reference of the local frame)."""
        self._yaw_offset_rad = wrap_pi(yaw_rad - (self._estimate.yaw_rad - self._yaw_offset_rad))
        self._estimate = dataclasses.replace(self._estimate, yaw_rad=wrap_pi(yaw_rad))

    @property
    def yaw_rad(self) -> float:
        return self._estimate.yaw_rad

    @property
    def estimate(self) -> AttitudeEstimate:
        return self._estimate

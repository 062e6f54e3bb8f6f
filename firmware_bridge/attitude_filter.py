"""A small complementary attitude filter on the board's IMU (the bridge's own ATTITUDE estimate).

``perception`` had no attitude filter when the bridge was written, so this one lives here: gyro
integration of the ZYX Euler angles, corrected towards the accelerometer's gravity direction with a
time constant ``tau_s`` when the specific force is close to 1 g (paper 000 section IV uses the
same kind of filter on the board). Yaw is gyro-integrated only; the bridge re-anchors it to the
companion's odometry yaw when ODOMETRY arrives (:meth:`set_yaw`), so LOCAL_NED setpoints are
rotated with the companion's heading.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from quadlink.frames import GRAVITY_M_S2, wrap_pi


@dataclass(frozen=True)
class AttitudeEstimate:
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    rollspeed_rad_s: float  # body rates (FRD), from the gyro
    pitchspeed_rad_s: float
    yawspeed_rad_s: float


class ComplementaryAttitudeFilter:
    def __init__(self, tau_s: float = 1.0, accel_gate_fraction: float = 0.15) -> None:
        self.tau_s = tau_s
        self.accel_gate_fraction = accel_gate_fraction
        self.roll_rad = 0.0
        self.pitch_rad = 0.0
        self.yaw_rad = 0.0
        self._rates = (0.0, 0.0, 0.0)
        self._initialised = False

    def update(self, dt_s: float, gyro_q_rad_s: np.ndarray, accel_q_m_s2: np.ndarray) -> AttitudeEstimate:
        """One IMU sample: body rates (rad/s, FRD) and specific force (m/s^2, FRD)."""
        p, q, r = (float(x) for x in gyro_q_rad_s)
        fx, fy, fz = (float(x) for x in accel_q_m_s2)
        norm = math.sqrt(fx * fx + fy * fy + fz * fz)
        if not self._initialised and norm > 0.5 * GRAVITY_M_S2:
            # first sample: take roll and pitch straight from gravity
            self.roll_rad = math.atan2(-fy, -fz)
            self.pitch_rad = math.atan2(fx, math.hypot(fy, fz))
            self._initialised = True
        dt_s = min(max(dt_s, 0.0), 0.05)
        phi, theta = self.roll_rad, self.pitch_rad
        cos_theta = math.cos(theta) if abs(math.cos(theta)) > 1e-3 else 1e-3
        # ZYX Euler kinematics
        phi_dot = p + (q * math.sin(phi) + r * math.cos(phi)) * math.tan(theta)
        theta_dot = q * math.cos(phi) - r * math.sin(phi)
        psi_dot = (q * math.sin(phi) + r * math.cos(phi)) / cos_theta
        phi += phi_dot * dt_s
        theta += theta_dot * dt_s
        self.yaw_rad = wrap_pi(self.yaw_rad + psi_dot * dt_s)
        if abs(norm - GRAVITY_M_S2) < self.accel_gate_fraction * GRAVITY_M_S2 and self.tau_s > 0:
            k = dt_s / (self.tau_s + dt_s)
            phi += k * wrap_pi(math.atan2(-fy, -fz) - phi)
            theta += k * (math.atan2(fx, math.hypot(fy, fz)) - theta)
        self.roll_rad = wrap_pi(phi)
        self.pitch_rad = min(max(theta, -math.pi / 2), math.pi / 2)
        self._rates = (p, q, r)
        return self.estimate

    def set_yaw(self, yaw_rad: float) -> None:
        self.yaw_rad = wrap_pi(yaw_rad)

    @property
    def estimate(self) -> AttitudeEstimate:
        return AttitudeEstimate(self.roll_rad, self.pitch_rad, self.yaw_rad, *self._rates)

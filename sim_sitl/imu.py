"""IMU model of the MK board (pure; rng injected): specific force and body rates -> noisy SI values.

Quantisation to 10-bit ADC counts and saturation happen in ``ImuSample.from_si`` (the wire codec),
so the SITL and the bridge share one definition of the counts. On top of the true values this model
adds a random-walk bias (initial sigma + density * sqrt(dt) per sample), white noise and motor
vibration (a sinusoid per rotor at its propeller frequency, amplitude growing with thrust, sampled
at 500 Hz so it aliases as on the real board).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from quadlink.frames import GRAVITY_M_S2
from sim_sitl.config import ImuNoiseConfig

G_NED = np.array([0.0, 0.0, GRAVITY_M_S2])


@dataclass(frozen=True)
class ImuReading:
    """One IMU sample in SI units, body FRD axes."""

    t_s: float
    accel_q_m_s2: NDArray[np.float64]  # specific force: (0, 0, -g) at rest, level
    gyro_q_rad_s: NDArray[np.float64]


def specific_force_q(R_ned_q: NDArray[np.float64], a_ned_m_s2: NDArray[np.float64]) -> NDArray[np.float64]:
    """What an ideal accelerometer reads: f = R^T (a - g), g = (0, 0, +g) in NED."""
    return np.asarray(R_ned_q).T @ (np.asarray(a_ned_m_s2) - G_NED)


class ImuModel:
    def __init__(self, cfg: ImuNoiseConfig, rng: np.random.Generator, max_thrust_n: float) -> None:
        self.cfg = cfg
        self.rng = rng
        self.max_thrust_n = max_thrust_n
        self.accel_bias_m_s2 = rng.normal(0.0, cfg.accel_bias_init_m_s2, 3)
        self.gyro_bias_rad_s = rng.normal(0.0, cfg.gyro_bias_init_rad_s, 3)
        self._phase_rad = rng.uniform(0.0, 2.0 * math.pi, 4)
        self._vib_dir = rng.normal(size=(4, 3))
        self._vib_dir /= np.linalg.norm(self._vib_dir, axis=1, keepdims=True)
        self._normals = np.empty((0, 12))
        self._next = 0

    def _draw(self) -> np.ndarray:
        """12 standard normals (bias walks, white noise); drawn in blocks, the same sequence as one by one."""
        if self._next >= len(self._normals):
            self._normals = self.rng.standard_normal((512, 12))
            self._next = 0
        row = self._normals[self._next]
        self._next += 1
        return row

    def measure(self, t_s: float, dt_s: float, R_ned_q: NDArray[np.float64], a_ned_m_s2: NDArray[np.float64],
                omega_q_rad_s: NDArray[np.float64], motor_thrust_n: NDArray[np.float64]) -> ImuReading:
        """One sample; ``dt_s`` is the time since the previous one (bias walk and rotor phase)."""
        c = self.cfg
        n = self._draw()
        sqrt_dt = math.sqrt(dt_s)
        self.accel_bias_m_s2 = self.accel_bias_m_s2 + (c.accel_bias_walk_m_s2_sqrt_s * sqrt_dt) * n[0:3]
        self.gyro_bias_rad_s = self.gyro_bias_rad_s + (c.gyro_bias_walk_rad_s_sqrt_s * sqrt_dt) * n[3:6]
        frac = np.clip(np.asarray(motor_thrust_n, dtype=float) / self.max_thrust_n, 0.0, 1.0)
        # propeller speed ~ sqrt(thrust)
        self._phase_rad = (self._phase_rad + 2.0 * math.pi * c.rotor_hz_at_full_thrust * np.sqrt(frac) * dt_s) % (
            2.0 * math.pi)
        vib = (frac * np.sin(self._phase_rad)) @ self._vib_dir
        accel = specific_force_q(R_ned_q, a_ned_m_s2) + self.accel_bias_m_s2 + \
            c.accel_noise_m_s2 * n[6:9] + c.vibration_accel_m_s2 * vib
        gyro = np.asarray(omega_q_rad_s, dtype=float) + self.gyro_bias_rad_s + \
            c.gyro_noise_rad_s * n[9:12] + c.vibration_gyro_rad_s * vib
        return ImuReading(t_s, accel, gyro)

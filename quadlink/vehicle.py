"""The vehicle description shared by the SITL, the bridge and the companion (configs/vehicle.yaml).

One file describes the MK-Quadro: its mass and geometry (SITL physics, bridge gravity
compensation), its motors, its IMU scales (SITL quantisation, bridge conversion of raw counts) and
the RGB-D camera mount ``R_qc`` / ``p_qc_m`` (SITL rendering, companion perception).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from quadlink.config import find_config, load_config
from quadlink.frames import GRAVITY_M_S2


@dataclass(frozen=True)
class MotorConfig:
    max_thrust_n: float = 5.0  # per motor, N (T/W of 2 for the 1 kg MK-Quadro)
    time_constant_s: float = 0.04  # first-order lag of thrust to command, s
    drag_torque_per_thrust_m: float = 0.016  # rotor drag torque / thrust, m
    idle_fraction: float = 0.08  # thrust fraction when armed at zero command


@dataclass(frozen=True)
class ImuConfig:
    """Raw 10-bit ADC counts -> SI; ``value = (count - zero_count) * lsb``."""

    accel_lsb_m_s2: float = 0.0039 * GRAVITY_M_S2  # 0.0039 g per count, +-2 g
    gyro_lsb_rad_s: float = float(np.deg2rad(0.586))  # 0.586 deg/s per count, +-300 deg/s
    zero_count: int = 512  # 10-bit ADC mid-scale
    rate_hz: float = 500.0


@dataclass(frozen=True)
class CameraConfig:
    """Asus-Xtion-like RGB-D camera. ``R_qc`` maps camera optical (x right, y down, z forward) to body FRD.

    The default is Rz(45 deg) Ry(-30 deg) [optical->FRD] Rz(90 deg): 45 deg right, 30 deg down, portrait.
    """

    R_qc: tuple[tuple[float, float, float], tuple[float, float, float], tuple[float, float, float]] = (
        (-0.353553, 0.707107, 0.612372),
        (-0.353553, -0.707107, 0.612372),
        (0.866025, 0.0, 0.5),
    )
    p_qc_m: tuple[float, float, float] = (0.08, 0.08, 0.05)
    width_px: int = 320
    height_px: int = 240
    hfov_deg: float = 58.0
    vfov_deg: float = 45.0
    rate_hz: float = 30.0
    min_range_m: float = 0.5
    max_range_m: float = 3.5

    def __post_init__(self) -> None:
        R = np.asarray(self.R_qc, dtype=float)
        # entries of a rotation lie in [-1, 1]: checked first, so a huge one is refused without overflowing R R^T
        # (the config fuzz soak: 1.3e154 in R_qc raised numpy's overflow warning instead of the config error)
        if not np.all(np.abs(R) <= 1.0 + 1e-4) or not np.allclose(R @ R.T, np.eye(3), atol=1e-4) \
                or np.linalg.det(R) < 0:
            raise ValueError("R_qc is not a rotation matrix (orthonormal, det +1)")

    @property
    def R_qc_matrix(self) -> np.ndarray:
        return np.asarray(self.R_qc, dtype=float)

    @property
    def p_qc(self) -> np.ndarray:
        return np.asarray(self.p_qc_m, dtype=float)


@dataclass(frozen=True)
class BatteryConfig:
    cells: int = 3
    capacity_mah: float = 2200.0
    full_cell_v: float = 4.2
    empty_cell_v: float = 3.3

    def __post_init__(self) -> None:
        if not 1 <= self.cells <= 12:
            raise ValueError(f"cells must be 1..12, got {self.cells}")
        if not 0 < self.empty_cell_v < self.full_cell_v:
            raise ValueError("need 0 < empty_cell_v < full_cell_v")
        if not self.capacity_mah > 0:
            raise ValueError("capacity_mah must be > 0")


@dataclass(frozen=True)
class VehicleConfig:
    name: str = "MK-Quadro"
    mass_kg: float = 1.0
    arm_length_m: float = 0.25  # centre to motor; 0.5 m motor-to-motor span
    frame: Literal["x", "plus"] = "x"
    propeller_diameter_m: float = 0.254
    inertia_kg_m2: tuple[float, float, float] = (0.0075, 0.0075, 0.013)
    linear_drag_n_s_m: tuple[float, float, float] = (0.25, 0.25, 0.35)
    motor: MotorConfig = field(default_factory=MotorConfig)
    imu: ImuConfig = field(default_factory=ImuConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    battery: BatteryConfig = field(default_factory=BatteryConfig)

    @property
    def max_total_thrust_n(self) -> float:
        return 4.0 * self.motor.max_thrust_n

    @property
    def hover_thrust_fraction(self) -> float:
        return self.mass_kg * GRAVITY_M_S2 / self.max_total_thrust_n


def load_vehicle(name_or_path: str | Path = "vehicle") -> VehicleConfig:
    """Load ``configs/vehicle.yaml`` (or the given file) into a :class:`VehicleConfig`."""
    return load_config(find_config(str(name_or_path)), VehicleConfig)

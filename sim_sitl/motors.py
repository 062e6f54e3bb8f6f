"""Rotor geometry, mixing and the first-order motor lag (pure; no pybullet).

Body frame Q is FRD. A rotor at ``(x, y)`` producing thrust ``T`` (along -z) gives the torque
``r x F = (-y T, x T, 0)``; its drag torque about z is ``spin * k_d * T`` where ``spin = +1`` for a
rotor whose reaction torque yaws the body to the right (positive FRD yaw).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from quadlink.vehicle import VehicleConfig


@dataclass(frozen=True)
class RotorLayout:
    positions_q_m: NDArray[np.float64]  # 4 x 3, FRD
    spin: NDArray[np.float64]  # 4, +1 / -1 (sign of the yaw reaction torque)
    allocation: NDArray[np.float64]  # 4x4: [T, tau_x, tau_y, tau_z] = allocation @ thrusts
    allocation_inv: NDArray[np.float64]


def rotor_layout(vehicle: VehicleConfig) -> RotorLayout:
    """Rotor positions and the allocation matrix for the X or + frame (MK order: front, rear, right, left)."""
    L = vehicle.arm_length_m
    if vehicle.frame == "x":
        angles = [math.radians(a) for a in (45.0, -135.0, 135.0, -45.0)]  # FR, RL, RR, FL
        spin = np.array([1.0, 1.0, -1.0, -1.0])  # diagonal pairs turn the same way
    else:
        angles = [math.radians(a) for a in (0.0, 180.0, 90.0, -90.0)]  # front, rear, right, left
        spin = np.array([1.0, 1.0, -1.0, -1.0])
    pos = np.array([[L * math.cos(a), L * math.sin(a), 0.0] for a in angles])
    k_d = vehicle.motor.drag_torque_per_thrust_m
    A = np.vstack([np.ones(4), -pos[:, 1], pos[:, 0], spin * k_d])
    return RotorLayout(pos, spin, A, np.linalg.inv(A))


def mix(layout: RotorLayout, thrust_n: float, torque_q_nm: NDArray[np.float64], min_thrust_n: float,
        max_thrust_n: float) -> NDArray[np.float64]:
    """Per-motor thrust commands for a collective thrust and body torque, saturated per motor.

    When the torque demand does not fit, the collective is shifted first (attitude has priority over
    altitude, as flight controllers do) and then the torques are scaled down.
    """
    tau = np.asarray(torque_q_nm, dtype=float)
    diff = layout.allocation_inv @ np.array([0.0, tau[0], tau[1], tau[2]])
    base = thrust_n / 4.0
    span = diff.max() - diff.min()
    room = max_thrust_n - min_thrust_n
    if span > room:  # torque alone exceeds the motors' range: scale it down
        diff = diff * (room / span)
    lo, hi = base + diff.min(), base + diff.max()
    if hi > max_thrust_n:
        base -= hi - max_thrust_n
    elif lo < min_thrust_n:
        base += min_thrust_n - lo
    return np.clip(base + diff, min_thrust_n, max_thrust_n)


def motor_lag(thrust_n: NDArray[np.float64], command_n: NDArray[np.float64], time_constant_s: float,
              dt_s: float) -> NDArray[np.float64]:
    """First-order lag, discretised exactly: T <- T + (1 - exp(-dt/tau)) (T_cmd - T)."""
    if time_constant_s <= 0.0:
        return np.array(command_n, dtype=float)
    alpha = 1.0 - math.exp(-dt_s / time_constant_s)
    return thrust_n + alpha * (command_n - thrust_n)


def body_wrench(layout: RotorLayout, thrusts_n: NDArray[np.float64]) -> tuple[float, NDArray[np.float64]]:
    """Total thrust (N, along -z of Q) and torque (N m, Q) produced by the rotors."""
    w = layout.allocation @ thrusts_n
    return float(w[0]), w[1:]

"""Rotations and frame conversions, in one place (DESIGN.md "Frames and units").

Conventions used everywhere in quadlink:

* Body Q, horizontal H, device D are NED/FRD-like (x forward, y right, z down).
* Euler angles are aerospace ZYX (yaw psi, then pitch theta, then roll phi):
  ``R_wq = Rz(yaw) @ Ry(pitch) @ Rx(roll)`` maps body vectors into the NED world.
* ``R_ab`` maps vectors expressed in frame b into frame a (``v_a = R_ab @ v_b``).
* Quaternions: **this module and MAVLink use [w, x, y, z]**; scipy uses [x, y, z, w] —
  convert only through :func:`quat_wxyz_from_R` / :func:`R_from_quat_wxyz`.
* The world frame W of the papers is NWU; on every interface quadlink uses local NED.
  :data:`R_NED_NWU` converts once, at the edge (it is its own inverse: Rx(pi)).
* The group math (exp/log maps, rigid-transform inverse, geodesic angles) is in :mod:`quadlink.lie`.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

Vec3 = NDArray[np.float64]
Mat3 = NDArray[np.float64]

#: NWU -> NED (x stays, y and z flip); equals the paper's Rx(pi) and is its own inverse. The same matrix
#: maps body FLU (pybullet's) to FRD: :data:`R_FRD_FLU`.
R_NED_NWU: Mat3 = np.diag([1.0, -1.0, -1.0])
R_FRD_FLU: Mat3 = R_NED_NWU

GRAVITY_M_S2 = 9.80665


def Rx(angle_rad: float) -> Mat3:
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def Ry(angle_rad: float) -> Mat3:
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def Rz(angle_rad: float) -> Mat3:
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def R_from_euler(roll_rad: float, pitch_rad: float, yaw_rad: float) -> Mat3:
    """Body-to-world rotation for ZYX Euler angles (NED)."""
    return Rz(yaw_rad) @ Ry(pitch_rad) @ Rx(roll_rad)


def euler_from_R(R: Mat3) -> tuple[float, float, float]:
    """(roll, pitch, yaw) in rad from a body-to-world rotation (ZYX)."""
    pitch = -math.asin(max(-1.0, min(1.0, float(R[2, 0]))))
    roll = math.atan2(float(R[2, 1]), float(R[2, 2]))
    yaw = math.atan2(float(R[1, 0]), float(R[0, 0]))
    return roll, pitch, yaw


def euler_yaw_rate_rad_s(omega_q_rad_s: NDArray[np.float64] | list[float] | tuple[float, ...], roll_rad: float,
                         pitch_rad: float) -> float:
    """ZYX Euler yaw rate from body rates: psi_dot = (q sin(phi) + r cos(phi)) / cos(theta).

    At gimbal lock (``|cos(theta)| < 1e-3``, pitch within 0.06 deg of +-90 deg) psi_dot is undefined; the
    body yaw rate ``r`` is returned, which stays bounded and is what a level-ish flight reads anyway. The
    sign of cos(theta) is kept (a clamp to ``max(cos, 1e-3)`` flips the sign beyond 90 deg of pitch and
    jumps to 1000x the rates there).
    """
    w = np.asarray(omega_q_rad_s, dtype=float)
    c = math.cos(pitch_rad)
    if abs(c) < 1e-3:
        return float(w[2])
    return float((w[1] * math.sin(roll_rad) + w[2] * math.cos(roll_rad)) / c)


def R_hq(roll_rad: float, pitch_rad: float) -> Mat3:
    """Body Q -> horizontal H: the attitude without its yaw (paper: v_h = R_hq v_q)."""
    return Ry(pitch_rad) @ Rx(roll_rad)


def quat_wxyz_from_R(R: Mat3) -> NDArray[np.float64]:
    """Unit quaternion [w, x, y, z] (w >= 0) of a rotation matrix."""
    m = np.asarray(R, dtype=float)
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0.0:
        s = math.sqrt(tr + 1.0) * 2.0
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2.0
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif m[1, 1] > m[2, 2]:
        s = math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2.0
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2.0
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    out = np.array(q, dtype=float)
    out /= np.linalg.norm(out)
    return out if out[0] >= 0.0 else -out


def R_from_quat_wxyz(q_wxyz: NDArray[np.float64] | list[float] | tuple[float, ...]) -> Mat3:
    """Rotation matrix of a quaternion [w, x, y, z] (normalised first)."""
    w, x, y, z = np.asarray(q_wxyz, dtype=float) / np.linalg.norm(q_wxyz)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def quat_wxyz_from_euler(roll_rad: float, pitch_rad: float, yaw_rad: float) -> NDArray[np.float64]:
    return quat_wxyz_from_R(R_from_euler(roll_rad, pitch_rad, yaw_rad))


def euler_from_quat_wxyz(q_wxyz: NDArray[np.float64] | list[float]) -> tuple[float, float, float]:
    return euler_from_R(R_from_quat_wxyz(q_wxyz))


def wrap_pi(angle_rad: float) -> float:
    """Wrap an angle to [-pi, pi)."""
    return (angle_rad + math.pi) % (2.0 * math.pi) - math.pi

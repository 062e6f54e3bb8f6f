"""SO(3) and SE(3): the one implementation of the rotation group math every package imports.

Conventions (as :mod:`quadlink.frames`): ``R_ab`` maps frame-b vectors into frame a; a 4x4 ``T_ab``
holds ``R_ab`` and the origin of b in a. Rotation vectors are axis x angle in rad; a twist is
``(v, omega)`` (translation first), as the odometry's Gauss-Newton step orders it.

Angles are taken with ``atan2(|skew part|, trace part)``, never ``acos`` of the trace alone: acos loses
half the digits near 0 (an error of 1e-8 rad reads as ~1e-4) and near pi.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

Vec3 = NDArray[np.float64]
Mat3 = NDArray[np.float64]
Mat4 = NDArray[np.float64]

_SMALL_ANGLE_RAD = 1e-7   # below: first-order log/exp (the series' next term is below double precision)
_NEAR_PI_RAD = 1e-3       # within this of pi: the axis comes from the symmetric part (sin(theta) ~ 0)


def skew(v: Vec3) -> Mat3:
    """[v]x, so that ``skew(v) @ u == cross(v, u)``."""
    x, y, z = v
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def vee(W: Mat3) -> Vec3:
    """Inverse of :func:`skew` (of the antisymmetric part)."""
    return 0.5 * np.array([W[2, 1] - W[1, 2], W[0, 2] - W[2, 0], W[1, 0] - W[0, 1]])


def so3_exp(w: Vec3) -> Mat3:
    """Rotation of a rotation vector (Rodrigues)."""
    theta = float(np.linalg.norm(w))
    W = skew(w)
    if theta < 1e-9:
        return np.eye(3) + W
    return np.eye(3) + math.sin(theta) / theta * W + (1.0 - math.cos(theta)) / theta**2 * (W @ W)


def rotation_angle_rad(R: Mat3) -> float:
    """Angle of a rotation in [0, pi] (the geodesic distance from the identity)."""
    s = 0.5 * math.sqrt((R[2, 1] - R[1, 2]) ** 2 + (R[0, 2] - R[2, 0]) ** 2 + (R[1, 0] - R[0, 1]) ** 2)
    return math.atan2(s, (float(R[0, 0] + R[1, 1] + R[2, 2]) - 1.0) / 2.0)


def angle_between_rad(R_a: Mat3, R_b: Mat3) -> float:
    """Geodesic distance between two rotations: the angle of ``R_a^T R_b`` (symmetric in a and b)."""
    return rotation_angle_rad(np.asarray(R_a, dtype=float).T @ np.asarray(R_b, dtype=float))


def so3_log(R: Mat3) -> Vec3:
    """Rotation vector of a rotation matrix (angle in [0, pi])."""
    w2 = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])  # 2 sin(theta) axis
    s = 0.5 * float(np.linalg.norm(w2))
    c = (float(R[0, 0] + R[1, 1] + R[2, 2]) - 1.0) / 2.0
    theta = math.atan2(s, c)
    if theta < _SMALL_ANGLE_RAD:
        return 0.5 * w2
    if math.pi - theta > _NEAR_PI_RAD:
        return theta / (2.0 * s) * w2
    # near pi: (R + R^T)/2 = c I + (1 - c) n n^T; the largest diagonal gives the best-conditioned column
    B = (0.5 * (R + R.T) - c * np.eye(3)) / (1.0 - c)
    i = int(np.argmax(np.diag(B)))
    n = B[:, i] / math.sqrt(max(float(B[i, i]), 1e-300))
    n /= np.linalg.norm(n)
    if float(n @ w2) < 0.0:  # the symmetric part has no sign; the (small) skew part has it
        n = -n
    return theta * n


def so3_exp_batch(w: NDArray[np.float64]) -> NDArray[np.float64]:
    """Rodrigues for (N, 3) rotation vectors -> (N, 3, 3)."""
    theta = np.linalg.norm(w, axis=1)
    small = theta < 1e-9
    th = np.where(small, 1.0, theta)
    a = np.where(small, 1.0, np.sin(th) / th)
    b = np.where(small, 0.5, (1.0 - np.cos(th)) / th**2)
    K = np.zeros((w.shape[0], 3, 3))
    K[:, 0, 1], K[:, 0, 2] = -w[:, 2], w[:, 1]
    K[:, 1, 0], K[:, 1, 2] = w[:, 2], -w[:, 0]
    K[:, 2, 0], K[:, 2, 1] = -w[:, 1], w[:, 0]
    return np.eye(3) + a[:, None, None] * K + b[:, None, None] * (K @ K)


def so3_log_batch(R: NDArray[np.float64]) -> NDArray[np.float64]:
    """Rotation vectors of (N, 3, 3) rotations -> (N, 3); for angles away from pi (filter sigma points)."""
    w2 = np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], axis=1)
    s = 0.5 * np.linalg.norm(w2, axis=1)
    theta = np.arctan2(s, (np.trace(R, axis1=1, axis2=2) - 1.0) / 2.0)
    f = np.where(theta < _SMALL_ANGLE_RAD, 0.5, theta / (2.0 * np.where(s < 1e-300, 1.0, s)))
    out: NDArray[np.float64] = w2 * f[:, None]
    near_pi = math.pi - theta < _NEAR_PI_RAD
    for k in np.flatnonzero(near_pi):  # rare: do them one by one, exactly
        out[k] = so3_log(R[k])
    return out


def inv_T(T: Mat4) -> Mat4:
    """Inverse of a rigid transform (``R^T``, ``-R^T t``), exact where ``np.linalg.inv`` rounds."""
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


def make_T(R: Mat3, t: Vec3) -> Mat4:
    out = np.eye(4)
    out[:3, :3] = R
    out[:3, 3] = t
    return out


def pose_error(T_a: Mat4, T_b: Mat4) -> tuple[float, float]:
    """(translation in m, geodesic rotation angle in rad) between two poses expressed in the same frame."""
    return (float(np.linalg.norm(np.asarray(T_a)[:3, 3] - np.asarray(T_b)[:3, 3])),
            angle_between_rad(np.asarray(T_a)[:3, :3], np.asarray(T_b)[:3, :3]))

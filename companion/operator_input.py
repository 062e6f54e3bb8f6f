"""The operator's command (paper 000, eqs. 2-3, with alpha's first term of eq. 6), pure.

Frames: the velocity is in H (horizontal, NED: x along the heading, y right, z down); yaw rates are NED
(positive = turning right seen from above).

* :func:`operator_from_manual_control` maps MANUAL_CONTROL (QGroundControl's joystick ranges:
  x, y in -1000..1000, z in 0..1000 with 500 = no climb) to the normalised handle position q.
* :func:`camera_yaw_rad` is alpha's first term, the yaw of the camera in Q (eq. 6). The paper's camera
  frame has x along the optical axis (alpha = atan2(r21, r11)); quadlink's C is optical (z forward),
  so the optical axis is the third column of R_qc and alpha = atan2(r23, r13).
* :func:`operator_velocity` is eqs. (2)-(3) with alpha from eq. (6). The paper's psi_dot_d = -k_psi q_y
  is written for its NWU-yaw convention; in NED the same gesture (handle to the right -> turn right) is
  psi_dot_d = +k_psi q_y.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from companion.reference_params import ReferenceParams

MANUAL_XY_FULL_SCALE = 1000.0  # MANUAL_CONTROL x, y: -1000..1000
MANUAL_Z_CENTRE = 500.0  # MANUAL_CONTROL z: 0..1000, 500 = no climb (QGroundControl joystick)
MANUAL_Z_HALF_RANGE = 500.0


@dataclass(frozen=True)
class OperatorInput:
    """Normalised handle position: ``qx`` forward, ``qy`` right (-> yaw rate), ``qz`` up, each in [-1, 1]."""

    qx: float = 0.0
    qy: float = 0.0
    qz: float = 0.0


def _deadband(value: float, width: float) -> float:
    value = max(-1.0, min(1.0, value))
    if abs(value) <= width:
        return 0.0
    return math.copysign((abs(value) - width) / (1.0 - width), value) if width < 1.0 else 0.0


def operator_from_manual_control(x: int, y: int, z: int, deadband: float = 0.0) -> OperatorInput:
    """MANUAL_CONTROL axes -> handle position (x forward, y -> yaw, z climb with 500 = no climb)."""
    return OperatorInput(
        qx=_deadband(x / MANUAL_XY_FULL_SCALE, deadband),
        qy=_deadband(y / MANUAL_XY_FULL_SCALE, deadband),
        qz=_deadband((z - MANUAL_Z_CENTRE) / MANUAL_Z_HALF_RANGE, deadband),
    )


def camera_yaw_rad(R_qc: ArrayLike) -> float:
    """Yaw of the camera's optical axis in Q (first term of eq. 6, for an optical camera frame)."""
    R = np.asarray(R_qc, dtype=float)
    return math.atan2(R[1, 2], R[0, 2])


def operator_velocity(op: OperatorInput, alpha_rad: float, params: ReferenceParams
                      ) -> tuple[NDArray[np.float64], float]:
    """Eqs. (2)-(3): operator velocity in H (NED, climb is -z) and yaw rate (NED)."""
    v = np.array([params.k_v_m_s * op.qx * math.cos(alpha_rad),  # eq. (2)
                  params.k_v_m_s * op.qx * math.sin(alpha_rad),
                  -params.k_climb_m_s * op.qz])
    return v, params.k_psi_rad_s * op.qy  # eq. (3), NED sign (see module doc)

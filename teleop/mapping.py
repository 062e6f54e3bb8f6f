"""Device position q (frame D, NED) -> operator command, paper 000 eqs. (2)-(3). Pure.

The companion (companion/operator_input.py) turns MANUAL_CONTROL into the desired velocity of eqs. (2)-(3):
``v_d = k_v (q_x cos a, q_x sin a, q_z)`` and the yaw rate ``k_psi q_y`` (the paper's -k_psi q_y
written for NED: handle to the right -> turn right). On the wire the command is normalized: ``x``
(forward, along alpha) and ``y`` (yaw rate; ``r`` with ``yaw_axis: r``) in -1000..1000, ``z`` (climb)
in 0..1000 with 500 = no climb (QGroundControl's convention: above 500 = up, so z_D down maps below
500). Eq. (2) allows no motion orthogonal to alpha, so no other axis is used. Full scale is the
companion's maximum speed / yaw rate / climb rate, after its own dead-band ``companion_deadband``,
see :func:`mapping_gains` for the equivalent gains k_v, k_psi.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from teleop.config import DeviceConfig, MappingConfig

MANUAL_CONTROL_FULL_SCALE = 1000
MANUAL_CONTROL_Z_NEUTRAL = 500


@dataclass(frozen=True)
class ManualControl:
    """One MANUAL_CONTROL command (normalized integers, MAVLink ranges)."""

    x: int          # forward along alpha, -1000..1000
    y: int          # yaw rate with yaw_axis 'y' (the companion's), -1000..1000, > 0 = turn right (NED)
    z: int          # climb, 0..1000, 500 = none, > 500 = up
    r: int          # yaw rate with yaw_axis 'r', else 0
    buttons: int = 0


@dataclass(frozen=True)
class MappingGains:
    """Equivalent gains of eqs. (2)-(3) (SI), used by the force law's q~ (eqs. (16)-(18))."""

    k_v_xy_per_s: float      # m/s per m of q_x beyond the dead-band
    k_v_z_per_s: float       # m/s per m of q_z
    k_psi_rad_s_m: float     # rad/s per m of q_y (magnitude; the sign is yaw_sign)
    yaw_sign: float
    # per axis (x, y, z), the device position at which the companion's command starts to move: the device
    # dead-band plus the companion's, carried back to metres of q
    command_onset_m: tuple[float, float, float] = (0.0, 0.0, 0.0)


def mapping_gains(mapping: MappingConfig, device: DeviceConfig) -> MappingGains:
    """Slope of velocity vs device position beyond both dead-bands: v = k (|q| - db_eff) sign(q).

    The companion maps n -> (|n| - db_c) / (1 - db_c), so one metre of q beyond the device dead-band is
    worth ``max / ((workspace - deadband) (1 - db_c))``, and the command starts at
    ``db_eff = deadband + db_c (workspace - deadband)`` (``command_onset_m``, 6.3 mm with the shipped
    config), which :func:`teleop.force.q_tilde` adds back so that the cue vanishes when the vehicle follows.
    """
    span = [w - d for w, d in zip(device.workspace_m, mapping.deadband_m)]
    if min(span) <= 0:
        raise ValueError("dead-band must be smaller than the workspace on every axis")
    scale = 1.0 - mapping.companion_deadband
    onset = tuple(d + mapping.companion_deadband * s for d, s in zip(mapping.deadband_m, span))
    return MappingGains(mapping.max_speed_m_s / (span[0] * scale), mapping.max_climb_m_s / (span[2] * scale),
                        mapping.max_yaw_rate_rad_s / (span[1] * scale), mapping.yaw_sign,
                        (onset[0], onset[1], onset[2]))


def shape_axis(q_m: float, deadband_m: float, workspace_m: float) -> float:
    """Dead-band then workspace scaling: -1..1, zero inside the dead-band, continuous at its edge."""
    magnitude = abs(q_m) - deadband_m
    if magnitude <= 0.0 or not np.isfinite(q_m):
        return 0.0
    return float(np.copysign(min(magnitude / (workspace_m - deadband_m), 1.0), q_m))


def map_device_to_command(q_d_m: NDArray[np.float64], mapping: MappingConfig, device: DeviceConfig,
                          buttons: int = 0) -> ManualControl:
    """eqs. (2)-(3) on the normalized MANUAL_CONTROL axes."""
    nx, ny, nz = (shape_axis(float(q_d_m[i]), mapping.deadband_m[i], device.workspace_m[i]) for i in range(3))
    x = round(MANUAL_CONTROL_FULL_SCALE * nx)
    yaw = round(MANUAL_CONTROL_FULL_SCALE * mapping.yaw_sign * ny)  # eq. (3)
    # z_D is down: pushing the handle down (q_z > 0) commands a descent (z < 500).
    z = round(MANUAL_CONTROL_Z_NEUTRAL - MANUAL_CONTROL_Z_NEUTRAL * nz)
    if mapping.yaw_axis == "y":
        return ManualControl(x=x, y=yaw, z=z, r=0, buttons=buttons)
    return ManualControl(x=x, y=0, z=z, r=yaw, buttons=buttons)


def command_to_velocity(cmd: ManualControl, mapping: MappingConfig) -> tuple[float, float, float]:
    """What the companion makes of ``cmd``: (forward m/s along alpha, climb-down m/s (NED z), yaw rate rad/s)."""
    db = mapping.companion_deadband

    def shaped(n: float) -> float:   # the companion's dead-band on the normalized axis
        n = max(-1.0, min(1.0, n))
        return 0.0 if abs(n) <= db else float(np.copysign((abs(n) - db) / (1.0 - db), n))

    yaw = cmd.y if mapping.yaw_axis == "y" else cmd.r
    forward = mapping.max_speed_m_s * shaped(cmd.x / MANUAL_CONTROL_FULL_SCALE)
    v_down = -mapping.max_climb_m_s * shaped((cmd.z - MANUAL_CONTROL_Z_NEUTRAL) / MANUAL_CONTROL_Z_NEUTRAL)
    yaw_rate = mapping.max_yaw_rate_rad_s * shaped(yaw / MANUAL_CONTROL_FULL_SCALE)
    return forward, v_down, yaw_rate

"""Reference velocity and yaw rate from the operator, the pan-scan and the obstacles (paper 000, eqs. 2-8).

Pure functions of their inputs (no clock, no I/O). Frames: everything is in H (horizontal, NED: x along
the heading, y right, z down); yaw rates are NED (positive = turning right seen from above).

:func:`reference_velocity` composes the stages, each pure in its own module:

* the operator's command, eqs. (2)-(3) with alpha from eq. (6) (:mod:`companion.operator_input`), or in its
  place a scripted command from :mod:`companion.arbiter`;
* when the obstacle data are stale or unknown sectors are not allowed, no horizontal motion toward unknown
  sectors (:func:`companion.avoidance.remove_toward_unknown`);
* the repulsion v_o added (eq. 7, :func:`companion.avoidance.repulsion_velocity`), then the safety
  constraints: a closing speed toward each obstacle point within reach of at most
  ``approach_gain_per_s (d - safe distance)`` — zero inside the safe distance
  (:func:`companion.avoidance.limit_speed_toward_obstacles`), on the points
  :mod:`companion.obstacle_points` selects;
* the vertical limits (:mod:`companion.vertical_limits`) and the speed limit ``max_speed_m_s``;
* the pan-scan yaw rate added to the operator's (eq. 8).

Gains and limits: :class:`companion.reference_params.ReferenceParams`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from companion.avoidance import limit_speed_prepared, remove_toward_unknown, repulsion_prepared
from companion.obstacle_points import constraint_points, select_points
from companion.operator_input import OperatorInput, camera_yaw_rad, operator_velocity
from companion.pan_scan import PanScanState
from companion.reference_params import ReferenceParams
from companion.vertical_limits import VerticalLimits, apply_vertical_limits, vertical_limits


@dataclass(frozen=True)
class ReferenceOutput:
    """Reference for the velocity tracker, in H, and its parts (for TELEOP_FEEDBACK)."""

    v_ref_h_m_s: NDArray[np.float64]  # eq. (7), after the safety constraints
    yaw_rate_ref_rad_s: float  # eq. (8)
    v_operator_h_m_s: NDArray[np.float64]  # eq. (2)
    v_repulsion_h_m_s: NDArray[np.float64]  # v_o of eq. (7)
    alpha_rad: float  # eq. (6)
    pan_scan_yaw_rate_rad_s: float  # eq. (4)
    operator_yaw_rate_rad_s: float  # eq. (3)
    constrained: bool  # a safety constraint removed part of the command
    vertical_limits: VerticalLimits | None = None  # the climb/descent bounds applied (None: height not used)


def reference_velocity(op: OperatorInput, R_qc: ArrayLike, scan: PanScanState,
                       obstacle_points_h_m: ArrayLike | None, params: ReferenceParams,
                       sectors_m: ArrayLike | None = None, block_unknown: bool = False,
                       operator_enabled: bool = True, sector_offset_rad: float = 0.0,
                       height_m: float | None = None, v_est_h_m_s: ArrayLike | None = None,
                       v_command_h_m_s: ArrayLike | None = None, command_yaw_rate_rad_s: float = 0.0,
                       height_verified: bool = True, height_uncertainty_m: float = 0.0,
                       baro_height_m: float | None = None) -> ReferenceOutput:
    """Eqs. (2)-(8) with the safety constraints (see module doc).

    ``operator_enabled`` False (hold, link lost) zeroes the operator part but keeps the repulsion;
    ``block_unknown`` forbids horizontal operator motion toward unknown sectors of ``sectors_m``
    (the caller sets it when the obstacle data are stale, passing ``sectors_m=None``). ``height_m``:
    height above the take-off floor (odometry), to tell the floor from obstacles; None = unknown.
    The odometry counts ``height_m`` from the take-off pose: ``params.takeoff_height_m`` is added to make it
    the height above the floor. ``v_est_h_m_s``: the estimated velocity in H, for the closing-speed law's
    stopping distance (None: the law without it). ``v_command_h_m_s`` / ``command_yaw_rate_rad_s``: a
    scripted command (from :mod:`companion.arbiter`) that replaces eqs. (2)-(3); everything after them
    applies to it alike. ``height_verified``: the height was checked against the floor recently
    (:mod:`companion.vertical_limits`: otherwise no climb toward a configured ceiling); ``height_uncertainty_m``:
    how far it may have drifted since (kept from the room's ceiling). ``baro_height_m``: the autopilot's
    barometer-fused height above the take-off spot, as ``height_m``; None if none is fresh (the ceiling is kept from
    the higher of the two)."""
    alpha = camera_yaw_rad(R_qc) + scan.yaw_offset_rad  # eq. (6)
    if height_m is not None:
        height_m = height_m + params.takeoff_height_m
    if baro_height_m is not None:
        baro_height_m = baro_height_m + params.takeoff_height_m
    if not operator_enabled:
        op = OperatorInput()
    if v_command_h_m_s is not None and operator_enabled:
        v_d = np.array(v_command_h_m_s, dtype=float).reshape(3)
        if not np.all(np.isfinite(v_d)):
            v_d = np.zeros(3)
        yaw_rate_d = float(command_yaw_rate_rad_s) if math.isfinite(command_yaw_rate_rad_s) else 0.0
    else:
        v_d, yaw_rate_d = operator_velocity(op, alpha, params)  # eqs. (2)-(3)
    constrained = False
    if block_unknown:
        v_d, constrained = remove_toward_unknown(v_d, sectors_m, params.unknown_sector_guard_rad, sector_offset_rad)
    # the map's points once: only those within reach of either rule matter (a few of its ~2000 particles)
    # the constraints look as far as a vehicle at the commanded (or current) speed needs to brake
    reach = max(params.influence_distance_m, params.safe_distance_m)
    speed = max(float(np.linalg.norm(v_d)), 0.0 if v_est_h_m_s is None else float(np.linalg.norm(v_est_h_m_s)))
    if math.isfinite(speed) and math.isfinite(params.approach_gain_per_s) and params.approach_gain_per_s > 0:
        reach = max(reach, params.safe_distance_m + speed * (params.stopping_time_s + 1.0 / params.approach_gain_per_s))
    p = select_points(obstacle_points_h_m, params, height_m, reach)   # the repulsion uses those within d_0
    v_o = repulsion_prepared(p, params)
    if sectors_m is not None:
        # the repulsion is motion nobody commanded: like a script's, it never goes where the map has not
        # looked (campaign 3, flight 1: pan-scan off, the push off a seen wall carried the vehicle sideways
        # to 0.36 m of a partition's end it had never seen); inside the safe distance the speed law below
        # still sends the vehicle back out
        v_o, _ = remove_toward_unknown(v_o, sectors_m, params.unknown_sector_guard_rad, sector_offset_rad)
    v_r = v_d + v_o  # eq. (7)
    c = constraint_points(obstacle_points_h_m, params, height_m, reach, band=p)
    v_r, removed = limit_speed_prepared(v_r, c, params.safe_distance_m, params.approach_gain_per_s, reach,
                                        v_est_h_m_s, params.stopping_time_s)
    if removed and sectors_m is not None and c.shape[0]:
        # the slide along an obstacle that the projection makes of a push is motion nobody commanded: like the
        # repulsion, it never goes where the map has not looked (CI's corner push slid left along the wall, where
        # the camera, 45 deg right of the nose, had not looked for 20 s, to 0.39 m of it). Backing out of the
        # safe distance is never held back: inside it, a slide toward the unknown gives way to the law's own
        # back-out, from the repulsion alone (a starved companion's push, 0.35 m from the south wall: projected
        # off a wall it saw, the push slid at 0.35 m/s toward one it had not, a few cm inside the safe distance)
        v_kept, toward_unknown = remove_toward_unknown(v_r, sectors_m, params.unknown_sector_guard_rad,
                                                       sector_offset_rad)
        if toward_unknown:
            if float(np.min(np.hypot(c[:, 0], c[:, 1]))) >= params.safe_distance_m:
                v_r = v_kept
            else:
                v_back = np.array([v_o[0], v_o[1], v_r[2]])    # the climb or descent commanded stays
                v_r, _ = limit_speed_prepared(v_back, c, params.safe_distance_m, params.approach_gain_per_s, reach,
                                              v_est_h_m_s, params.stopping_time_s)
    v_up = None if v_est_h_m_s is None else -float(np.asarray(v_est_h_m_s, dtype=float)[2])
    limits = vertical_limits(height_m, v_up, params.vertical(), height_verified, height_uncertainty_m, baro_height_m)
    v_r, vertical = apply_vertical_limits(v_r, limits)
    speed = float(np.linalg.norm(v_r))
    if speed > params.max_speed_m_s:
        v_r *= params.max_speed_m_s / speed
        constrained = True
    yaw_rate = yaw_rate_d + scan.yaw_rate_rad_s  # eq. (8)
    return ReferenceOutput(v_r, yaw_rate, v_d, v_o, alpha, scan.yaw_rate_rad_s, yaw_rate_d,
                           constrained or removed or vertical, limits)

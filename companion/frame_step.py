"""The companion's work on one camera frame and at the feedback rate, without I/O (pure).

:func:`frame_step`: perception output + operator input + mode -> the reference velocity for the
autopilot (eqs. (2)-(8) in :mod:`companion.reference`) and the nearest obstacle for the feedback.
:func:`fallback_step` is the same without a fresh frame (camera silent). :func:`feedback_message` and
:func:`operator_image_meta` build what the ground station receives from the state those steps leave.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum
from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion import messages as msgs
from companion.modes import Mode
from companion.obstacle_points import avoidance_points, drifted_toward, nearest_obstacle, with_open_tops
from companion.operator_input import OperatorInput, camera_yaw_rad
from companion.pan_scan import PanScanParams, PanScanState
from companion.reference import ReferenceOutput, reference_velocity
from companion.reference_params import ReferenceParams
from perception.pipeline import PerceptionOutput
from quadlink.frames import R_hq, euler_yaw_rate_rad_s
from quadlink.operator_image import (
    MAX_OBSTACLE_POINTS,
    NO_VERTICAL,
    OperatorImageMeta,
    PanScanMeta,
    VerticalMeta,
    finite_or_none,
)

NO_SCAN = PanScanState(0.0, 0.0, False)


@dataclass(frozen=True)
class FrameStep:
    """One frame's decision: ``ref`` (sent as the setpoint when in control), the nearest obstacle
    (vector in H, distance m) that TELEOP_FEEDBACK reports between frames, and the map points the
    avoidance acts on (H, m; the operator image shows these)."""

    ref: ReferenceOutput
    nearest: tuple[NDArray[np.float64], float] | None
    obstacle_points_h_m: NDArray[np.float64]


class HeightFrom(Enum):
    """``frame_step``'s default height source: the odometry's alone (no :mod:`companion.height` estimator)."""

    ODOMETRY = "odometry"


def height_m(out: PerceptionOutput | None) -> float | None:
    """Height above the take-off pose from the odometry alone (its world starts on the ground, NED); the
    daemon holds it to the floor the camera sees (:class:`companion.height.HeightEstimator`)."""
    if out is None or not out.odometry_ok or out.position_m is None:
        return None
    z = float(np.asarray(out.position_m, dtype=float)[2])
    return -z if math.isfinite(z) else None


def map_points_h_m(out: PerceptionOutput | None, params: ReferenceParams,
                   height_m: float | None = None) -> NDArray[np.float64] | None:
    """Perception's map points as the avoidance takes them: each moved toward the vehicle by the odometry's drift
    since it was seen (``params.map_drift_m_s``, :func:`companion.obstacle_points.drifted_toward`), and those
    below the vehicle whose top the camera never saw over extended up to its level
    (:func:`companion.obstacle_points.with_open_tops`; ``height_m`` above the floor keeps the floor out)."""
    if out is None:
        return None
    p = drifted_toward(out.obstacle_points_h_m, out.obstacle_ages_s, params.map_drift_m_s)
    if p is None:
        return None
    return with_open_tops(np.asarray(p, dtype=float).reshape(-1, 3), out.obstacle_open_top, height_m,
                          params.floor_margin_m)


def frame_step(out: PerceptionOutput | None, op: OperatorInput, R_qc: NDArray[np.float64], scan: PanScanState,
               params: ReferenceParams, operator_enabled: bool, allow_unknown_when_fresh: bool,
               v_command_h_m_s: NDArray[np.float64] | None = None, command_yaw_rate_rad_s: float = 0.0,
               height_above_takeoff_m: float | None | HeightFrom = HeightFrom.ODOMETRY,
               command_into_unknown: bool = False, height_verified: bool = True,
               height_uncertainty_m: float = 0.0, baro_height_m: float | None = None) -> FrameStep:
    """The reference for a frame; ``out`` is perception's output (None: perception failed on it).
    ``v_command_h_m_s`` / ``command_yaw_rate_rad_s``: a scripted command (companion.arbiter) instead of
    the operator's handle ``op``; the measured velocity feeds the closing-speed law's stopping distance.
    ``height_above_takeoff_m``: the vehicle's height (None = unknown; default: the odometry's);
    ``height_verified``: checked against the floor lately (otherwise no climb toward a configured ceiling);
    ``baro_height_m``: the autopilot's barometer-fused height above the take-off spot (None: none fresh)."""
    h = height_m(out) if isinstance(height_above_takeoff_m, HeightFrom) else height_above_takeoff_m
    points = map_points_h_m(out, params, h)
    sectors, _, offset_deg = msgs.sector_arrays(None if out is None else out.sectors)
    # the operator pushing forward moves along the camera's axis (eq. 2), which is always in view; a script
    # commands any direction, and an operator pulling the handle back reverses away from the camera: neither
    # goes where the map has not looked (PX4's CP_GO_NO_DATA = 0), fresh data or not (campaign flight 25
    # backed blind into a partition, 0.24 m)
    # (``command_into_unknown``: PX4's CP_GO_NO_DATA = 1 for scripts, as a configuration chooses)
    blind_side = (v_command_h_m_s is not None and not command_into_unknown) or (operator_enabled and op.qx < 0.0)
    ref = reference_velocity(op, R_qc, scan, points, params, sectors_m=sectors,
                             block_unknown=out is None or not allow_unknown_when_fresh or blind_side,
                             operator_enabled=operator_enabled, sector_offset_rad=math.radians(offset_deg),
                             height_m=h, height_verified=height_verified, height_uncertainty_m=height_uncertainty_m,
                             baro_height_m=baro_height_m,
                             v_est_h_m_s=None if out is None or not out.odometry_ok else out.v_h_m_s,
                             v_command_h_m_s=v_command_h_m_s, command_yaw_rate_rad_s=command_yaw_rate_rad_s)
    # the warning and the dots use the avoidance's points: the floor (within the floor margin once the height
    # is known, or below the band without out_of_band_3d) is not an obstacle to it, nor to the operator
    avoid = avoidance_points(points, params, h)
    return FrameStep(ref, nearest_obstacle(avoid, params), avoid)


def fallback_step(last_out: PerceptionOutput | None, op: OperatorInput, R_qc: NDArray[np.float64],
                  params: ReferenceParams, operator_enabled: bool,
                  height_above_takeoff_m: float | None | HeightFrom = HeightFrom.ODOMETRY,
                  height_verified: bool = True, baro_height_m: float | None = None) -> ReferenceOutput:
    """No camera: obstacle data stale -> no motion toward unknown (= all) sectors, repulsion from the last
    map kept (conservative), no pan-scan; the operator is zeroed by HOLD (``operator_enabled``)."""
    h = height_m(last_out) if isinstance(height_above_takeoff_m, HeightFrom) else height_above_takeoff_m
    points = map_points_h_m(last_out, params, h)
    # the last velocity estimate is stale: the stopping distance uses none (the hold is the vehicle's)
    return reference_velocity(op, R_qc, NO_SCAN, points, params, sectors_m=None, block_unknown=True,
                              operator_enabled=operator_enabled, height_verified=height_verified,
                              height_m=h, baro_height_m=baro_height_m)


def setpoint_velocity(ref: ReferenceOutput, in_control: bool) -> tuple[NDArray[np.float64], float]:
    """(v in H, yaw rate) to send. Outside TELEOP/HOLD the autopilot flies its own mode: the (zero) stream
    only keeps offboard ready. A non-finite reference (a bug upstream) is sent as a hold, never as NaN
    (issue 16: a NaN setpoint makes an autopilot refuse the stream and fail safe)."""
    if in_control:
        v = np.asarray(ref.v_ref_h_m_s, dtype=float)
        yaw_rate = float(ref.yaw_rate_ref_rad_s)
        if math.isfinite(yaw_rate) and v.shape == (3,) and bool(np.all(np.isfinite(v))):
            return v, yaw_rate
    return np.zeros(3), 0.0


def feedback_message(stamp_s: float, out: PerceptionOutput | None, ref: ReferenceOutput | None, scan: PanScanState,
                     R_qc: NDArray[np.float64], nearest: tuple[NDArray[np.float64], float] | None,
                     gyro_q_rad_s: NDArray[np.float64], mode: Mode, odometry_ok: bool, gcs_ok: bool,
                     obstacles_fresh: bool) -> Any:
    """TELEOP_FEEDBACK at ``stamp_s`` from the last frame's state and the pan-scan now."""
    zero = np.zeros(3)
    v_est = zero if out is None else np.asarray(out.v_h_m_s, dtype=float)
    roll = 0.0 if out is None else out.roll_rad
    pitch = 0.0 if out is None else out.pitch_rad
    yaw_cmd = (0.0 if ref is None else ref.operator_yaw_rate_rad_s) + scan.yaw_rate_rad_s  # eq. (8) held
    alpha = camera_yaw_rad(R_qc) + scan.yaw_offset_rad  # eq. (6) at this instant
    obst, dist = nearest if nearest is not None else (zero, -1.0)
    flags = msgs.feedback_flags(scan.enabled, odometry_ok, gcs_ok, obstacles_fresh)
    v_cmd = zero if ref is None else ref.v_ref_h_m_s
    v_rep = zero if ref is None else ref.v_repulsion_h_m_s
    return msgs.teleop_feedback_message(stamp_s, v_est, v_cmd, v_rep, alpha, scan.yaw_rate_rad_s, yaw_cmd,
                                        euler_yaw_rate_rad_s(gyro_q_rad_s, roll, pitch), obst, dist,
                                        mode, flags)


def _vec3(v: Any) -> tuple[float, float, float]:
    a = np.asarray(v, dtype=float).reshape(3)
    return (float(a[0]), float(a[1]), float(a[2]))


def obstacle_points_c_m(points_h_m: NDArray[np.float64] | None, roll_rad: float, pitch_rad: float,
                        R_qc: NDArray[np.float64], p_qc_m: NDArray[np.float64]) -> NDArray[np.float64]:
    """The avoidance's points (H) in the camera frame C for the operator image, nearest first, at most
    MAX_OBSTACLE_POINTS: p_q = R_hq^T p_h, p_c = R_qc^T (p_q - p_qc) (row vectors below)."""
    if points_h_m is None:
        return np.zeros((0, 3))
    p_h = np.asarray(points_h_m, dtype=float).reshape(-1, 3)
    p_h = p_h[np.all(np.isfinite(p_h), axis=1)]
    p_h = p_h[np.argsort(np.einsum("ij,ij->i", p_h, p_h), kind="stable")[:MAX_OBSTACLE_POINTS]]
    p_q = p_h @ R_hq(roll_rad, pitch_rad)  # rows: (R_hq^T p)^T = p^T R_hq
    return (p_q - np.asarray(p_qc_m, dtype=float).reshape(3)) @ np.asarray(R_qc, dtype=float)


def operator_image_meta(stamp_s: float, out: PerceptionOutput, ref: ReferenceOutput, scan: PanScanState,
                        scan_params: PanScanParams, gyro_q_rad_s: NDArray[np.float64], mode: Mode,
                        avoidance_points_h_m: NDArray[np.float64] | None, R_qc: NDArray[np.float64],
                        p_qc_m: NDArray[np.float64]) -> OperatorImageMeta:
    """The operator image's metadata for a frame perception processed (``out`` not None); its obstacle
    points are the avoidance's (``FrameStep.obstacle_points_h_m``), in the frame's camera frame."""
    pts = obstacle_points_c_m(avoidance_points_h_m, out.roll_rad, out.pitch_rad, R_qc, p_qc_m)
    return OperatorImageMeta(
        stamp_s=float(stamp_s), roll_rad=float(out.roll_rad), pitch_rad=float(out.pitch_rad),
        yaw_rad=float(out.yaw_rad),
        gyro_yaw_rate_rad_s=euler_yaw_rate_rad_s(gyro_q_rad_s, out.roll_rad, out.pitch_rad),
        obstacle_points_c_m=tuple(_vec3(p) for p in np.round(pts, 3)),
        v_cmd_h_m_s=_vec3(ref.v_ref_h_m_s), v_est_h_m_s=_vec3(out.v_h_m_s),
        pan_scan=PanScanMeta(enabled=bool(scan.enabled), yaw_rate_rad_s=float(scan.yaw_rate_rad_s),
                             yaw_offset_rad=float(scan.yaw_offset_rad), alpha_rad=float(ref.alpha_rad),
                             amplitude_rad_s=float(scan_params.amplitude_rad_s),
                             omega_rad_s=float(scan_params.omega_rad_s)),
        mode=mode.name.lower(), vertical=_vertical_meta(ref))


def _vertical_meta(ref: ReferenceOutput) -> VerticalMeta:
    """The vertical limits the reference applied (none: the height was unknown)."""
    lim = ref.vertical_limits
    if lim is None:
        return NO_VERTICAL
    return VerticalMeta(finite_or_none(lim.height_m), finite_or_none(lim.floor_height_m),
                        finite_or_none(lim.ceiling_height_m))

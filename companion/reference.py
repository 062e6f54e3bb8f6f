"""Reference velocity and yaw rate from the operator, the pan-scan and the obstacles (paper 000, eqs. 2-8).

Pure functions of their inputs (no clock, no I/O). Frames: everything is in H (horizontal, NED: x along
the heading, y right, z down); yaw rates are NED (positive = turning right seen from above).

* :func:`operator_from_manual_control` maps MANUAL_CONTROL (QGroundControl's joystick ranges:
  x, y in -1000..1000, z in 0..1000 with 500 = no climb) to the normalised handle position q.
* :func:`camera_yaw_rad` is alpha's first term, the yaw of the camera in Q (eq. 6). The paper's camera
  frame has x along the optical axis (alpha = atan2(r21, r11)); quadlink's C is optical (z forward),
  so the optical axis is the third column of R_qc and alpha = atan2(r23, r13).
* :func:`operator_velocity` is eqs. (2)-(3) with alpha from eq. (6). The paper's psi_dot_d = -k_psi q_y
  is written for its NWU-yaw convention; in NED the same gesture (handle to the right -> turn right) is
  psi_dot_d = +k_psi q_y.
* :func:`repulsion_velocity` is v_o of eq. (7), "the weighted sum of all contributions": each map point
  within d_0 contributes the gradient of a standard (Khatib) repulsive potential
  ``U_j = eta/2 (1/d_j - 1/d_0)^2``, i.e. ``v_j = m_j (-p_j / d_j)`` with ``m_j = eta (1/d_j - 1/d_0) / d_j^2``,
  and the weights are ``w_j = m_j / sum_k m_k``. The weighted sum keeps the direction of the plain sum but
  its size is that of the nearest points, whatever the number of points sampling a surface (a column seen
  in ten image sectors, each point as several map particles, would otherwise push ten times harder and
  stop the vehicle far outside the safe distance). ``combine="sum"`` is the plain superposition. The
  result is limited to ``max_repulsion_m_s``.
* :func:`reference_velocity` adds them (eq. 7) and the pan-scan yaw rate (eq. 8), then enforces the
  safety constraints: a closing speed toward each obstacle point within d_0 of at most
  ``approach_gain_per_s (d - safe distance)`` — zero inside the safe distance — and (when the obstacle
  data are stale or unknown sectors are not allowed) no horizontal motion toward unknown sectors.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from companion.pan_scan import PanScanState
from companion.vertical_limits import VerticalLimits, VerticalParams, apply_vertical_limits, vertical_limits

MANUAL_XY_FULL_SCALE = 1000.0  # MANUAL_CONTROL x, y: -1000..1000
MANUAL_Z_CENTRE = 500.0  # MANUAL_CONTROL z: 0..1000, 500 = no climb (QGroundControl joystick)
MANUAL_Z_HALF_RANGE = 500.0


@dataclass(frozen=True)
class OperatorInput:
    """Normalised handle position: ``qx`` forward, ``qy`` right (-> yaw rate), ``qz`` up, each in [-1, 1]."""

    qx: float = 0.0
    qy: float = 0.0
    qz: float = 0.0


@dataclass(frozen=True)
class ReferenceParams:
    """Gains and safety limits of the reference velocity.

    k_v_m_s: horizontal speed at full handle deflection (eq. 2); k_climb_m_s: climb speed at full
    deflection; k_psi_rad_s: yaw rate at full deflection (eq. 3). Repulsion (eq. 7): eta gain
    [m^3/s], influence distance d_0, limit on |v_o|, how the points' contributions combine (``weighted``:
    the paper's weighted sum, see :func:`repulsion_velocity`; ``sum``: plain superposition); safe
    distance (paper Fig. 8: 0.45 m) inside which the reference has no component toward the obstacle.
    The default eta = 0.13 m^3/s makes one obstacle cancel the full-deflection push (k_v = 0.6 m/s) at
    0.47 m, so a vehicle pushed at an obstacle comes to rest just outside the safe distance;
    ``approach_gain_per_s`` bounds the closing speed toward points within d_0 to gain x (d - safe
    distance) so it gets there without coasting through (see :func:`limit_speed_toward_obstacles`). ``horizontal_only``:
    repulsion and the safe distance act in the horizontal plane, on the points within
    ``vertical_band_m`` of the vehicle's height (the camera looks down, so it samples tall obstacles
    mostly below the vehicle: in 3D their sum would push the vehicle up, and the floor is not an
    obstacle to horizontal motion); False is the paper's 3D form. When the height above the take-off
    floor is known, points within ``floor_margin_m`` of the floor are the floor, not obstacles (a low
    vehicle sees the floor ahead at its own height: repelled by it, it would back away blindly).

    Safety constraints (issue 14): ``stopping_time_s`` is the distance the vehicle travels, per m/s of its
    speed, after its reference drops to zero — the bridge's velocity loop (PI, time constant ~0.5 s, with
    its integral's overshoot: ~0.7 s in a closed-loop simulation of the real tracker) plus the
    camera-to-setpoint latency; the closing-speed bound toward a point counts the measured closing speed
    times this time as distance already used up (see :func:`limit_speed_toward_obstacles`).
    ``surface_gap_m``: neighbouring map points closer than this are taken as one surface and the segment
    between them constrains the motion (the camera samples a wall with one point per image sector:
    between two samples 0.5 m apart a vehicle kept 0.45 m from both is only 0.37 m from the wall;
    bridging gaps narrower than twice the safe distance forbids no passage the vehicle could take).
    ``out_of_band_3d``: points outside the height band (a box top below the vehicle, a ceiling point
    above it) constrain the motion by their 3D distance instead of being ignored. Vertical limits
    (:mod:`companion.vertical_limits`): ``max_height_m`` above the take-off floor (an altitude fence),
    ``room_height_m`` (the ceiling, kept ``safe_distance_m`` away), ``floor_min_height_m`` (the lowest
    height the reference descends to; take-off and landing are the autopilot's). ``takeoff_height_m``:
    height of the vehicle's origin above the floor when it stands on it (its landing gear):
    :func:`reference_velocity`'s ``height_m`` is the odometry's, counted from the take-off pose, held to
    the floor the camera sees with ``floor_height_time_constant_s`` (:mod:`companion.height`; 0: the
    odometry's alone); without a floor seen for ``height_fix_max_age_s`` the height is not verified and the
    vehicle does not climb toward a configured ceiling.
    """

    k_v_m_s: float = 0.6
    k_climb_m_s: float = 0.4
    k_psi_rad_s: float = 0.8
    deadband: float = 0.03
    combine: Literal["weighted", "sum"] = "weighted"
    repulsion_gain_m3_s: float = 0.13
    influence_distance_m: float = 0.9
    max_repulsion_m_s: float = 1.0
    safe_distance_m: float = 0.45
    approach_gain_per_s: float = 1.2
    max_speed_m_s: float = 1.5
    unknown_sector_guard_rad: float = math.radians(15.0)
    horizontal_only: bool = True
    vertical_band_m: float = 0.3
    floor_margin_m: float = 0.15
    stopping_time_s: float = 0.8
    surface_gap_m: float = 0.9
    out_of_band_3d: bool = True
    max_height_m: float | None = None
    room_height_m: float | None = None
    floor_min_height_m: float = 0.3
    takeoff_height_m: float = 0.0
    floor_height_time_constant_s: float = 0.5
    height_fix_max_age_s: float = 4.0

    def vertical(self) -> VerticalParams:
        """The vertical limits' parameters (:mod:`companion.vertical_limits`), sharing the safe distance and
        the closing-speed law."""
        return VerticalParams(self.max_height_m, self.room_height_m, self.safe_distance_m, self.floor_min_height_m,
                              self.approach_gain_per_s if math.isfinite(self.approach_gain_per_s) else 1.2,
                              self.stopping_time_s)


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


def _finite_rows(points_h_m: ArrayLike) -> NDArray[np.float64]:
    """Points as N x 3 floats without the rows holding a NaN or inf (one flat check first: rows are only
    filtered when something is wrong)."""
    p = np.asarray(points_h_m, dtype=float).reshape(-1, 3)
    return p if np.isfinite(p).all() else p[np.isfinite(p).all(axis=1)]


def _avoidance_mask(p: NDArray[np.float64], params: ReferenceParams | None, height_m: float | None,
                    reach_m: float) -> NDArray[np.bool_] | None:
    """Which of the finite points ``p`` the avoidance acts on (None: all of them); see :func:`_points`."""
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    horizontal = params is not None and params.horizontal_only
    keep = None
    if math.isfinite(reach_m):
        r2 = x * x + y * y
        if not horizontal:
            r2 += z * z
        keep = r2 < reach_m * reach_m
    if params is not None and height_m is not None and math.isfinite(height_m):
        floor = (height_m - z) > params.floor_margin_m  # height of the point above the floor (H: z down)
        keep = floor if keep is None else keep & floor
    if horizontal:
        assert params is not None
        band = np.abs(z) <= params.vertical_band_m
        keep = band if keep is None else keep & band
    return keep


def _points(points_h_m: ArrayLike | None, params: ReferenceParams | None = None,
            height_m: float | None = None, reach_m: float = math.inf) -> NDArray[np.float64]:
    """Finite points, minus the floor (if ``height_m`` above it is known); with ``params.horizontal_only``
    those within the height band, projected to z = 0; only those closer than ``reach_m``.

    One boolean mask over the (typically ~2000) map particles, one copy of the few that pass: this runs
    at camera rate on the whole map."""
    if points_h_m is None:
        return np.zeros((0, 3))
    p = _finite_rows(points_h_m)
    keep = _avoidance_mask(p, params, height_m, reach_m)
    p = p[keep] if keep is not None else p.copy()
    if params is not None and params.horizontal_only:
        p[:, 2] = 0.0
    return p


def _constraint_points(points_h_m: ArrayLike | None, params: ReferenceParams, height_m: float | None,
                       reach_m: float, band: NDArray[np.float64] | None = None) -> NDArray[np.float64]:
    """The vectors (vehicle to obstacle, in H) the safety constraints act on: the band's points projected
    horizontally (``band``, if already computed by :func:`_points` with the same reach), the closest points
    of the surfaces they sample (:func:`surface_points`) and, with ``out_of_band_3d``, the other non-floor
    points in 3D."""
    if band is None:
        band = _points(points_h_m, params, height_m, reach_m)
    parts = [band, surface_points(band, params.surface_gap_m, params.influence_distance_m)]
    if params.horizontal_only and params.out_of_band_3d and points_h_m is not None:
        p = _finite_rows(points_h_m)
        keep = np.abs(p[:, 2]) > params.vertical_band_m
        keep &= np.einsum("ij,ij->i", p, p) < reach_m * reach_m
        if height_m is not None and math.isfinite(height_m):
            keep &= (height_m - p[:, 2]) > params.floor_margin_m
        parts.append(p[keep])
    return np.concatenate(parts) if any(x.shape[0] for x in parts[1:]) else band


def surface_points(points_h_m: NDArray[np.float64], max_gap_m: float, reach_m: float,
                   grid_m: float = 0.05, neighbours: int = 6) -> NDArray[np.float64]:
    """Closest points (to the vehicle at the origin) of the segments joining map points less than
    ``max_gap_m`` apart, for the points within ``reach_m + max_gap_m / 2``.

    A surface sampled by points is nearer than its nearest sample wherever the vehicle faces the gap
    between two samples; the segment between them is the surface's piecewise-linear stand-in. The points
    are thinned to one per ``grid_m`` cell first (the map holds several particles per measured point),
    then each is joined to its ``neighbours`` next points in azimuth as the vehicle sees them (the gaps
    that matter are between samples adjacent in the view; O(n) segments instead of all pairs). Only
    segments whose closest point lies strictly between their ends add a point (otherwise the end is
    itself a map point)."""
    if points_h_m.shape[0] < 2 or max_gap_m <= 0.0:
        return np.zeros((0, 3))
    p = points_h_m[np.einsum("ij,ij->i", points_h_m, points_h_m) < (reach_m + max_gap_m / 2.0) ** 2]
    if p.shape[0] < 2:
        return np.zeros((0, 3))
    cell = np.floor(p / grid_m).astype(np.int64) + (1 << 20)   # non-negative within +-50 km at 5 cm
    _, first = np.unique((cell[:, 0] << 42) | (cell[:, 1] << 21) | cell[:, 2], return_index=True)
    p = p[first]
    n = p.shape[0]
    if n < 2:
        return np.zeros((0, 3))
    p = p[np.argsort(np.arctan2(p[:, 1], p[:, 0]))]
    k = min(neighbours, n - 1)
    i = np.repeat(np.arange(n), k)
    j = (i + np.tile(np.arange(1, k + 1), n)) % n
    if 2 * k >= n:   # few points: the cyclic neighbours repeat pairs
        pair = np.unique(np.minimum(i, j) * n + np.maximum(i, j))
        i, j = pair // n, pair % n
    a, ab = p[i], p[j] - p[i]
    length2 = np.einsum("ij,ij->i", ab, ab)
    t = -np.einsum("ij,ij->i", a, ab) / np.maximum(length2, 1e-12)
    inner = (length2 < max_gap_m * max_gap_m) & (length2 > 1e-12) & (t > 1e-6) & (t < 1.0 - 1e-6)
    return a[inner] + t[inner, None] * ab[inner]


def avoidance_points(points_h_m: ArrayLike | None, params: ReferenceParams,
                     height_m: float | None = None) -> NDArray[np.float64]:
    """The map points the safety constraints act on, where they are (not projected): finite, not the floor
    (when ``height_m`` is known) and, with ``horizontal_only``, within the height band — plus, with
    ``out_of_band_3d``, the other non-floor points (as :func:`_constraint_points` takes them). What the operator
    is shown as obstacles and warned about, so the view never flags what the avoidance ignores (the floor)."""
    if points_h_m is None:
        return np.zeros((0, 3))
    p = _finite_rows(points_h_m)
    if params.horizontal_only and params.out_of_band_3d:
        keep = _avoidance_mask(p, None, None, math.inf)   # all finite points ...
        if height_m is not None and math.isfinite(height_m):
            keep = (height_m - p[:, 2]) > params.floor_margin_m   # ... but the floor
    else:
        keep = _avoidance_mask(p, params, height_m, math.inf)
    return p[keep] if keep is not None else p.copy()


def repulsion_velocity(points_h_m: ArrayLike | None, params: ReferenceParams,
                       height_m: float | None = None) -> NDArray[np.float64]:
    """v_o of eq. (7): summed repulsive-potential gradients of the map points (vehicle at the origin of H)."""
    return _repulsion(_points(points_h_m, params, height_m), params)


def _repulsion(p: NDArray[np.float64], params: ReferenceParams) -> NDArray[np.float64]:
    """:func:`repulsion_velocity` of points already through :func:`_points`."""
    if p.size == 0:
        return np.zeros(3)
    d = np.linalg.norm(p, axis=1)
    near = (d < params.influence_distance_m) & (d > 1e-6)
    if not np.any(near):
        return np.zeros(3)
    p, d = p[near], d[near]
    magnitude = params.repulsion_gain_m3_s * (1.0 / d - 1.0 / params.influence_distance_m) / d**2
    if params.combine == "weighted":
        total = float(magnitude.sum())
        if total <= 0.0:
            return np.zeros(3)
        magnitude = magnitude * (magnitude / total)   # w_j m_j, w_j = m_j / sum m
    v = np.sum((-p / d[:, None]) * magnitude[:, None], axis=0)
    speed = float(np.linalg.norm(v))
    if speed > params.max_repulsion_m_s:
        v *= params.max_repulsion_m_s / speed
    return v


def limit_speed_toward_obstacles(v_h_m_s: NDArray[np.float64], points_h_m: ArrayLike | None,
                                 safe_distance_m: float, approach_gain_per_s: float = math.inf,
                                 params: ReferenceParams | None = None, height_m: float | None = None,
                                 reach_m: float | None = None, v_est_h_m_s: ArrayLike | None = None,
                                 stopping_time_s: float = 0.0) -> tuple[NDArray[np.float64], bool]:
    """Limit the component of v toward each obstacle point j to the closing-speed law

        v . u_j <= k (d_j - d_safe - t_stop max(v_est . u_j, 0))        (k = ``approach_gain_per_s``)

    Outside the safe distance (up to ``reach_m``, default the influence distance of ``params``) the closing
    speed shrinks linearly to zero at the safe distance, like PX4's collision prevention, so the vehicle
    slows down in time whatever the lag of the velocity loop; the measured closing speed ``v_est`` (when
    given) times ``stopping_time_s`` is the distance the vehicle still travels before a new reference
    takes effect, and is counted as used up. That term damps the approach: for a velocity loop with time
    constant tau and t_stop >= tau, e = d - d_safe obeys tau e'' + (1 + k t_stop) e' + k e = 0, which
    is critically damped or slower for every k (without it, k tau > 1/4 overshoots the safe distance).
    Inside the safe distance the bound is negative: the vehicle is sent back out at k (d_safe - d), so it
    never rests inside it. ``approach_gain_per_s = inf`` keeps only the rule "no component toward points
    within the safe distance". Projection onto the half-spaces {v . u_j <= b_j}, repeated so that
    satisfying one constraint cannot leave another violated; if the constraints cannot all be met (the
    vehicle squeezed between points) the non-negative part of the bounds is used, and failing that the
    velocity is zero. With ``params`` the points are prepared as :func:`reference_velocity` does
    (height band, floor, surfaces between samples, points out of the band in 3D).
    """
    if reach_m is None:
        reach_m = params.influence_distance_m if params is not None else safe_distance_m
    p = _constraint_points(points_h_m, params, height_m, reach_m) if params is not None else \
        _points(points_h_m, None, None, reach_m)
    return _limit_speed(v_h_m_s, p, safe_distance_m, approach_gain_per_s, reach_m, v_est_h_m_s, stopping_time_s)


def _limit_speed(v_h_m_s: NDArray[np.float64], p: NDArray[np.float64], safe_distance_m: float,
                 approach_gain_per_s: float, reach_m: float, v_est_h_m_s: ArrayLike | None = None,
                 stopping_time_s: float = 0.0) -> tuple[NDArray[np.float64], bool]:
    """:func:`limit_speed_toward_obstacles` of points already prepared."""
    v = np.array(v_h_m_s, dtype=float)
    if p.size == 0:
        return v, False
    d = np.linalg.norm(p, axis=1)
    finite_gain = math.isfinite(approach_gain_per_s)
    reach_m = max(reach_m, safe_distance_m) if finite_gain else safe_distance_m
    close = (d < reach_m) & (d > 1e-6)
    if not np.any(close):
        return v, False
    d = d[close]
    u = p[close] / d[:, None]
    if finite_gain:
        margin = d - safe_distance_m
        if v_est_h_m_s is not None and stopping_time_s > 0.0:
            v_est = np.asarray(v_est_h_m_s, dtype=float)
            if np.all(np.isfinite(v_est)):
                margin = margin - stopping_time_s * np.maximum(u @ v_est, 0.0)
        bound = approach_gain_per_s * margin
    else:
        bound = np.zeros_like(d)
    out, ok = _project(v, u, bound)
    if not ok:
        # squeezed: no velocity meets every (negative) bound; settle for not closing in on any point
        out, ok = _project(v, u, np.maximum(bound, 0.0))
        if not ok:
            out[:] = 0.0
    return out, bool(np.any(np.abs(out - v) > 1e-12))


def _project(v: NDArray[np.float64], u: NDArray[np.float64], bound: NDArray[np.float64],
             iterations: int = 20) -> tuple[NDArray[np.float64], bool]:
    """Repeated projection of v onto the most violated half-space {x . u_j <= b_j}; converged?"""
    v = v.copy()
    for _ in range(iterations):
        excess = u @ v - bound
        worst = int(np.argmax(excess))
        if excess[worst] <= 1e-9:
            return v, True
        v = v - excess[worst] * u[worst]
    return v, bool(np.all(u @ v - bound <= 1e-6))


def remove_toward_close_obstacles(v_h_m_s: NDArray[np.float64], points_h_m: ArrayLike | None,
                                  safe_distance_m: float, params: ReferenceParams | None = None,
                                  height_m: float | None = None) -> tuple[NDArray[np.float64], bool]:
    """Remove from v every component toward an obstacle point closer than ``safe_distance_m``."""
    return limit_speed_toward_obstacles(v_h_m_s, points_h_m, safe_distance_m, math.inf, params, height_m)


def nearest_obstacle(points_h_m: ArrayLike | None, params: ReferenceParams) -> tuple[NDArray[np.float64], float] | None:
    """The nearest map point as the avoidance sees it: with ``horizontal_only``, a point within the height band
    counts by its horizontal distance (and is reported projected to z = 0) — the band stands for obstacles
    that extend vertically through the vehicle's height, which the camera, looking down, samples below it;
    other points (the floor, say) count by their 3D distance. None if there are no finite points."""
    if points_h_m is None:
        return None
    p = _finite_rows(points_h_m)
    if p.shape[0] == 0:
        return None
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    d2 = x * x + y * y
    if params.horizontal_only:
        d2 = np.where(np.abs(z) <= params.vertical_band_m, d2, d2 + z * z)
    else:
        d2 = d2 + z * z
    i = int(np.argmin(d2))
    v = p[i].copy()
    if params.horizontal_only and abs(v[2]) <= params.vertical_band_m:
        v[2] = 0.0
    return v, math.sqrt(float(d2[i]))


def sector_index(angle_rad: float, n_sectors: int, offset_rad: float = 0.0) -> int:
    """Sector of a direction in H (azimuth from +x toward +y); sector i is centred on offset + i 2 pi / n."""
    width = 2.0 * math.pi / n_sectors
    return int(math.floor((angle_rad - offset_rad + width / 2.0) / width)) % n_sectors


def remove_toward_unknown(v_h_m_s: NDArray[np.float64], sectors_m: ArrayLike | None,
                          guard_rad: float, offset_rad: float = 0.0) -> tuple[NDArray[np.float64], bool]:
    """Zero the horizontal velocity if it points (within ``guard_rad``) into a sector of unknown distance.

    ``sectors_m`` is the 360 deg sector array in H (NaN = unknown, inf = free), sector i centred on
    azimuth ``offset_rad + i 2 pi / n`` (perception's ObstacleSectors); None means nothing is known.
    Like PX4's collision prevention without CP_GO_NO_DATA: no motion toward where nothing is known.
    """
    v = np.array(v_h_m_s, dtype=float)
    speed = math.hypot(v[0], v[1])
    if speed < 1e-9:
        return v, False
    if sectors_m is None:
        v[:2] = 0.0
        return v, True
    s = np.asarray(sectors_m, dtype=float).ravel()
    n = s.size
    if n == 0:
        v[:2] = 0.0
        return v, True
    heading = math.atan2(v[1], v[0])
    width = 2.0 * math.pi / n
    steps = int(math.ceil(guard_rad / width))
    for k in range(-steps, steps + 1):
        if np.isnan(s[sector_index(heading + k * width, n, offset_rad)]):
            v[:2] = 0.0
            return v, True
    return v, False


def reference_velocity(op: OperatorInput, R_qc: ArrayLike, scan: PanScanState,
                       obstacle_points_h_m: ArrayLike | None, params: ReferenceParams,
                       sectors_m: ArrayLike | None = None, block_unknown: bool = False,
                       operator_enabled: bool = True, sector_offset_rad: float = 0.0,
                       height_m: float | None = None, v_est_h_m_s: ArrayLike | None = None,
                       v_command_h_m_s: ArrayLike | None = None, command_yaw_rate_rad_s: float = 0.0,
                       height_verified: bool = True
                       ) -> ReferenceOutput:
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
    (:mod:`companion.vertical_limits`: otherwise no climb toward a configured ceiling).
    """
    alpha = camera_yaw_rad(R_qc) + scan.yaw_offset_rad  # eq. (6)
    if height_m is not None:
        height_m = height_m + params.takeoff_height_m
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
    p = _points(obstacle_points_h_m, params, height_m, reach)   # the repulsion uses those within d_0
    v_o = _repulsion(p, params)
    if sectors_m is not None:
        # the repulsion is motion nobody commanded: like a script's, it never goes where the map has not
        # looked (campaign 3, flight 1: pan-scan off, the push off a seen wall carried the vehicle sideways
        # to 0.36 m of a partition's end it had never seen); inside the safe distance the speed law below
        # still sends the vehicle back out
        v_o, _ = remove_toward_unknown(v_o, sectors_m, params.unknown_sector_guard_rad, sector_offset_rad)
    v_r = v_d + v_o  # eq. (7)
    c = _constraint_points(obstacle_points_h_m, params, height_m, reach, band=p)
    v_r, removed = _limit_speed(v_r, c, params.safe_distance_m, params.approach_gain_per_s, reach, v_est_h_m_s,
                                params.stopping_time_s)
    v_up = None if v_est_h_m_s is None else -float(np.asarray(v_est_h_m_s, dtype=float)[2])
    limits = vertical_limits(height_m, v_up, params.vertical(), height_verified)
    v_r, vertical = apply_vertical_limits(v_r, limits)
    speed = float(np.linalg.norm(v_r))
    if speed > params.max_speed_m_s:
        v_r *= params.max_speed_m_s / speed
        constrained = True
    yaw_rate = yaw_rate_d + scan.yaw_rate_rad_s  # eq. (8)
    return ReferenceOutput(v_r, yaw_rate, v_d, v_o, alpha, scan.yaw_rate_rad_s, yaw_rate_d,
                           constrained or removed or vertical, limits)

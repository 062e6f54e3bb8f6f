"""What the obstacles do to the reference velocity (paper 000: v_o of eq. 7, and the safety constraints), pure.

Frames: everything is in H (horizontal, NED), the vehicle at its origin; the points come selected by
:mod:`companion.obstacle_points`.

* :func:`repulsion_velocity` is v_o of eq. (7), "the weighted sum of all contributions": each map point
  within d_0 contributes the gradient of a standard (Khatib) repulsive potential
  ``U_j = eta/2 (1/d_j - 1/d_0)^2``, i.e. ``v_j = m_j (-p_j / d_j)`` with ``m_j = eta (1/d_j - 1/d_0) / d_j^2``,
  and the weights are ``w_j = m_j / sum_k m_k``. The weighted sum keeps the direction of the plain sum but
  its size is that of the nearest points, whatever the number of points sampling a surface (a column seen
  in ten image sectors, each point as several map particles, would otherwise push ten times harder and
  stop the vehicle far outside the safe distance). ``combine="sum"`` is the plain superposition. The
  result is limited to ``max_repulsion_m_s``.
* :func:`limit_speed_toward_obstacles` is the closing-speed law: a closing speed toward each obstacle point
  within reach of at most ``approach_gain_per_s (d - safe distance)`` — zero at the safe distance, negative
  inside it; :func:`remove_toward_close_obstacles` keeps only its rule "no component toward points within
  the safe distance".
* :func:`remove_toward_unknown`: no horizontal motion toward sectors of unknown distance (when the obstacle
  data are stale or unknown sectors are not allowed).

:func:`companion.reference.reference_velocity` composes them with the operator's command (see its module).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from companion.obstacle_points import constraint_points, select_points
from companion.reference_params import ReferenceParams


def repulsion_velocity(points_h_m: ArrayLike | None, params: ReferenceParams,
                       height_m: float | None = None) -> NDArray[np.float64]:
    """v_o of eq. (7): summed repulsive-potential gradients of the map points (vehicle at the origin of H)."""
    return repulsion_prepared(select_points(points_h_m, params, height_m), params)


def repulsion_prepared(p: NDArray[np.float64], params: ReferenceParams) -> NDArray[np.float64]:
    """:func:`repulsion_velocity` of points already through :func:`companion.obstacle_points.select_points`."""
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
    velocity is zero. With ``params`` the points are prepared as :func:`companion.reference.reference_velocity` does
    (height band, floor, surfaces between samples, points out of the band in 3D).
    """
    if reach_m is None:
        reach_m = params.influence_distance_m if params is not None else safe_distance_m
    p = constraint_points(points_h_m, params, height_m, reach_m) if params is not None else \
        select_points(points_h_m, None, None, reach_m)
    return limit_speed_prepared(v_h_m_s, p, safe_distance_m, approach_gain_per_s, reach_m, v_est_h_m_s, stopping_time_s)


def limit_speed_prepared(v_h_m_s: NDArray[np.float64], p: NDArray[np.float64], safe_distance_m: float,
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

"""Which map points the avoidance acts on (pure): the obstacle map's points in H (vehicle at the origin), as the
repulsion and the safety constraints (:mod:`companion.avoidance`) and the operator's view take them.

With ``horizontal_only`` (:class:`companion.reference_params.ReferenceParams`) the points within
``vertical_band_m`` of the vehicle's height stand for obstacles that extend through it (the camera, looking
down, samples them below the vehicle): they act by their horizontal distance, projected to z = 0. Points
within ``floor_margin_m`` of the floor, once the height is known, are the floor, not obstacles. With
``out_of_band_3d`` the other points constrain the motion by their 3D distance. A surface sampled by points
is stood in for by the segments between neighbouring samples (:func:`surface_points`).
:func:`nearest_obstacle` is the nearest point as TELEOP_FEEDBACK and the operator image report it.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from companion.reference_params import ReferenceParams
from perception.obstacle_map import sector_index


def finite_rows(points_h_m: ArrayLike) -> NDArray[np.float64]:
    """Points as N x 3 floats without the rows holding a NaN or inf (one flat check first: rows are only
    filtered when something is wrong)."""
    p = np.asarray(points_h_m, dtype=float).reshape(-1, 3)
    return p if np.isfinite(p).all() else p[np.isfinite(p).all(axis=1)]


def drifted_toward(points_h_m: ArrayLike | None, ages_s: ArrayLike | None,
                   drift_m_s: float) -> NDArray[np.float64] | None:
    """The map's points moved toward the vehicle, horizontally, by the distance the odometry may have drifted
    since each was last seen: ``drift_m_s`` x its age, at most half its horizontal distance (the direction is
    kept, so it still stands for the same surface).

    A particle is carried with the estimated velocity (eq. 14); a velocity error that persists (a bias of
    1-2 cm/s, the campaigns' velocity-estimate RMSE) moves the real vehicle toward a surface the camera no
    longer sees while the particle stays where it was: resting in a corner with the pan-scan on, the truth
    crept from 0.53 to 0.45 m in 5 s while the map kept reading 0.45 m (issue 14, the real-time corner push).
    What the camera sees again is measured afresh (age 0) and carries no margin. None or mismatched ages:
    the points unchanged."""
    if points_h_m is None or ages_s is None or not drift_m_s > 0.0:
        return None if points_h_m is None else np.asarray(points_h_m, dtype=float)
    p = np.asarray(points_h_m, dtype=float).reshape(-1, 3)
    age = np.asarray(ages_s, dtype=float).reshape(-1)
    if age.shape[0] != p.shape[0] or not p.shape[0]:
        return p
    horiz = np.hypot(p[:, 0], p[:, 1])
    margin = drift_m_s * np.where(np.isfinite(age) & (age > 0.0), age, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(horiz > 0.0, np.maximum(1.0 - margin / horiz, 0.5), 1.0)
    out = p.copy()
    out[:, 0] *= scale
    out[:, 1] *= scale
    return out


COLUMN_GRID_M = 0.05   # one upward extension per cell of this size: a wall's particles come in copies
TOP_NEAR_M = 0.1       # a top seen over within about this (one cell of it, or the next) horizontally caps a point
TOP_LEVEL_M = 0.10     # ... and so does one up to this much lower than it: the map's copies of one flat top scatter
                       # (the measurement's noise, 2 cm per m of range, and eq. 14's, 2 cm after 6 s, 4 cm after the
                       # near field's 20 s), and open copies of a box's top edge (its probe fell in the projector's
                       # shadow past the edge, in the blind zone) stood 2 and 6 cm (aged 6.5 s) above their seen-over
                       # neighbours, uncapped: extended to columns 0.42 and 0.34 m away, they pushed the vehicle
                       # hovering over the box up to 0.5 m aside (the LAND-over-a-box test)


def with_open_tops(points: ArrayLike, open_top: ArrayLike | None, height_m: float | None = None,
                   floor_margin_m: float = 0.0) -> NDArray[np.float64]:
    """The points, plus one at the vehicle's level (z = 0) above each point below it whose top no ray passed over
    (``open_top``, perception's ``ObstacleMap.open_top``) and that no top seen over caps (a point the rays passed
    over, higher or level with it to ``TOP_LEVEL_M``, within about ``TOP_NEAR_M`` horizontally: a box's top edge
    above its front face, the rest of a flat top beside one of its copies): the surface it
    samples may reach the vehicle's height, as a wall the camera saw from lower down does, so it acts on the
    avoidance by its horizontal distance and counts as beside the vehicle, not below it
    (:mod:`companion.landing_spot`). Not for points of the floor (within ``floor_margin_m`` of it, ``height_m`` below
    the vehicle, when known). Thinned to one per 5 cm cell. A mismatched ``open_top``: the points unchanged."""
    points_h_m = np.asarray(points, dtype=float).reshape(-1, 3)
    if open_top is None:
        return points_h_m
    flags = np.asarray(open_top, dtype=bool).reshape(-1)
    if flags.shape[0] != points_h_m.shape[0] or not flags.any():
        return points_h_m
    x, y, z = points_h_m[:, 0], points_h_m[:, 1], points_h_m[:, 2]
    finite = np.isfinite(x) & np.isfinite(y) & np.isfinite(z)   # (.all(axis=1) on N x 3 is the slow reduction)
    up = flags & finite & (z > 0.0)
    if height_m is not None and math.isfinite(height_m):
        up &= (height_m - z) > floor_margin_m
    q = points_h_m[up]
    if not q.shape[0]:
        return points_h_m
    seen = points_h_m[~flags & finite]
    if seen.shape[0]:
        q = q[~_capped(q, seen)]   # before the thinning: a cell keeps its column if any of its points is uncapped
    if not q.shape[0]:
        return points_h_m
    _, first = np.unique(_cell_keys(np.floor(q[:, :2] / COLUMN_GRID_M).astype(np.int64)), return_index=True)
    q = q[first]
    columns = np.column_stack([q[:, 0], q[:, 1], np.zeros(q.shape[0])])
    return np.concatenate([points_h_m, columns]) if columns.shape[0] else points_h_m


def _capped(q: NDArray[np.float64], seen: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Which points of ``q`` have a seen-over point higher than them (smaller z), or less than ``TOP_LEVEL_M`` lower,
    in their ``TOP_NEAR_M`` cell or the eight around it: per cell the highest seen point, then nine sorted look-ups
    (no tree per frame)."""
    # only the seen points that could cap one: not too low for the lowest candidate, near the candidates' box
    lo, hi = q[:, :2].min(axis=0) - 2 * TOP_NEAR_M, q[:, :2].max(axis=0) + 2 * TOP_NEAR_M
    near = (seen[:, 2] < q[:, 2].max() + TOP_LEVEL_M) & (seen[:, 0] >= lo[0]) & (seen[:, 1] >= lo[1]) \
        & (seen[:, 0] <= hi[0]) & (seen[:, 1] <= hi[1])
    seen = seen[near]
    if not seen.shape[0]:
        return np.zeros(q.shape[0], dtype=bool)
    k = _cell_keys(np.floor(seen[:, :2] / TOP_NEAR_M).astype(np.int64))
    order = np.argsort(k, kind="stable")
    k, zs = k[order], seen[order, 2]
    start = np.flatnonzero(np.r_[True, k[1:] != k[:-1]])
    uk, highest = k[start], np.minimum.reduceat(zs, start)   # per cell, its smallest z (the highest point)
    qc = np.floor(q[:, :2] / TOP_NEAR_M).astype(np.int64)
    capped = np.zeros(q.shape[0], dtype=bool)
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            kk = _cell_keys(qc + np.array([di, dj]))
            i = np.minimum(np.searchsorted(uk, kk), uk.size - 1)
            capped |= (uk[i] == kk) & (highest[i] < q[:, 2] + TOP_LEVEL_M)
    return capped


def _cell_keys(ij: NDArray[np.int64]) -> NDArray[np.int64]:
    """One int64 per 2D integer cell (each index within +-2^31)."""
    return (ij[:, 0] << 32) + (ij[:, 1] & 0xFFFFFFFF)


def avoidance_mask(p: NDArray[np.float64], params: ReferenceParams | None, height_m: float | None,
                   reach_m: float) -> NDArray[np.bool_] | None:
    """Which of the finite points ``p`` the avoidance acts on (None: all of them); see :func:`select_points`."""
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


def select_points(points_h_m: ArrayLike | None, params: ReferenceParams | None = None,
                  height_m: float | None = None, reach_m: float = math.inf) -> NDArray[np.float64]:
    """Finite points, minus the floor (if ``height_m`` above it is known); with ``params.horizontal_only``
    those within the height band, projected to z = 0; only those closer than ``reach_m``.

    One boolean mask over the (typically ~2000) map particles, one copy of the few that pass: this runs
    at camera rate on the whole map."""
    if points_h_m is None:
        return np.zeros((0, 3))
    p = finite_rows(points_h_m)
    keep = avoidance_mask(p, params, height_m, reach_m)
    p = p[keep] if keep is not None else p.copy()
    if params is not None and params.horizontal_only:
        p[:, 2] = 0.0
    return p


def constraint_points(points_h_m: ArrayLike | None, params: ReferenceParams, height_m: float | None,
                      reach_m: float, band: NDArray[np.float64] | None = None) -> NDArray[np.float64]:
    """The vectors (vehicle to obstacle, in H) the safety constraints act on: the band's points projected
    horizontally (``band``, if already computed by :func:`select_points` with the same reach), the closest points
    of the surfaces they sample (:func:`surface_points`) and, with ``out_of_band_3d``, the other non-floor
    points in 3D."""
    if band is None:
        band = select_points(points_h_m, params, height_m, reach_m)
    parts = [band, surface_points(band, params.surface_gap_m, params.influence_distance_m)]
    if params.horizontal_only and params.out_of_band_3d and points_h_m is not None:
        p = finite_rows(points_h_m)
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
    ``out_of_band_3d``, the other non-floor points (as :func:`constraint_points` takes them). What the operator
    is shown as obstacles and warned about, so the view never flags what the avoidance ignores (the floor)."""
    if points_h_m is None:
        return np.zeros((0, 3))
    p = finite_rows(points_h_m)
    if params.horizontal_only and params.out_of_band_3d:
        keep = avoidance_mask(p, None, None, math.inf)   # all finite points ...
        if height_m is not None and math.isfinite(height_m):
            keep = (height_m - p[:, 2]) > params.floor_margin_m   # ... but the floor
    else:
        keep = avoidance_mask(p, params, height_m, math.inf)
    return p[keep] if keep is not None else p.copy()


def sector_distances_m(points_h_m: ArrayLike | None, map_distances_m: ArrayLike, increment_deg: float,
                       angle_offset_deg: float, min_distance_m: float, band_m: float) -> NDArray[np.float64]:
    """OBSTACLE_DISTANCE's sectors (in H, sector i centred at ``angle_offset_deg + i * increment_deg``) as the
    avoidance sees the map: per sector the horizontal distance of the nearest of its points within ``band_m``
    of the vehicle's height (``points_h_m``: :func:`avoidance_points`, the floor already left out), at least
    ``min_distance_m``; a sector without one reads free (inf) where the map observed it lately and unknown (NaN)
    where it did not (``map_distances_m``: the map's own summary, NaN = unknown). So a ground station is shown
    what the vehicle keeps away from, not a floor particle the avoidance never acts on."""
    known = np.asarray(map_distances_m, dtype=float).ravel()
    out = np.where(np.isnan(known), np.nan, np.inf)
    n = out.size
    if points_h_m is None or n == 0:
        return out
    p = finite_rows(points_h_m)
    p = p[np.abs(p[:, 2]) <= band_m]
    if p.shape[0] == 0:
        return out
    index = sector_index(np.arctan2(p[:, 1], p[:, 0]), n, math.radians(angle_offset_deg))
    best = np.full(n, np.inf)
    np.minimum.at(best, index, np.hypot(p[:, 0], p[:, 1]))
    return np.where(best < np.inf, np.maximum(best, min_distance_m), out)


def nearest_obstacle(points_h_m: ArrayLike | None, params: ReferenceParams) -> tuple[NDArray[np.float64], float] | None:
    """The nearest map point as the avoidance sees it: with ``horizontal_only``, a point within the height band
    counts by its horizontal distance (and is reported projected to z = 0) — the band stands for obstacles
    that extend vertically through the vehicle's height, which the camera, looking down, samples below it;
    other points (the floor, say) count by their 3D distance. None if there are no finite points."""
    if points_h_m is None:
        return None
    p = finite_rows(points_h_m)
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

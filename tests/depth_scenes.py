"""Depth images of ray-cast scenes for the perception tests (no renderer, no SITL): a floor, full-height columns
and a box, intersected exactly and seen by the vehicle's camera mount (45 deg right, 30 deg down, portrait) at the
SITL's QVGA intrinsics, with structured-light noise. A dark column returns nothing, as the Xtion model's dark and
specular materials do (sim_sitl/xtion.py); the driver reports nothing nearer than 0.5 m or beyond 3.5 m.
Used by ``tests/unit/test_hidden_floor.py`` and ``tests/unit/test_open_top.py``.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from quadlink.camera import CameraIntrinsics

R_QC = np.array([[-0.353553, 0.707107, 0.612372], [-0.353553, -0.707107, 0.612372], [0.866025, 0.0, 0.5]])
P_QC_M = np.array([0.08, 0.08, 0.05])
K = CameraIntrinsics.from_fov(320, 240, 58.0, 45.0)
VIEW_AZ_RAD = math.atan2(R_QC[1, 2], R_QC[0, 2])   # the camera's horizontal view direction in H (45 deg right)


def column_at(distance_m: float, offset_rad: float = 0.0, radius_m: float = 0.15, dark: bool = True
              ) -> tuple[float, float, float, bool]:
    """A column whose axis is ``distance_m`` from the body, ``offset_rad`` off the camera's view azimuth."""
    a = VIEW_AZ_RAD + offset_rad
    return distance_m * math.cos(a), distance_m * math.sin(a), radius_m, dark


def render(height_m: float, columns: list[tuple[float, float, float, bool]], rng: np.random.Generator | None = None,
           dropout: float = 0.0, R_hc: NDArray[np.float64] = R_QC, p_hc_m: NDArray[np.float64] = P_QC_M
           ) -> NDArray[np.float32]:
    """Depth (optical z, m; 0 = no reading) of a floor ``height_m`` below the body and full-height columns
    (x, y, radius, dark) in H, seen by a camera at ``R_hc``, ``p_hc_m`` in H; a dark column's pixels read 0."""
    u, v = np.meshgrid(np.arange(K.width, dtype=float), np.arange(K.height, dtype=float))
    rays_c = np.stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones_like(u)], axis=-1)
    d = rays_c @ R_hc.T
    o = p_hc_m
    with np.errstate(divide="ignore", invalid="ignore"):
        t_floor = (height_m - o[2]) / d[..., 2]
    t = np.where(t_floor > 0, t_floor, np.inf)
    dark_hit = np.zeros(u.shape, dtype=bool)
    for cx, cy, r, dark in columns:
        # |o_xy + t d_xy - c|^2 = r^2
        ox, oy = o[0] - cx, o[1] - cy
        a = d[..., 0] ** 2 + d[..., 1] ** 2
        b = 2.0 * (ox * d[..., 0] + oy * d[..., 1])
        c = ox * ox + oy * oy - r * r
        disc = b * b - 4.0 * a * c
        with np.errstate(invalid="ignore"):
            t_col = (-b - np.sqrt(disc)) / (2.0 * a)
        hit = (disc >= 0) & (t_col > 0) & (t_col < t)
        t = np.where(hit, t_col, t)
        dark_hit = np.where(hit, dark, dark_hit & ~hit)
    depth = t
    if rng is not None:
        noise = rng.normal(0.0, 1.0, depth.shape) * (0.0012 + 0.0019 * (np.minimum(depth, 1e3) - 0.4) ** 2)
        depth = depth + noise
        if dropout > 0.0:
            depth = np.where(rng.random(depth.shape) < dropout, 0.0, depth)
    depth = np.where(np.isfinite(depth) & (depth <= 3.5) & (depth >= 0.5) & ~dark_hit, depth, 0.0)
    return depth.astype(np.float32)


def render_box_with_shadow(height_m: float, near_m: float, depth_m: float, half_width_m: float, top_m: float,
                           shadow_m: float, rng: np.random.Generator) -> NDArray[np.float32]:
    """A matte box on the floor along the camera's view direction (from ``near_m`` to ``near_m + depth_m`` ahead,
    ``half_width_m`` to each side, ``top_m`` high) and the structured light's shadow of its top edge: the floor
    from its far side to ``shadow_m`` beyond returns nothing."""
    u, v = np.meshgrid(np.arange(K.width, dtype=float), np.arange(K.height, dtype=float))
    rays_c = np.stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones_like(u)], axis=-1)
    d = rays_c @ R_QC.T
    o = P_QC_M
    fwd = np.array([math.cos(VIEW_AZ_RAD), math.sin(VIEW_AZ_RAD), 0.0])
    side = np.array([-fwd[1], fwd[0], 0.0])
    with np.errstate(divide="ignore", invalid="ignore"):
        t_floor = (height_m - o[2]) / d[..., 2]
        t = np.where(t_floor > 0, t_floor, np.inf)
        # slabs: along fwd [near, near + depth], along side [-w, w], z in [height - top, height] (H z down)
        lo = np.full(u.shape, -np.inf)
        hi = np.full(u.shape, np.inf)
        for axis, a, b in ((fwd, near_m, near_m + depth_m), (side, -half_width_m, half_width_m),
                           (np.array([0.0, 0.0, 1.0]), height_m - top_m, height_m)):
            da, oa = d @ axis, float(o @ axis)
            t1, t2 = (a - oa) / da, (b - oa) / da
            lo = np.maximum(lo, np.minimum(t1, t2))
            hi = np.minimum(hi, np.maximum(t1, t2))
        hit = (lo <= hi) & (lo > 0) & (lo < t)
        t = np.where(hit, lo, t)
        floor_pt = o + d * t_floor[..., None]
        along, across = floor_pt @ fwd, floor_pt @ side
        shadow = ~hit & (t == t_floor) & (along >= near_m + depth_m) & (along <= near_m + depth_m + shadow_m) \
            & (np.abs(across) <= half_width_m)
    depth = t + rng.normal(0.0, 1.0, t.shape) * (0.0012 + 0.0019 * (np.minimum(t, 1e3) - 0.4) ** 2)
    depth = np.where(np.isfinite(depth) & (depth <= 3.5) & (depth >= 0.5) & ~shadow, depth, 0.0)
    return depth.astype(np.float32)

"""Obstacle points from the depth image (paper 000 section III).

The depth image is divided into ``n x m`` sectors; in each, the valid pixel closest to the camera (by
range, within ``[min_range, max_range]``) gives ``C p_ij``; with the extrinsics ``R_QC, Q p_C`` and the
estimated roll and pitch it becomes ``H p_ij = R_HQ (R_QC C p_ij + Q p_C)``. A sector whose valid pixels
are all beyond ``max_range`` is *free*; one without any valid pixel is *unobserved*.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from quadlink.camera import CameraIntrinsics
from quadlink.frames import R_hq


@dataclass(frozen=True)
class ObstacleConfig:
    rows: int = 6                 # n: sectors along the image height
    cols: int = 8                 # m: sectors along the image width
    min_range_m: float = 0.5      # the sensor's minimum range (Xtion/Kinect-class: 0.5 m): nearer it is blind
    max_range_m: float = 3.5


@dataclass(frozen=True)
class SectorObservation:
    """Per-sector result of one frame (arrays of shape (n*m,), sector-major by rows)."""

    points_c_m: NDArray[np.float64]     # (K, 3) closest points of the sectors that have one, camera frame
    points_h_m: NDArray[np.float64]     # (K, 3) the same points in H
    ranges_m: NDArray[np.float64]       # (n*m,) closest range; inf = free, nan = unobserved
    rays_h: NDArray[np.float64]         # (n*m, 3) unit rays through the sector centres, in H
    R_hc: NDArray[np.float64]           # camera -> H rotation used (R_HQ R_QC)
    p_hc_m: NDArray[np.float64]         # camera origin in H
    intrinsics: CameraIntrinsics
    rows: int
    cols: int
    min_range_m: float = 0.0            # nearer than this the sensor sees nothing: no evidence of free space
    open_top: NDArray[np.bool_] | None = None  # (K,) no ray of this frame passed over the point (top_seen_over)

    def sector_and_range_of_points_h(self, points_h_m: NDArray[np.float64]) -> tuple[NDArray[np.intp],
                                                                                   NDArray[np.float64]]:
        """Sector index (row-major, -1 where not in the image) and range from the camera of points in H."""
        K = self.intrinsics
        # camera coordinates, one row per axis: R_hc^T (p - p_hc)
        pc = self.R_hc.T @ points_h_m.T - (self.R_hc.T @ self.p_hc_m)[:, None]
        x, y, z = pc
        bw, bh = K.width // self.cols, K.height // self.rows
        ok = z > 1e-3
        inv_z = 1.0 / np.where(ok, z, 1.0)
        # sector column / row as pixel coordinate over block size: (f x / z + c) / b
        col = x * inv_z * (K.fx / bw) + K.cx / bw
        row = y * inv_z * (K.fy / bh) + K.cy / bh
        ok &= (col >= 0.0) & (row >= 0.0) & (col < self.cols) & (row < self.rows)
        sector = np.where(ok, row.astype(np.intp) * self.cols + col.astype(np.intp), -1)
        return sector, np.sqrt(np.einsum("ij,ij->j", pc, pc))


@dataclass(frozen=True)
class _SectorGrid:
    """Constant geometry of the n x m sector grid of one image size (cached per intrinsics)."""

    rows: int
    cols: int
    block_h: int
    block_w: int
    ray_norms: NDArray[np.float32]      # (rows*block_h, cols*block_w) range per unit depth |(x/z, y/z, 1)|
    top: NDArray[np.intp]               # (n*m,) first pixel row of each sector
    left: NDArray[np.intp]              # (n*m,) first pixel column of each sector
    pixel: NDArray[np.intp]             # (n*m, bh*bw) flat image index of each pixel of each sector
    pixel_rays: NDArray[np.float64]     # (n*m, bh*bw, 3) (x/z, y/z, 1) of each pixel of each sector
    rays_c: NDArray[np.float64]         # (n*m, 3) unit rays through the sector centres, camera frame


@lru_cache(maxsize=8)
def _sector_grid(K: CameraIntrinsics, height: int, width: int, rows: int, cols: int) -> _SectorGrid:
    bh, bw = height // rows, width // cols
    u, v = np.meshgrid(np.arange(bw * cols, dtype=np.float32), np.arange(bh * rows, dtype=np.float32))
    norms = np.sqrt(((u - K.cx) / K.fx) ** 2 + ((v - K.cy) / K.fy) ** 2 + 1.0).astype(np.float32)
    si, sj = np.divmod(np.arange(rows * cols), cols)
    # per sector, its pixels in row-major order (the order of the argmin over a sector's block)
    v_blk = (si * bh)[:, None] + np.repeat(np.arange(bh), bw)[None, :]
    u_blk = (sj * bw)[:, None] + np.tile(np.arange(bw), bh)[None, :]
    pixel_rays = np.stack([(u_blk - K.cx) / K.fx, (v_blk - K.cy) / K.fy, np.ones(v_blk.shape)], axis=-1)
    uc = (sj + 0.5) * bw
    vc = (si + 0.5) * bh
    rays_c = np.column_stack([(uc - K.cx) / K.fx, (vc - K.cy) / K.fy, np.ones(rows * cols)])
    rays_c /= np.linalg.norm(rays_c, axis=1, keepdims=True)
    return _SectorGrid(rows, cols, bh, bw, norms, si * bh, sj * bw, v_blk * width + u_blk, pixel_rays, rays_c)


def extract_obstacles(depth_m: NDArray[np.float32], K: CameraIntrinsics, R_qc: NDArray[np.float64],
                      p_qc_m: NDArray[np.float64], roll_rad: float, pitch_rad: float,
                      config: ObstacleConfig | None = None) -> SectorObservation:
    cfg = config or ObstacleConfig()
    n, m = cfg.rows, cfg.cols
    g = _sector_grid(K, *depth_m.shape, n, m)
    bh, bw = g.block_h, g.block_w
    depth = depth_m[: bh * n, : bw * m]
    # One key per pixel whose per-sector minimum tells all three cases: the range of a valid pixel (near
    # ones are below max_range, far ones above it) and inf for no reading (depth 0, NaN, closer than
    # min_range).
    key = depth * g.ray_norms
    min_range = max(cfg.min_range_m, float(np.finfo(key.dtype).tiny))   # depth 0 is no reading even at 0 m
    np.copyto(key, np.inf, where=~(key >= min_range))
    blocks = key.reshape(n, bh, m, bw).transpose(0, 2, 1, 3).reshape(n * m, bh * bw)
    idx = np.argmin(blocks, axis=1)
    best = blocks[np.arange(n * m), idx].astype(float)
    has = best <= cfg.max_range_m
    ranges = np.where(has, best, np.where(np.isinf(best), np.nan, np.inf))
    for s in np.isinf(best).nonzero()[0]:
        # an infinite depth is a valid reading beyond range (REP 117: no return), not a missing one
        if (depth[g.top[s]: g.top[s] + bh, g.left[s]: g.left[s] + bw] == np.inf).any():
            ranges[s] = np.inf
    # the chosen pixels: C p_ij = z (x/z, y/z, 1)
    sel = has.nonzero()[0]
    j = idx[sel]
    z = np.ravel(depth_m)[g.pixel[sel, j]].astype(float)
    pc = g.pixel_rays[sel, j] * z[:, None]
    R_h = R_hq(roll_rad, pitch_rad)
    R_hc = R_h @ R_qc
    p_hc = R_h @ p_qc_m
    ph = pc @ R_hc.T + p_hc   # H p_ij = R_HQ (R_QC C p_ij + Q p_C)
    open_top = ~top_seen_over(pc, depth_m, K, R_hc, cfg.min_range_m)
    return SectorObservation(pc, ph, ranges, g.rays_c @ R_hc.T, R_hc, p_hc, K, n, m, cfg.min_range_m, open_top)


#: how far above a measured point the camera must have seen past it for the point to be a top (m)
TOP_PROBE_M = 0.10


def top_seen_over(points_c_m: NDArray[np.float64], depth_m: NDArray[np.float32], K: CameraIntrinsics,
                  R_hc: NDArray[np.float64], min_range_m: float, probe_m: float = TOP_PROBE_M) -> NDArray[np.bool_]:
    """Whether this frame's rays passed over each point (K x 3, camera frame): the point ``probe_m`` above it (H's
    up, -z) is in the image, and the pixel it falls on measured something farther along its ray than it (the
    floor or a wall behind), or nothing within range (the driver's 0 past ``max_range``; not where the probe is
    nearer than ``min_range_m``, where the sensor is blind).

    The camera looks 30 deg down and its upper ray is about level: a wall is seen up to the camera's height and no
    higher, and the highest points seen of it look like a top. They are not one: the probe above them falls
    outside the image, or on the wall itself. Seen from below, a wall's "top" lies under the vehicle once it
    climbs; taken for an object below, it refused a LAND, and taken for a low obstacle (3D distance past the
    avoidance's band), the vehicle slid over it to 0.18 m of the doorway beside it (falsify trial 48, 58). The
    map keeps the flag per particle (``ObstacleMap.open_top``) and the companion extends such points upward
    (:func:`companion.obstacle_points.with_open_tops`). A dark or shiny surface that returns nothing above a seen
    part reads as seen over: the hidden-floor detector covers those it can."""
    if not points_c_m.shape[0]:
        return np.zeros(0, dtype=bool)
    up_c = R_hc.T @ np.array([0.0, 0.0, -probe_m])      # H's up, in the camera frame
    q = points_c_m + up_c
    z = q[:, 2]
    ok = z > 1e-3
    inv_z = 1.0 / np.where(ok, z, 1.0)
    u = np.floor(q[:, 0] * inv_z * K.fx + K.cx + 0.5)
    v = np.floor(q[:, 1] * inv_z * K.fy + K.cy + 0.5)
    h, w = depth_m.shape
    ok &= (u >= 0.0) & (v >= 0.0) & (u < w) & (v < h)
    seen = np.zeros(points_c_m.shape[0], dtype=bool)
    i = ok.nonzero()[0]
    if i.size:
        d = depth_m[v[i].astype(np.intp), u[i].astype(np.intp)].astype(float)
        zi = z[i]
        # farther along the probe's ray than the probe (by the sensor's noise, ~1 cm at 2 m, and a margin), or no
        # return at all (0, NaN: past the range, not in the blind zone) or a return past range (inf, REP 117)
        # (the sensor's minimum is on the optical axis's depth, which a near probe off-axis reaches first)
        blind = zi < min_range_m + 0.1
        seen[i] = (~(d > 0.0) & ~blind) | (d == np.inf) | (d > zi + 0.05 + 0.01 * zi * zi)
    return seen

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
    min_range_m: float = 0.3
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

    def sector_of_points_h(self, points_h_m: NDArray[np.float64]) -> NDArray[np.intp]:
        """Sector index (row-major) of points given in H, or -1 where they are not in the image."""
        K = self.intrinsics
        pc = (points_h_m - self.p_hc_m) @ self.R_hc          # R_hc^T (p - p_hc), row-wise
        z = pc[:, 2]
        ok = z > 1e-3
        zs = np.where(ok, z, 1.0)
        u = K.fx * pc[:, 0] / zs + K.cx
        v = K.fy * pc[:, 1] / zs + K.cy
        bw, bh = K.width // self.cols, K.height // self.rows
        ok &= (u >= 0) & (v >= 0) & (u < bw * self.cols) & (v < bh * self.rows)
        si = np.minimum(np.maximum(v, 0.0) // bh, self.rows - 1).astype(np.intp)
        sj = np.minimum(np.maximum(u, 0.0) // bw, self.cols - 1).astype(np.intp)
        return np.where(ok, si * self.cols + sj, -1)


@lru_cache(maxsize=8)
def _ray_norms(K: CameraIntrinsics) -> NDArray[np.float32]:
    """Range per unit depth for every pixel: |(x/z, y/z, 1)|."""
    u, v = np.meshgrid(np.arange(K.width, dtype=np.float32), np.arange(K.height, dtype=np.float32))
    return np.sqrt(((u - K.cx) / K.fx) ** 2 + ((v - K.cy) / K.fy) ** 2 + 1.0).astype(np.float32)


def extract_obstacles(depth_m: NDArray[np.float32], K: CameraIntrinsics, R_qc: NDArray[np.float64],
                      p_qc_m: NDArray[np.float64], roll_rad: float, pitch_rad: float,
                      config: ObstacleConfig | None = None) -> SectorObservation:
    cfg = config or ObstacleConfig()
    h, w = depth_m.shape
    n, m = cfg.rows, cfg.cols
    bh, bw = h // n, w // m
    depth = depth_m[: bh * n, : bw * m]
    rng = depth * _ray_norms(K)[: bh * n, : bw * m]
    valid = (depth > 0) & (rng >= cfg.min_range_m)
    near = valid & (rng <= cfg.max_range_m)
    r_near = np.where(near, rng, np.inf)
    blocks = r_near.reshape(n, bh, m, bw).transpose(0, 2, 1, 3).reshape(n * m, bh * bw)
    idx = np.argmin(blocks, axis=1)
    best = blocks[np.arange(n * m), idx]
    any_valid = valid.reshape(n, bh, m, bw).any(axis=(1, 3)).reshape(n * m)
    ranges = np.where(np.isfinite(best), best, np.where(any_valid, np.inf, np.nan))
    # pixel coordinates of the chosen pixels
    si, sj = np.divmod(np.arange(n * m), m)
    bi, bj = np.divmod(idx, bw)
    v = (si * bh + bi).astype(float)
    u = (sj * bw + bj).astype(float)
    has = np.isfinite(best)
    z = depth[v[has].astype(int), u[has].astype(int)].astype(float)
    pc = np.column_stack([(u[has] - K.cx) / K.fx * z, (v[has] - K.cy) / K.fy * z, z])
    R_h = R_hq(roll_rad, pitch_rad)
    ph = (pc @ R_qc.T + p_qc_m) @ R_h.T   # H p_ij = R_HQ (R_QC C p_ij + Q p_C)
    uc = (sj + 0.5) * bw
    vc = (si + 0.5) * bh
    rays_c = np.column_stack([(uc - K.cx) / K.fx, (vc - K.cy) / K.fy, np.ones(n * m)])
    rays_c /= np.linalg.norm(rays_c, axis=1, keepdims=True)
    rays_h = rays_c @ (R_h @ R_qc).T
    return SectorObservation(pc, ph, ranges, rays_h, R_h @ R_qc, R_h @ p_qc_m, K, n, m)

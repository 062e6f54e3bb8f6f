"""The floor under the vehicle, measured in one depth image (pure): the vehicle's height above it.

The odometry's height drifts with the distance climbed and starts wherever the odometry started (in the air
when it failed on the ground: campaign flight 28 started 0.2 m up, and a climb then came 0.2 m closer to the
ceiling than its limit). The camera looks 30 deg down, so the floor is in view at any height the vehicle
flies indoors (its lower edge reaches the floor within the depth range up to ~2.7 m): a direct, drift-free
measurement of the height, as a downward range finder gives PX4's and ArduPilot's height estimators.

The floor is the *lowest horizontal surface* in view:

* the depth image is sampled on a grid (``stride_px``), back-projected and turned into H (level, origin at
  the body's centre, z down) with the attitude's roll and pitch;
* a sample is on a horizontal surface when the normal of its grid neighbourhood is within
  ``max_normal_tilt_rad`` of vertical and its neighbours lie on the same surface (no depth edge) — walls,
  columns and the edges of boxes are not;
* of those at least ``min_drop_m`` below the body, the deepest layer (``layer_m`` thick) that holds
  ``min_points`` samples is the floor: a box top under the vehicle is a horizontal surface too, but the
  floor around it lies lower. A wall's lowest visible strip is never taken for it (its normal is horizontal),
  so the measurement errs only when no floor is in view, and then it is None.

The height returned is the body centre's above that layer (the median of its samples' depths).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from quadlink.camera import CameraIntrinsics
from quadlink.frames import R_hq


@dataclass(frozen=True)
class FloorConfig:
    """How the floor is found in a depth image (see the module's docstring)."""

    enabled: bool = True
    stride_px: int = 6                           # grid spacing of the samples (320x240: 54x40 samples)
    min_range_m: float = 0.5                     # the sensor's blind range
    max_range_m: float = 3.5                     # beyond it structured-light depth noise grows as z^2
    max_normal_tilt_rad: float = 0.21             # 12 deg
    max_edge_ratio: float = 0.15                 # a neighbour farther than this x range: a depth edge
    min_drop_m: float = 0.05                     # below the body's centre (the floor never is above it)
    layer_m: float = 0.06                        # thickness of one horizontal layer
    min_points: int = 20                         # samples that make a layer a surface, not noise


@dataclass(frozen=True)
class FloorObservation:
    """The floor in one image: the body centre's height above it (m) and the samples that carry it."""

    height_m: float
    points: int


def measure_floor(depth_m: NDArray[np.floating], K: CameraIntrinsics, R_qc: NDArray[np.float64],
                  p_qc_m: NDArray[np.float64], roll_rad: float, pitch_rad: float,
                  config: FloorConfig | None = None) -> FloorObservation | None:
    """The lowest horizontal surface in ``depth_m`` (m along the optical axis; 0/nan/inf = no reading) seen
    by a camera mounted at ``R_qc``, ``p_qc_m`` on a body at ``roll_rad``, ``pitch_rad``; None if none."""
    cfg = config or FloorConfig()
    if not cfg.enabled:
        return None
    s = max(int(cfg.stride_px), 1)
    depth = np.asarray(depth_m, dtype=np.float64)[::s, ::s]
    rows, cols = depth.shape
    if rows < 3 or cols < 3:
        return None
    v = np.arange(0, rows * s, s, dtype=np.float64)[:, None]
    u = np.arange(0, cols * s, s, dtype=np.float64)[None, :]
    valid = np.isfinite(depth) & (depth >= cfg.min_range_m) & (depth <= cfg.max_range_m)
    z_c = np.where(valid, depth, 0.0)
    p_c = np.stack(((u - K.cx) / K.fx * z_c, (v - K.cy) / K.fy * z_c, z_c), axis=-1)
    R_h = R_hq(roll_rad, pitch_rad)
    R_hc = R_h @ np.asarray(R_qc, dtype=float)
    p_h = p_c @ R_hc.T + R_h @ np.asarray(p_qc_m, dtype=float).reshape(3)
    # central differences on the grid: the neighbourhood's tangent vectors, its normal, its depth edges
    du = p_h[1:-1, 2:] - p_h[1:-1, :-2]
    dv = p_h[2:, 1:-1] - p_h[:-2, 1:-1]
    all_valid = valid[1:-1, 1:-1] & valid[1:-1, 2:] & valid[1:-1, :-2] & valid[2:, 1:-1] & valid[:-2, 1:-1]
    normal = np.cross(du, dv)
    norm = np.linalg.norm(normal, axis=-1)
    centre = p_h[1:-1, 1:-1]
    reach = np.maximum(np.linalg.norm(du, axis=-1), np.linalg.norm(dv, axis=-1))
    smooth = reach <= cfg.max_edge_ratio * depth[1:-1, 1:-1] * 2.0 + 1e-9   # two grid steps apart
    with np.errstate(invalid="ignore", divide="ignore"):
        level = np.abs(normal[..., 2]) >= math.cos(cfg.max_normal_tilt_rad) * norm
    keep = all_valid & smooth & level & (norm > 0.0) & (centre[..., 2] >= cfg.min_drop_m)
    drop_m = centre[..., 2][keep]
    if drop_m.size < cfg.min_points:
        return None
    # the deepest layer with enough samples: bins of layer_m, counted over a window of two bins so a layer
    # split by a bin edge still counts whole
    edges = np.arange(cfg.min_drop_m, float(drop_m.max()) + 2.0 * cfg.layer_m, cfg.layer_m / 2.0)
    counts, _ = np.histogram(drop_m, bins=edges)
    window = np.convolve(counts, np.ones(3, dtype=int), mode="same")   # layer_m wide around each half-bin
    dense = np.nonzero(window >= cfg.min_points)[0]
    if dense.size == 0:
        return None
    k = int(dense[-1])
    while k > 0 and window[k - 1] > window[k]:   # from the deep tail of the layer's noise to its peak
        k -= 1
    centre_m = 0.5 * (edges[k] + edges[k + 1])
    layer = drop_m[np.abs(drop_m - centre_m) <= cfg.layer_m]
    if layer.size < cfg.min_points:
        return None
    return FloorObservation(float(np.median(layer)), int(layer.size))

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

**The layer is levelled by the floor itself** (``plane_fit``). H comes from the attitude and the configured
camera mount; an error in either tilts the floor in H, and a layer's median 1-3 m ahead is then off by the
tilt times that distance. Campaign 12's flight 4 (re-flown and logged): the odometry's attitude, which
levels H, jumped 5 deg in roll at lift-off and the camera was mounted 1.8 deg off; the floor read 6-10 cm low
for 10 s of climbing, and the ceiling limit let the vehicle 0.36 m from the ceiling. So once the layer is
found, the floor's own plane is fitted: the mean normal of the layer's neighbourhoods gives its tilt (a
tilted floor shows in H's layer only as a strip), every level sample near that plane joins it, and a least-
squares plane through those (weighted by the depth noise), refitted once on the samples near it, gives the
height as the body centre's distance to the plane (a distance does not care how H is tilted). A plane fitted
to a strip or to a few noisy samples is tilted by the noise (2-20 cm at 2.5 m on the SITL's frames), so the
fit is taken only when its samples are many (``plane_min_points``) and spread (``plane_min_span_m``), and its
tilt in H plausible (``plane_max_tilt_rad``); otherwise the samples are levelled by the mean normal alone.
Re-flown with this, flight 4's floor read within 1 cm of the truth all flight, and the flight came to
0.44 m of the ceiling.
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
    plane_fit: bool = True                       # level the layer by the floor's own plane (module docstring)
    plane_min_points: int = 150                  # samples of the fitted plane
    plane_min_span_m: float = 1.0                # their spread in horizontal distance from the body
    plane_max_tilt_rad: float = 0.14             # 8 deg: attitude error + mount error + a floor's own slope


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
    depth = np.asarray(depth_m)[::s, ::s].astype(np.float64)   # the grid's samples only, then in double
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
    # (per component: np.cross and np.linalg.norm's own arithmetic, in their order, without their generic overhead)
    du = [p_h[1:-1, 2:, i] - p_h[1:-1, :-2, i] for i in range(3)]
    dv = [p_h[2:, 1:-1, i] - p_h[:-2, 1:-1, i] for i in range(3)]
    all_valid = valid[1:-1, 1:-1] & valid[1:-1, 2:] & valid[1:-1, :-2] & valid[2:, 1:-1] & valid[:-2, 1:-1]
    normal = [du[1] * dv[2] - du[2] * dv[1], du[2] * dv[0] - du[0] * dv[2], du[0] * dv[1] - du[1] * dv[0]]
    norm = _length(normal)
    centre = p_h[1:-1, 1:-1]
    reach = np.maximum(_length(du), _length(dv))
    smooth = reach <= cfg.max_edge_ratio * depth[1:-1, 1:-1] * 2.0 + 1e-9   # two grid steps apart
    with np.errstate(invalid="ignore", divide="ignore"):
        level = np.abs(normal[2]) >= math.cos(cfg.max_normal_tilt_rad) * norm
    keep = all_valid & smooth & level & (norm > 0.0) & (centre[..., 2] >= cfg.min_drop_m)
    floor_h = centre[keep]
    drop_m = floor_h[:, 2]
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
    in_layer = np.abs(drop_m - centre_m) <= cfg.layer_m
    if int(np.count_nonzero(in_layer)) < cfg.min_points:
        return None
    if cfg.plane_fit:
        plane = _fit_floor_plane(floor_h, np.stack([c[keep] for c in normal], axis=-1) / norm[keep][:, None],
                                 in_layer, cfg)
        if plane is not None:
            return plane
    return FloorObservation(float(np.median(drop_m[in_layer])), int(np.count_nonzero(in_layer)))


def _median(x: NDArray[np.float64]) -> float:
    """``np.median`` of a non-empty 1-D array, to the bit (the middle value, or the mean of the two), without its
    generic machinery (a third of this module's time); NaN if any value is."""
    if np.isnan(x).any():
        return math.nan
    k = x.size // 2
    if x.size % 2:
        return float(np.partition(x, k)[k])
    part = np.partition(x, (k - 1, k))
    return float((part[k - 1] + part[k]) / 2.0)


def _length(v: list[NDArray[np.float64]]) -> NDArray[np.float64]:
    """The Euclidean length of the vectors whose three components are ``v``."""
    return np.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])


def _plane_normal(points: NDArray[np.float64]) -> NDArray[np.float64]:
    """The unit normal (z >= 0) of the plane z = a x + b y + c through ``points`` (N x 3), fitted by least
    squares weighted by each sample's depth noise (structured light: sigma ~ range^2, so weight ~ range^-4)."""
    range2 = np.maximum(np.einsum("ij,ij->i", points, points), 1e-6)
    w = 1.0 / (range2 * range2)
    A = np.stack((points[:, 0], points[:, 1], np.ones(len(points))), axis=1)
    AtW = A.T * w
    a, b, _ = np.linalg.solve(AtW @ A + 1e-12 * np.eye(3), AtW @ points[:, 2])
    n = np.array([-a, -b, 1.0])
    return n / float(np.linalg.norm(n))


def _fit_floor_plane(floor_h: NDArray[np.float64], normals_h: NDArray[np.float64], in_layer: NDArray[np.bool_],
                     cfg: FloorConfig) -> FloorObservation | None:
    """The floor's own plane through the layer (see the module's docstring): the body centre's distance to
    it; when the fit is not well conditioned, the median distance to the plane of the layer's mean normal;
    None when not even that has ``min_points`` samples (the layer's median in H then stands)."""
    n = normals_h[in_layer].mean(axis=0)
    n = n * (1.0 if n[2] >= 0.0 else -1.0)
    length = float(np.linalg.norm(n))
    if not length > 0.0:
        return None
    n = n / length
    d_m = floor_h @ n   # every sample's distance along n (each row's own dot product: a subset's are the same)
    offset = _median(d_m[in_layer])
    near = np.abs(d_m - offset) <= cfg.layer_m   # the whole floor, however H tilts it
    count = int(np.count_nonzero(near))
    if count < cfg.min_points:
        return None
    # levelled by the mean normal alone (each neighbourhood's normal is noisy, and the level test truncates its
    # spread, so this takes out most of a tilt, not all): the fallback when no plane can be fitted
    levelled = FloorObservation(_median(d_m[near]), count)
    for band_m in (cfg.layer_m, cfg.layer_m / 2.0):
        if count < max(cfg.plane_min_points, 3):
            return levelled
        n = _plane_normal(floor_h[near])
        d_m = floor_h @ n
        offset = _median(d_m[near])
        near = np.abs(d_m - offset) <= band_m
        count = int(np.count_nonzero(near))
    if count < max(cfg.plane_min_points, 3) or math.acos(min(1.0, float(n[2]))) > cfg.plane_max_tilt_rad:
        return levelled
    reach_m = np.hypot(floor_h[near, 0], floor_h[near, 1])
    if float(np.ptp(reach_m)) < cfg.plane_min_span_m:
        return levelled
    return FloorObservation(_median(d_m[near]), count)

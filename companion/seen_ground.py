"""Which ground the camera has looked at: a landing needs to have seen where it comes down (pure; issue 29).

The camera looks ahead and 30 deg down: at 1.4 m up it sees the floor from ~1.1 m ahead of the vehicle, never under
it. What is under the vehicle at a landing was seen on the way there only if the vehicle came that way, camera
first. A scripted flight that drove sideways, the camera turned 30-90 deg away from its motion, came to rest over a
0.53 m box the camera had never seen; its LAND was accepted (nothing was known below) and came down on the box's
corner, 0.10 m (campaign seed 5353, flight 18). :class:`BelowMemory` keeps the tops of the objects it saw; this
keeps where it looked.

:class:`SeenGround` marks the cells of a world grid (the odometry's frame, like :class:`BelowMemory`) where a depth
pixel landed below the vehicle's level — the floor, or the top or side of something standing on it — and the spot
where the vehicle stood on the ground before its take-off. :meth:`SeenGround.unseen_fraction` is the share of a
landing footprint never seen; :meth:`SeenGround.unseen_points_h` gives the unseen cells around the vehicle as points
in H for choosing a way off to seen ground. What the camera saw is only as good as the odometry that placed it
(centimetres of drift over a flight).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from quadlink.camera_frame import CameraIntrinsics
from quadlink.frames import R_hq

_KEY_OFFSET = 1 << 20   # cell indices (up to +-100 km at 0.1 m) packed into one int64 key


@dataclass(frozen=True)
class SeenGroundParams:
    """``enabled``: refuse landings over ground the camera has not seen; ``grid_m``: the world grid's cell;
    ``stride_px``: every this many depth pixels in each direction are placed (80 x 60 of a QVGA image at 4);
    ``max_unseen_fraction``: a landing footprint with more of its cells unseen is no place to land (the footprint's
    rim lies on cell edges: a few cells can be missed by the sampling); ``takeoff_radius_m``: the ground around the
    vehicle while it stands before a take-off counts as seen (it stood there)."""

    enabled: bool = True
    grid_m: float = 0.1
    stride_px: int = 4
    max_unseen_fraction: float = 0.1
    takeoff_radius_m: float = 0.6

    def __post_init__(self) -> None:
        if not 0.02 <= self.grid_m <= 1.0:
            raise ValueError(f"grid_m must be in [0.02, 1] m, got {self.grid_m}")
        if not 1 <= self.stride_px <= 64:
            raise ValueError(f"stride_px must be in [1, 64], got {self.stride_px}")
        if not 0.0 <= self.max_unseen_fraction < 1.0:
            raise ValueError(f"max_unseen_fraction must be in [0, 1), got {self.max_unseen_fraction}")
        if not self.takeoff_radius_m >= 0.0:
            raise ValueError(f"takeoff_radius_m must be >= 0, got {self.takeoff_radius_m}")


def _keys(ix: NDArray[np.int64], iy: NDArray[np.int64]) -> NDArray[np.int64]:
    return (ix + _KEY_OFFSET) * (2 * _KEY_OFFSET) + (iy + _KEY_OFFSET)


def _position_xy(position_w_m: ArrayLike | None) -> NDArray[np.float64] | None:
    if position_w_m is None:
        return None
    p = np.asarray(position_w_m, dtype=float).ravel()
    return p[:2] if p.size >= 2 and np.all(np.isfinite(p[:2])) else None


class SeenGround:
    """The ground cells the camera has seen (world grid in the odometry's frame), until the vehicle lands."""

    def __init__(self, params: SeenGroundParams | None = None) -> None:
        self.params = params or SeenGroundParams()
        self._cells: set[int] = set()
        self._disc_cache: dict[float, NDArray[np.float64]] = {}

    def __len__(self) -> int:
        return len(self._cells)

    def clear(self) -> None:
        self._cells.clear()

    def _disc(self, radius_m: float) -> NDArray[np.float64]:
        """Offsets (K x 2, m) of the cell centres of a grid laid on a disc of ``radius_m`` about the origin."""
        key = round(radius_m, 3)
        if key not in self._disc_cache:
            g = self.params.grid_m
            n = int(math.ceil(radius_m / g))
            o = (np.arange(-n, n) + 0.5) * g     # a cell's centre when the disc's centre is on a grid corner
            xx, yy = np.meshgrid(o, o, indexing="ij")
            inside = xx**2 + yy**2 <= radius_m**2
            self._disc_cache[key] = np.column_stack([xx[inside], yy[inside]])
        return self._disc_cache[key]

    def _cell_keys(self, xy_w_m: NDArray[np.float64]) -> NDArray[np.int64]:
        ij = np.floor(xy_w_m / self.params.grid_m).astype(np.int64)
        return _keys(ij[:, 0], ij[:, 1])

    def mark_disc(self, position_w_m: ArrayLike | None, radius_m: float) -> None:
        """The ground within ``radius_m`` of ``position_w_m`` (world, NED) counts as seen (the vehicle stood on it)."""
        xy = _position_xy(position_w_m)
        if xy is None or radius_m <= 0.0:
            return
        self._cells.update(self._cell_keys(xy + self._disc(radius_m)).tolist())

    def observe(self, depth_m: NDArray[np.float32] | None, K: CameraIntrinsics, R_qc: ArrayLike, p_qc_m: ArrayLike,
                roll_rad: float, pitch_rad: float, yaw_rad: float, position_w_m: ArrayLike | None) -> None:
        """One depth image (metres, 0 = invalid), the camera's mount (``R_qc`` camera -> body, ``p_qc_m``), the
        vehicle's attitude and its position in the odometry's world (NED): mark the cells where a depth pixel
        landed below the vehicle's level."""
        xy = _position_xy(position_w_m)
        if depth_m is None or xy is None or not all(math.isfinite(a) for a in (roll_rad, pitch_rad, yaw_rad)):
            return
        s = self.params.stride_px
        d = np.asarray(depth_m)[::s, ::s].astype(np.float64)
        v, u = np.mgrid[0:d.shape[0], 0:d.shape[1]]
        ok = np.isfinite(d) & (d > 0.0)
        if not ok.any():
            return
        z = d[ok]
        u_px, v_px = u[ok] * s, v[ok] * s
        p_c = np.column_stack([(u_px - K.cx) / K.fx * z, (v_px - K.cy) / K.fy * z, z])
        p_q = p_c @ np.asarray(R_qc, dtype=float).T + np.asarray(p_qc_m, dtype=float).reshape(3)
        p_h = p_q @ R_hq(roll_rad, pitch_rad).T
        below = p_h[p_h[:, 2] > 0.0]          # z down: under the vehicle's level (the floor, what stands on it)
        if not below.shape[0]:
            return
        c, sn = math.cos(yaw_rad), math.sin(yaw_rad)
        w = np.column_stack([xy[0] + c * below[:, 0] - sn * below[:, 1], xy[1] + sn * below[:, 0] + c * below[:, 1]])
        self._cells.update(np.unique(self._cell_keys(w)).tolist())

    def _seen_mask(self, xy_w_m: NDArray[np.float64]) -> NDArray[np.bool_]:
        if not self._cells:
            return np.zeros(xy_w_m.shape[0], dtype=bool)
        keys = self._cell_keys(xy_w_m)
        return np.fromiter((k in self._cells for k in keys.tolist()), dtype=bool, count=keys.size)

    def unseen_fraction(self, position_w_m: ArrayLike | None, radius_m: float) -> float | None:
        """The share of the cells within ``radius_m`` of ``position_w_m`` never seen; None without a position."""
        xy = _position_xy(position_w_m)
        if xy is None:
            return None
        return float(1.0 - self._seen_mask(xy + self._disc(radius_m)).mean())

    def unseen_points_h(self, position_w_m: ArrayLike | None, yaw_rad: float, within_m: float,
                        depth_below_m: float) -> NDArray[np.float64]:
        """The unseen cells within ``within_m`` of the vehicle as points in H (N x 3, ``depth_below_m`` under the
        vehicle): for choosing a way off toward seen ground as off an object's top."""
        xy = _position_xy(position_w_m)
        if xy is None or not math.isfinite(yaw_rad):
            return np.zeros((0, 3))
        offsets = self._disc(within_m)
        unseen = offsets[~self._seen_mask(xy + offsets)]
        c, s = math.cos(yaw_rad), math.sin(yaw_rad)
        return np.column_stack([c * unseen[:, 0] + s * unseen[:, 1], -s * unseen[:, 0] + c * unseen[:, 1],
                                np.full(unseen.shape[0], depth_below_m)])

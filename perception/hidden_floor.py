"""Objects the depth camera cannot see, found by the floor they hide (pure; issue 29).

A structured-light camera gets no return from a dark surface (it absorbs the pattern) or a specular one (it
mirrors the pattern away): such an object leaves a hole in the depth image, and the sector rule of
:mod:`perception.obstacles` (the nearest *valid* pixel) reports what lies beside or behind it — the floor in
front of it, the wall behind it — so the map calls its azimuth free (campaign seed 2031: a script flew into a
dark column to 0.25 m, a landing came down 0.10 m from a specular box). A hole alone says nothing: the driver
also reports 0 beyond its range, so a far wall looks the same.

**The floor tells them apart.** Where the floor is known (its depth ``floor_drop_m`` below the body, H z down,
from :mod:`perception.floor`), every pixel whose ray meets the floor inside the sensor's valid range, at an
incidence the sensor returns, *should* return the floor, or something nearer. A pixel that returns nothing
there is hiding the floor behind an object that gives no return, and that object stands between the camera and
the floor point. An object standing on the floor at horizontal distance ``D`` hides the floor beyond ``D`` along
its azimuth and leaves the floor in front of it visible; so per azimuth bin, the nearest hidden floor point is
where the object's foot is (or nearer). It is reported when the hidden pixels are many and dense beyond it
(``min_pixels``, ``min_fraction`` of the expected floor pixels within ``depth_window_m`` past it) and the floor
just in front of it returned (``min_floor_before_pixels`` within ``floor_before_m``): isolated dropouts, the thin
IR-shadow slivers beside a visible edge, and the shadow strip a box's top edge casts on the floor behind it (the
box, not floor, lies in front of that strip) are not an object. Nor is the projector's shadow beside any nearer
edge along the image rows (``ir_baseline_m``: a hole within ``f b (1/z_near - 1/z_floor)`` pixels of a nearer
valid pixel in its row): the landing tests' box cast one 9 px wide on the floor beside its corner.

The points are placed at the foot's horizontal distance (less ``margin_m``), on the bin's azimuth, at the
vehicle's level (no higher than ``foot_clearance_m`` above the floor), and repeated below it down to that
height: the object stands on the floor, so a vehicle that later flies lower still meets it. The obstacle map
carries them as it carries what the camera sees, so the safety layer keeps its distance from an object it never
saw. What this
cannot find: a non-returning object that does not stand on floor in view (a dark box on a desk, a black wall
whose foot is nearer than the camera's lowest ray), a dark or shiny floor (it reads as an object's foot), and
glass (it returns the floor behind it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from quadlink.camera import CameraIntrinsics
from quadlink.frames import R_hq


@dataclass(frozen=True)
class HiddenFloorConfig:
    """How hidden floor is read as an unseen object (see the module's docstring)."""

    enabled: bool = True               # on: its objects enter the map open-topped (perception.obstacles), so a wall
                                       # the vehicle rests 0.5 m from is beside it, not below it (it was off while it
                                       # refused MAVSDK's LAND there: CI on 91f21c5)
    stride_px: int = 4                 # grid spacing of the sampled pixels (80 x 60 of QVGA)
    range_margin_m: float = 0.1        # the floor must be this far inside the valid range to be expected
    max_incidence_deg: float = 72.0    # the floor is expected only where the sensor returns it (the SITL's
                                       # grazing limit is 78 deg; real sensors fade earlier)
    floor_tolerance_m: float = 0.05    # a return within this (+ the depth noise) of the expected floor is floor
    azimuth_bins: int = 144            # 2.5 deg: a 0.3 m column at 3 m spans two
    min_pixels: int = 12               # hidden pixels in a bin, at least
    min_fraction: float = 0.6          # ... and this share of the expected floor just past the foot
    depth_window_m: float = 0.5        # "just past": the foot's horizontal distance + this
    floor_before_m: float = 0.3        # the floor within this in front of the foot ...
    min_floor_before_pixels: int = 3   # ... returned in at least this many pixels (not a shadow behind a box)
    margin_m: float = 0.05             # the point is put this much nearer than the nearest hidden floor, and
    margin_per_m: float = 0.03         # this much per metre more (the sampled floor's spacing at a grazing view:
                                       # ~8 cm between samples 3 m ahead, 1 cm at 1 m)
    foot_clearance_m: float = 0.3      # the point's height above the floor at most (within the map's band)
    level_step_m: float = 0.3          # the object stands on the floor: its points are repeated at most this far
                                       # apart from its top point down to ``foot_clearance_m`` above the floor, so a
                                       # vehicle that descends under the level it was found at still meets it
                                       # within the map's height band (+-0.45 m; campaign 22, flight 35: a dark box
                                       # found from 1 m up during the take-off, flown into from 0.3 m up, 0.18 m)
    over_margin_m: float = 0.1         # a ray returned this far past the foot passed over the object, whose top
                                       # is put this far under the lowest such ray
    min_top_m: float = 0.2             # an object found lower than this above the floor is none (the gear's height)
    ir_baseline_m: float = 0.075       # the projector's offset along the depth image's x (Kinect, Xtion: 7.5 cm):
                                       # a hole beside a nearer edge along the image rows is its shadow

    def __post_init__(self) -> None:
        if self.stride_px < 1:
            raise ValueError(f"stride_px must be >= 1, got {self.stride_px}")
        if not 0.0 < self.max_incidence_deg < 90.0:
            raise ValueError(f"max_incidence_deg must be in (0, 90), got {self.max_incidence_deg}")
        if not self.level_step_m > 0.0:
            raise ValueError(f"level_step_m must be > 0, got {self.level_step_m}")
        if self.azimuth_bins < 8 or self.min_pixels < 1 or not 0.0 < self.min_fraction <= 1.0:
            raise ValueError("azimuth_bins >= 8, min_pixels >= 1 and min_fraction in (0, 1] are required")


EDGE_RATIO = 0.9   # a shadow's occluder is at most this fraction of the shadowed floor's depth
SHADOW_SLACK = 1.5  # the shadow measured wider than f b (1/z_near - 1/z_far): the edge pixel's own depth is not the
                    # occluding edge's, and the disparity's noise frays it (the landing tests' box: 9 px for 7.3)


def _in_ir_shadow(depth_m: NDArray[np.floating], flat_idx: NDArray[np.intp], hidden: NDArray[np.bool_],
                  floor_depth_m: NDArray[np.float64], fx_baseline_px_m: float, min_range_m: float,
                  max_range_m: float) -> NDArray[np.bool_]:
    """Which hidden pixels are the projector's shadow: a structured-light camera's projector sits beside its IR
    camera along the image's x, so a surface at depth z_far right beside an edge at z_near (along the row) gets
    no pattern over ``f b (1/z_near - 1/z_far)`` pixels (Khoshelham & Oude Elberink 2012; sim_sitl/xtion.py). A
    hidden pixel whose row has a valid, nearer pixel that close on either side (the projector's side is the
    device's, not assumed) is shadow, not an object."""
    out = np.zeros(hidden.shape, dtype=bool)
    cand = hidden.nonzero()[0]
    if not cand.size or fx_baseline_px_m <= 0.0:
        return out
    h, w = depth_m.shape[:2]
    t = floor_depth_m[cand]
    reach = int(math.ceil(fx_baseline_px_m * (1.0 / min_range_m - 1.0 / max_range_m))) + 1
    v, u = np.divmod(flat_idx[cand], w)
    k = np.arange(1, reach + 1)
    explained = np.zeros(cand.size, dtype=bool)
    flat = np.asarray(depth_m, dtype=float).reshape(-1)
    for sign in (-1, 1):
        uu = u[:, None] + sign * k[None, :]
        inside = (uu >= 0) & (uu < w)
        z = flat[v[:, None] * w + np.clip(uu, 0, w - 1)]
        # an edge: the occluder is clearly nearer than the floor behind it (the floor running on toward the hidden
        # pixel is continuous, a few per cent nearer per pixel, and casts no shadow)
        ok = inside & np.isfinite(z) & (z >= min_range_m) & (z <= max_range_m) & (z < EDGE_RATIO * t[:, None])
        with np.errstate(divide="ignore"):
            width = fx_baseline_px_m * (1.0 / np.where(ok, z, np.inf) - 1.0 / t[:, None])
        explained |= (ok & (k[None, :] <= SHADOW_SLACK * width + 1.0)).any(axis=1)
    out[cand] = explained
    return out


@lru_cache(maxsize=8)
def _pixel_rays(K: CameraIntrinsics, height: int, width: int, stride: int
                ) -> tuple[NDArray[np.intp], NDArray[np.float64]]:
    """Flat indices of the sampled pixels and their rays (x/z, y/z, 1) in the camera frame (3 x N)."""
    v, u = np.mgrid[stride // 2: height: stride, stride // 2: width: stride]
    u, v = u.ravel(), v.ravel()
    rays = np.vstack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones(u.size)])
    return v * width + u, rays


def _levels(z_top_m: float, z_low_m: float, step_m: float) -> NDArray[np.float64]:
    """Heights (H z down) from ``z_top_m`` down to ``z_low_m``, at most ``step_m`` apart, both ends included
    (``z_top_m`` alone when it is already that low)."""
    if z_low_m <= z_top_m:
        return np.array([z_top_m])
    return np.linspace(z_top_m, z_low_m, int(math.ceil((z_low_m - z_top_m) / step_m - 1e-9)) + 1)


def hidden_floor_points_h(depth_m: NDArray[np.floating], K: CameraIntrinsics, R_qc: NDArray[np.float64],
                          p_qc_m: NDArray[np.float64], roll_rad: float, pitch_rad: float,
                          floor_drop_m: float | None, min_range_m: float = 0.5, max_range_m: float = 3.5,
                          config: HiddenFloorConfig | None = None) -> NDArray[np.float64]:
    """Points (K x 3, H: level, origin at the body, z down) standing for objects that hide the floor; none when
    the floor's depth below the body is unknown or the check is off. ``min_range_m``, ``max_range_m``: the depth
    (optical axis) the sensor reports, as :class:`perception.obstacles.ObstacleConfig` has it."""
    cfg = config or HiddenFloorConfig()
    empty = np.zeros((0, 3))
    if not cfg.enabled or floor_drop_m is None or not math.isfinite(floor_drop_m) or floor_drop_m <= 0.0:
        return empty
    h, w = depth_m.shape[:2]
    idx, rays_c = _pixel_rays(K, h, w, cfg.stride_px)
    R_hc = R_hq(roll_rad, pitch_rad) @ R_qc
    p_hc = R_hq(roll_rad, pitch_rad) @ p_qc_m
    r = R_hc @ rays_c                                 # rays in H with unit camera depth
    drop = floor_drop_m - float(p_hc[2])              # the floor's depth below the camera
    if drop <= 0.0:
        return empty
    down = r[2] > 1e-6
    t = np.where(down, drop / np.where(down, r[2], 1.0), np.inf)   # camera depth of the floor on each ray
    norm = np.sqrt(np.einsum("ij,ij->j", r, r))
    sin_depression = np.where(down, r[2] / norm, 0.0)
    expected = down & (t >= min_range_m + cfg.range_margin_m) & (t <= max_range_m - cfg.range_margin_m) \
        & (sin_depression >= math.cos(math.radians(cfg.max_incidence_deg)))
    if not expected.any():
        return empty
    sel = expected.nonzero()[0]
    z = np.asarray(depth_m, dtype=float).ravel()[idx[sel]]
    t_sel = t[sel]
    valid = np.isfinite(z) & (z >= min_range_m) & (z <= max_range_m)
    tol = cfg.floor_tolerance_m + 0.01 * t_sel * t_sel   # structured light: the error grows with z^2
    hidden = ~valid
    shadow = _in_ir_shadow(np.asarray(depth_m), idx[sel], hidden, t_sel, K.fx * cfg.ir_baseline_m,
                           min_range_m, max_range_m)
    hidden &= ~shadow
    # a return nearer than the floor is a seen object (the map has it); farther, a hole in the floor: neither
    # is hidden floor. Only pixels that returned the floor or nothing take part.
    counted = hidden | (valid & (np.abs(z - t_sel) <= tol))     # (a shadowed pixel is neither)
    if hidden.sum() < cfg.min_pixels:
        return empty
    rx, ry = r[0, sel] * t_sel, r[1, sel] * t_sel
    horiz = np.hypot(rx + p_hc[0], ry + p_hc[1])           # horizontal distance of the floor point from the body
    az = np.arctan2(ry + p_hc[1], rx + p_hc[0])
    n = cfg.azimuth_bins
    b = (np.floor((az + math.pi) / (2.0 * math.pi) * n).astype(np.intp)) % n
    # every sampled pixel that returned something, for the object's height: a ray that passed over the foot and
    # returned beyond it bounds the object's top (a matte box's side seen edge-on returns nothing either, but the
    # rays over the box reach the floor behind it; over a dark column or partition nothing comes back)
    z_all = np.asarray(depth_m, dtype=float).ravel()[idx]
    ret = np.isfinite(z_all) & (z_all >= min_range_m) & (z_all <= max_range_m)
    r_ret = r[:, ret]
    end_x, end_y = r_ret[0] * z_all[ret] + p_hc[0], r_ret[1] * z_all[ret] + p_hc[1]
    horiz_ret = np.hypot(end_x, end_y)
    b_ret = (np.floor((np.arctan2(end_y, end_x) + math.pi) / (2.0 * math.pi) * n).astype(np.intp)) % n
    r_xy_ret = np.hypot(r_ret[0], r_ret[1])
    half_bin = math.pi / n
    out = []
    for k in np.unique(b[hidden]):
        in_bin = (b == k) & counted
        order = np.argsort(horiz[in_bin], kind="stable")
        d_all = horiz[in_bin][order]
        is_hidden = hidden[in_bin][order]
        if np.count_nonzero(is_hidden) < cfg.min_pixels:
            continue
        # the foot: the nearest hidden floor with dense hidden floor just past it (a lone dropout nearer does
        # not set it); counts over [foot, foot + window] from the sorted distances
        cum_hidden = np.concatenate(([0], np.cumsum(is_hidden)))
        feet = d_all[is_hidden]
        lo = np.searchsorted(d_all, feet, side="left")
        hi = np.searchsorted(d_all, feet + cfg.depth_window_m, side="right")
        n_hidden = cum_hidden[hi] - cum_hidden[lo]
        # the floor just in front of the foot must have returned: an object standing on the floor hides the floor
        # beyond its foot and leaves the floor before it in view. The structured light's shadow behind a box's top
        # edge (the projector sits above the IR camera in this portrait mount) is a strip of floor with no return
        # too, but in front of it lies the box, not floor (the landing tests' boxes read as walls without this)
        cum_floor = np.concatenate(([0], np.cumsum(~is_hidden)))
        before = np.searchsorted(d_all, feet - cfg.floor_before_m, side="left")
        n_floor_before = cum_floor[lo] - cum_floor[before]
        ok = (n_hidden >= cfg.min_pixels) & (n_hidden >= cfg.min_fraction * (hi - lo)) \
            & (n_floor_before >= cfg.min_floor_before_pixels)
        if ok.any():
            foot = float(feet[int(np.argmax(ok))])
            a = -math.pi + (k + 0.5) * 2.0 * math.pi / n
            d = max(foot - cfg.margin_m - cfg.margin_per_m * foot, 0.0)
            z_point = min(0.0, floor_drop_m - cfg.foot_clearance_m)       # unknown height: the vehicle's level
            over = (b_ret == k) & (horiz_ret > foot + cfg.over_margin_m) & (r_xy_ret > 1e-6)
            if over.any():
                # the rays' depth below the camera where they pass the foot (H z down): the object is lower
                z_pass = float(p_hc[2]) + r_ret[2, over] * (foot / r_xy_ret[over])
                z_point = max(z_point, float(np.min(z_pass)) + cfg.over_margin_m)
            if z_point < floor_drop_m - cfg.min_top_m:
                # across the whole bin, not only its centre: the foot is the nearest hidden floor anywhere in the
                # bin, so the object stands at ``d`` or farther over all of it. A point at the centre alone left an
                # object's end unmapped by up to 4.2 deg (median 1.4; now 2.6 and -0.9: the ray-cast columns of
                # tests/unit/test_hidden_floor.py): 15 cm at 2 m, where the dark partition's end was rounded at 0.36 m
                for z_k in _levels(z_point, floor_drop_m - cfg.foot_clearance_m, cfg.level_step_m):
                    for a_k in (a - half_bin, a, a + half_bin):
                        out.append((d * math.cos(a_k), d * math.sin(a_k), z_k))
    return np.array(out, dtype=float).reshape(-1, 3) if out else empty


class HiddenFloorConfirm:
    """A hidden object is reported once two consecutive frames found it (within ``match_m`` of each other in H):
    a dark object is found frame after frame, the odd shadow or dropout pattern that passes the tests above is not
    (the landing tests' box: one frame in a few hundred put a point on its side at the vehicle's level, and the
    map kept it). Between two frames at 30 Hz the vehicle moves a few centimetres and turns about 1 degree."""

    def __init__(self, match_m: float = 0.25) -> None:
        self.match_m = float(match_m)
        self._previous = np.zeros((0, 3))

    def update(self, points_h_m: NDArray[np.float64]) -> NDArray[np.float64]:
        """This frame's points (K x 3, H); returns those a point of the previous frame confirms."""
        pts = np.asarray(points_h_m, dtype=float).reshape(-1, 3)
        prev, self._previous = self._previous, pts
        if not pts.shape[0] or not prev.shape[0]:
            return np.zeros((0, 3))
        d = np.hypot(pts[:, None, 0] - prev[None, :, 0], pts[:, None, 1] - prev[None, :, 1])
        return pts[(d <= self.match_m).any(axis=1)]

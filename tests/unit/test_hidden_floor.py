"""perception.hidden_floor: an object that gives no return, found by the floor it hides (ray-cast scenes).

The scenes are a floor and vertical cylinders (columns) intersected exactly, seen by the vehicle's camera mount
(45 deg right, 30 deg down, portrait) at the SITL's QVGA intrinsics, with structured-light noise; a dark column
returns nothing, as the Xtion model's dark and specular materials do (sim_sitl/xtion.py), and the driver reports
nothing beyond 3.5 m.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.typing import NDArray

from perception.hidden_floor import HiddenFloorConfig, hidden_floor_points_h
from quadlink.camera import CameraIntrinsics
from quadlink.frames import R_hq

pytestmark = pytest.mark.unit

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


ON = HiddenFloorConfig(enabled=True)


def hidden(depth: NDArray[np.float32], height_m: float, cfg: HiddenFloorConfig = ON) -> NDArray[np.float64]:
    return hidden_floor_points_h(depth, K, R_QC, P_QC_M, 0.0, 0.0, height_m, config=cfg)


@pytest.mark.parametrize(("height_m", "distance_m"),
                         [(0.6, 1.0), (0.6, 1.4), (1.0, 1.2), (1.0, 1.8), (1.0, 2.4), (1.5, 1.2), (1.5, 1.8),
                          (1.5, 2.4)])
def test_a_dark_column_is_found_at_its_foot(height_m: float, distance_m: float, rng: np.random.Generator) -> None:
    """Where the floor behind its foot is in the sensor's range and returned at its incidence (72 deg: at 0.6 m
    up, 1.7 m ahead; at 1 m, 2.9 m)."""
    col = column_at(distance_m)
    pts = hidden(render(height_m, [col], rng), height_m)
    assert pts.shape[0] >= 1, "a dark column standing on the floor in view was not found"
    near = float(np.min(np.hypot(pts[:, 0], pts[:, 1])))
    foot_m = distance_m - col[2]
    # never beyond the column's near face; not more than 0.25 m short of it (the bins' width, the margin)
    assert foot_m - 0.25 <= near <= foot_m + 0.02, (near, foot_m)
    az = np.arctan2(pts[:, 1], pts[:, 0])
    col_az = math.atan2(col[1], col[0])
    assert np.all(np.abs((az - col_az + math.pi) % (2 * math.pi) - math.pi) < math.radians(10.0))
    # nothing passed over a full-height column: its middle bins stand at the vehicle's level (the edge bins, where
    # rays passed beside it, lower); all above the map's floor margin (0.15 m)
    assert np.any(pts[:, 2] <= 0.0) and np.all(pts[:, 2] <= height_m - 0.15 - 1e-9)


@pytest.mark.parametrize("height_m", [0.3, 0.6, 1.0, 1.5])
def test_open_floor_with_dropouts_and_nothing_in_range_beyond_is_not_an_object(height_m: float,
                                                                              rng: np.random.Generator) -> None:
    """The floor out of range reads 0 like a dark object (a big room): no points; 3 % random dropouts neither."""
    assert hidden(render(height_m, [], rng, dropout=0.03), height_m).shape == (0, 3)


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


@pytest.mark.parametrize("height_m", [1.0, 1.5])
def test_the_shadow_a_box_top_casts_on_the_floor_behind_it_is_not_an_object(height_m: float,
                                                                           rng: np.random.Generator) -> None:
    """The landing tests' case: a 0.5 m box 1.2 m ahead, its top edge's IR shadow a 0.3 m strip of floor with no
    return behind it (the projector above the IR camera in the portrait mount). In front of that strip lies the
    box, not floor: no object there but the box the camera sees."""
    depth = render_box_with_shadow(height_m, 1.2, 0.6, 0.3, 0.5, 0.3, rng)
    assert np.count_nonzero(depth == 0.0) > 500                  # the shadow is there
    assert hidden(depth, height_m).shape == (0, 3)


def with_ir_shadows(depth: NDArray[np.float32], fx_baseline_px_m: float = 290 * 0.075) -> NDArray[np.float32]:
    """The projector's shadows (projector along +x of the image, as the SITL's Xtion): along each row, the pixels
    just past a near-to-far depth edge get no pattern over f b (1/z_near - 1/z_far) pixels."""
    out = depth.copy()
    h, w = depth.shape
    for v in range(h):
        row = depth[v]
        for u in range(w - 1):
            zn, zf = float(row[u]), float(row[u + 1])
            if zn > 0.0 and zf > 0.0 and zn < 0.9 * zf:
                width = int(fx_baseline_px_m * (1.0 / zn - 1.0 / zf))
                out[v, u + 1: u + 1 + width] = 0.0
    return out


@pytest.mark.parametrize("distance_m", [1.0, 1.6])
def test_the_projectors_shadow_beside_a_matte_column_is_not_an_object(distance_m: float,
                                                                     rng: np.random.Generator) -> None:
    """The shadow beside a seen column's edge is floor with no return, right beside a nearer edge in its row: the
    landing tests' box cast one 9 px wide beside its corner, and read as an object there, blocked the flight over
    it. Here a matte column with its shadows; the shadow must be there, and not read as an object."""
    depth = render(1.0, [column_at(distance_m, dark=False)], rng)
    shadowed = with_ir_shadows(depth)
    assert np.count_nonzero((shadowed == 0.0) & (depth > 0.0)) > 20
    assert hidden(shadowed, 1.0).shape == (0, 3)


def test_a_matte_column_is_seen_not_hidden(rng: np.random.Generator) -> None:
    assert hidden(render(1.0, [column_at(1.6, dark=False)], rng), 1.0).shape == (0, 3)


def test_a_thin_sliver_of_no_return_is_not_an_object(rng: np.random.Generator) -> None:
    """An IR shadow beside an edge is a few pixels wide: a 1 cm dark rod at 1.5 m hides too little floor."""
    assert hidden(render(1.0, [column_at(1.5, radius_m=0.005)], rng), 1.0).shape == (0, 3)


def test_unknown_floor_or_off_gives_nothing(rng: np.random.Generator) -> None:
    depth = render(1.0, [column_at(1.5)], rng)
    assert hidden_floor_points_h(depth, K, R_QC, P_QC_M, 0.0, 0.0, None, config=ON).shape == (0, 3)
    assert hidden_floor_points_h(depth, K, R_QC, P_QC_M, 0.0, 0.0, math.nan, config=ON).shape == (0, 3)
    assert hidden_floor_points_h(depth, K, R_QC, P_QC_M, 0.0, 0.0, 1.0).shape == (0, 3)   # off by default
    assert hidden(depth, 1.0, HiddenFloorConfig(enabled=False)).shape == (0, 3)
    # a camera that returns nothing at all shows no floor in front of any foot: not an object (its floor is not
    # seen either, so the pipeline has no floor to expect)
    assert hidden(np.zeros_like(depth), 1.0).shape == (0, 3)


def test_the_body_tilt_is_taken_from_the_attitude(rng: np.random.Generator) -> None:
    """Rendered with the body pitched 5 deg and rolled 3 deg, found with that attitude: the foot as when level."""
    height_m, col = 1.0, column_at(1.8)
    roll, pitch = math.radians(3.0), math.radians(5.0)
    R_h = R_hq(roll, pitch)
    depth = render(height_m, [col], rng, R_hc=R_h @ R_QC, p_hc_m=R_h @ P_QC_M)
    pts = hidden_floor_points_h(depth, K, R_QC, P_QC_M, roll, pitch, height_m, config=ON)
    assert pts.shape[0] >= 1
    assert 1.8 - 0.15 - 0.25 <= float(np.min(np.hypot(pts[:, 0], pts[:, 1]))) <= 1.8 - 0.15 + 0.02
    # and read with the wrong attitude (level), the floor it expects is not where the rays meet it: still found
    # (the hidden pixels are hidden whatever the tilt), within the bins' width
    assert hidden(depth, height_m).shape[0] >= 1


def test_a_hidden_object_is_reported_once_two_frames_running_found_it() -> None:
    from perception.hidden_floor import HiddenFloorConfirm

    c = HiddenFloorConfirm(match_m=0.25)
    a = np.array([[2.0, 1.0, 0.0], [1.0, -1.0, 0.0]])
    assert c.update(a).shape == (0, 3)                        # first sighting: not yet
    b = np.array([[2.05, 1.02, 0.0], [3.0, 0.0, 0.0]])        # the first again (moved 5 cm), and a new one
    np.testing.assert_allclose(c.update(b), [[2.05, 1.02, 0.0]])
    assert c.update(np.zeros((0, 3))).shape == (0, 3)         # a frame without: nothing, and the chain is broken
    assert c.update(b).shape == (0, 3)

"""perception.floor: the body's height above the floor from one depth image, against ray-cast scenes.

The scenes are planes intersected exactly (floor, a wall ahead, a box's top), seen by the vehicle's real
camera mount (45 deg right, 30 deg down, portrait) at the SITL's QVGA intrinsics, with structured-light noise.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.typing import NDArray

from perception.floor import FloorConfig, _median, measure_floor
from quadlink.camera import CameraIntrinsics
from quadlink.frames import R_hq, Rx, Ry

R_QC = np.array([[-0.353553, 0.707107, 0.612372], [-0.353553, -0.707107, 0.612372], [0.866025, 0.0, 0.5]])
P_QC_M = np.array([0.08, 0.08, 0.05])
K = CameraIntrinsics.from_fov(320, 240, 58.0, 45.0)


def _depth(height_m: float, roll_rad: float = 0.0, pitch_rad: float = 0.0, wall_ahead_m: float | None = None,
           box: tuple[float, float, float, float, float] | None = None, rng: np.random.Generator | None = None,
           max_range_m: float = 3.5, R_qc: NDArray[np.float64] = R_QC) -> NDArray[np.float32]:
    """Depth (optical z, m; 0 = no reading) of a floor ``height_m`` below the body centre, an optional wall
    across the camera's horizontal view direction ``wall_ahead_m`` from the body, and an optional box top
    ``(x0, x1, y0, y1, top_height_m)`` in the camera's horizontal view frame (x along its heading), seen by a
    camera truly mounted at ``R_qc``."""
    u, v = np.meshgrid(np.arange(K.width, dtype=float), np.arange(K.height, dtype=float))
    rays_c = np.stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones_like(u)], axis=-1)   # optical z = 1
    R_h = R_hq(roll_rad, pitch_rad)
    d_h = rays_c @ (R_h @ R_qc).T
    o_h = R_h @ P_QC_M
    heading = np.array([R_QC[0, 2], R_QC[1, 2], 0.0])
    heading /= np.linalg.norm(heading)
    side = np.array([-heading[1], heading[0], 0.0])
    t = np.full(u.shape, np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_floor = (height_m - o_h[2]) / d_h[..., 2]
        t = np.where(t_floor > 0, t_floor, t)
        if wall_ahead_m is not None:
            along = d_h @ heading
            t_wall = (wall_ahead_m - o_h @ heading) / along
            t = np.where((t_wall > 0) & (t_wall < t), t_wall, t)
        if box is not None:
            x0, x1, y0, y1, top = box
            t_top = (height_m - top - o_h[2]) / d_h[..., 2]
            hit = o_h + d_h * t_top[..., None]
            inside = (hit @ heading >= x0) & (hit @ heading <= x1) & (hit @ side >= y0) & (hit @ side <= y1)
            t = np.where(inside & (t_top > 0) & (t_top < t), t_top, t)
    depth = t   # the rays have optical z = 1: the parameter is the depth
    if rng is not None:   # (a ray above the horizon stays no reading)
        noise = rng.normal(0.0, 1.0, depth.shape) * (0.0012 + 0.0019 * (np.minimum(depth, 1e3) - 0.4) ** 2)
        depth = depth + noise
    depth = np.where(np.isfinite(depth) & (depth <= max_range_m) & (depth >= 0.5), depth, 0.0)
    return depth.astype(np.float32)


@pytest.mark.parametrize("height_m", [0.25, 0.6, 1.2, 2.0, 2.6])
def test_the_height_above_a_bare_floor_within_two_centimetres(height_m: float, rng: np.random.Generator) -> None:
    obs = measure_floor(_depth(height_m, rng=rng), K, R_QC, P_QC_M, 0.0, 0.0)
    assert obs is not None
    assert obs.height_m == pytest.approx(height_m, abs=0.02)


def test_tilted_body_with_its_attitude(rng: np.random.Generator) -> None:
    roll, pitch = math.radians(8.0), math.radians(-6.0)
    obs = measure_floor(_depth(1.5, roll, pitch, rng=rng), K, R_QC, P_QC_M, roll, pitch)
    assert obs is not None and obs.height_m == pytest.approx(1.5, abs=0.02)
    # the same image read with a level attitude: a 10 deg error tilts the floor past the normal test
    assert measure_floor(_depth(1.5, roll, pitch, rng=rng), K, R_QC, P_QC_M, 0.0, 0.0) is None or \
        abs(measure_floor(_depth(1.5, roll, pitch, rng=rng), K, R_QC, P_QC_M, 0.0, 0.0).height_m - 1.5) < 0.2  # type: ignore[union-attr]


def test_a_wall_ahead_hides_part_of_the_floor_but_is_never_taken_for_it(rng: np.random.Generator) -> None:
    obs = measure_floor(_depth(2.3, wall_ahead_m=2.2, rng=rng), K, R_QC, P_QC_M, 0.0, 0.0)
    assert obs is not None and obs.height_m == pytest.approx(2.3, abs=0.02)


def test_only_a_wall_in_view_gives_no_height() -> None:
    """High up and close to a wall the whole image is wall: its lowest strip is no floor."""
    depth = _depth(2.6, wall_ahead_m=0.9)
    assert np.count_nonzero(depth) > 0.9 * depth.size
    assert measure_floor(depth, K, R_QC, P_QC_M, 0.0, 0.0) is None


def test_a_box_top_below_is_not_the_floor_when_the_floor_shows_around_it(rng: np.random.Generator) -> None:
    box = (0.6, 1.6, -0.6, 0.6, 0.7)   # a 0.7 m high box ahead, under much of the view
    depth = _depth(1.2, box=box, rng=rng)
    obs = measure_floor(depth, K, R_QC, P_QC_M, 0.0, 0.0)
    assert obs is not None and obs.height_m == pytest.approx(1.2, abs=0.02)


def test_floor_beyond_the_depth_range_gives_no_height() -> None:
    assert measure_floor(_depth(4.5), K, R_QC, P_QC_M, 0.0, 0.0) is None


def test_no_readings_and_garbage_give_no_height() -> None:
    assert measure_floor(np.zeros((240, 320), np.float32), K, R_QC, P_QC_M, 0.0, 0.0) is None
    junk = np.full((240, 320), np.nan, np.float32)
    junk[::7, ::5] = np.inf
    assert measure_floor(junk, K, R_QC, P_QC_M, 0.0, 0.0) is None
    assert measure_floor(_depth(1.0), K, R_QC, P_QC_M, 0.0, 0.0, FloorConfig(enabled=False)) is None


@pytest.mark.parametrize("height_m", [1.0, 1.6, 2.2])
def test_a_tilted_view_is_levelled_by_the_floors_own_plane(height_m: float, rng: np.random.Generator) -> None:
    """Campaign 12's flight 4: the attitude that levels H 5 deg off in roll (the odometry's, after a jump at
    lift-off) and the camera mounted 1.8 deg off. The layer's median in H is off by several centimetres; the
    floor's own plane gives the height within 1.5 cm."""
    R_true = Rx(math.radians(-1.8)) @ Ry(math.radians(-0.4)) @ R_QC
    roll_error, pitch_error = math.radians(-5.0), math.radians(1.5)
    depth = _depth(height_m, rng=rng, R_qc=R_true)
    in_h = measure_floor(depth, K, R_QC, P_QC_M, roll_error, pitch_error, FloorConfig(plane_fit=False))
    assert in_h is not None and abs(in_h.height_m - height_m) > 0.04   # the bias this is about
    obs = measure_floor(depth, K, R_QC, P_QC_M, roll_error, pitch_error)
    assert obs is not None and obs.height_m == pytest.approx(height_m, abs=0.015)


def test_a_strip_of_floor_is_levelled_by_its_normals_not_fitted(rng: np.random.Generator) -> None:
    """High up with a wall 1.9 m ahead only a strip of floor shows (too narrow for a plane: its fit would be
    tilted by the noise); its neighbourhoods' mean normal still takes out most of a 4 deg tilt."""
    roll_error = math.radians(4.0)
    depth = _depth(2.4, wall_ahead_m=1.9, rng=rng)
    in_h = measure_floor(depth, K, R_QC, P_QC_M, roll_error, 0.0, FloorConfig(plane_fit=False))
    obs = measure_floor(depth, K, R_QC, P_QC_M, roll_error, 0.0)
    assert in_h is not None and obs is not None
    assert abs(obs.height_m - 2.4) < 0.5 * abs(in_h.height_m - 2.4)
    assert obs.height_m == pytest.approx(2.4, abs=0.03)


def test_the_floors_median_is_numpys_to_the_bit(rng: np.random.Generator) -> None:
    """The fit's own median (no np.median machinery) gives np.median's value exactly: odd and even sizes, ties, a
    NaN."""
    for n in (1, 2, 3, 4, 7, 8, 150, 151, 1301):
        for x in (rng.normal(size=n), np.round(rng.normal(size=n), 1)):
            assert _median(x) == float(np.median(x))
    assert math.isnan(_median(np.array([0.5, math.nan, 0.7])))

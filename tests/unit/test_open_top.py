"""A surface seen only up to the camera's upper ray is no top (issue 31, falsify trials 48 and 58).

The camera looks 30 deg down and its upper ray is about level: a wall or a column is seen up to the camera's height.
Seen from below, after a climb, the highest points seen of it lie under the vehicle; they must neither count as an
object below it (a LAND refused, then a "move clear" into the doorway's other side) nor as a low obstacle the vehicle
may pass over (the avoidance's 3D distance past its band).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from depth_scenes import P_QC_M, R_QC, VIEW_AZ_RAD, K, column_at, render, render_box_with_shadow

from companion.landing_spot import LandingSpotParams, object_below
from companion.obstacle_points import select_points, with_open_tops
from companion.reference_params import ReferenceParams
from perception.obstacle_map import ObstacleMap, ObstacleMapConfig
from perception.obstacles import ObstacleConfig, extract_obstacles

pytestmark = pytest.mark.unit

CFG = ObstacleConfig(rows=6, cols=8)


def observe(depth: np.ndarray):
    return extract_obstacles(depth, K, R_QC, P_QC_M, 0.0, 0.0, CFG)


@pytest.mark.parametrize("height_m", [0.8, 1.2, 1.6])
@pytest.mark.parametrize("distance_m", [0.75, 0.8, 0.9, 1.4, 2.2])
def test_a_full_height_column_has_no_top_and_the_floor_has_one(height_m: float, distance_m: float,
                                                                 rng: np.random.Generator) -> None:
    """Every sector point on a column that rises past the image is open; every one on the floor is seen over."""
    obs = observe(render(height_m, [column_at(distance_m, radius_m=0.3, dark=False)], rng))
    assert obs.open_top is not None and obs.open_top.shape == (obs.points_h_m.shape[0],)
    on_floor = obs.points_h_m[:, 2] > height_m - 0.05
    assert (~on_floor).sum() >= 3, "the column is in view"
    assert obs.open_top[~on_floor].all()
    assert not obs.open_top[on_floor].any()


@pytest.mark.parametrize("height_m,top_m", [(1.0, 0.5), (1.3, 0.75), (1.6, 0.4)])
def test_the_top_of_a_box_below_the_camera_is_seen_over(height_m: float, top_m: float,
                                                         rng: np.random.Generator) -> None:
    """The points on a box's top face, with the floor behind it in view (or out of range), are tops; its near face's
    points below the top are not (the top face above them is what the probe falls on)."""
    obs = observe(render_box_with_shadow(height_m, 1.0, 0.6, 0.4, top_m, 0.0, rng))
    z_top = height_m - top_m
    on_top = np.abs(obs.points_h_m[:, 2] - z_top) < 0.03
    assert on_top.sum() >= 2
    assert not obs.open_top[on_top].any()


def test_the_map_carries_the_flag_and_hidden_objects_come_in_open(rng: np.random.Generator) -> None:
    m = ObstacleMap(ObstacleMapConfig())
    obs = observe(render(1.0, [column_at(1.2, radius_m=0.3, dark=False)], rng))
    hidden = np.array([[1.5, -0.5, 0.2]])
    m.measure(0.0, obs, rng, hidden)
    assert m.open_top.shape == (len(m),)
    near_hidden = np.linalg.norm(m.points_h_m - hidden, axis=1) < 0.2
    assert near_hidden.any() and m.open_top[near_hidden].all()
    m.predict(0.1, np.array([0.3, 0.0, -0.2]), np.array([0.3, 0.0, -0.2]), 0.0, 0.0, rng)
    assert m.open_top.shape == (len(m),)
    assert m.open_top.sum() >= obs.open_top.sum()


def wall_seen_from_below(climb_m: float) -> tuple[np.ndarray, np.ndarray]:
    """A wall 0.3 m beside the vehicle, seen (from a distance, before a climb of ``climb_m``) from the floor to the
    camera's old height: 1.0 m below the old level, z down; open-top flags as perception gives them."""
    rows = []
    for y in np.arange(-0.6, 0.61, 0.1):
        for z in np.arange(0.0, 1.0, 0.1):
            rows.append((0.3, y, z + climb_m))
    p = np.array(rows)
    open_top = np.ones(p.shape[0], dtype=bool)
    return p, open_top


def test_a_wall_seen_from_below_is_beside_the_vehicle_not_below_it() -> None:
    params = LandingSpotParams()
    p, open_top = wall_seen_from_below(climb_m=0.4)
    height_m = 1.0 + 0.4
    # without the flag its seen "top" lies 0.4 m under the vehicle, inside the footprint: an object below
    assert object_below(p, height_m, params, floor_margin_m=0.1) is not None
    extended = with_open_tops(p, open_top, height_m, 0.1)
    assert object_below(extended, height_m, params, floor_margin_m=0.1) is None
    # the avoidance takes it by its horizontal distance, inside its band
    band = select_points(extended, ReferenceParams(), height_m, 2.0)
    assert band.shape[0] and float(np.min(np.hypot(band[:, 0], band[:, 1]))) == pytest.approx(0.3, abs=1e-9)
    assert band.shape[0] < select_points(p, ReferenceParams(), height_m, 2.0).shape[0] + 20   # one per 5 cm cell


def test_a_box_with_a_seen_top_stays_an_object_below() -> None:
    params = LandingSpotParams()
    box = np.array([[x, y, 0.5] for x in (-0.1, 0.0, 0.1) for y in (-0.1, 0.0, 0.1)])   # 0.5 m tall, 1.0 m below
    seen_over = np.zeros(box.shape[0], dtype=bool)
    below = object_below(with_open_tops(box, seen_over, 1.0, 0.1), 1.0, params, floor_margin_m=0.1)
    assert below is not None and below.top_height_m == pytest.approx(0.5)


def test_the_floor_is_never_extended_and_mismatched_flags_change_nothing() -> None:
    floor = np.array([[1.0, 0.0, 1.0], [2.0, 0.5, 0.98]])
    assert with_open_tops(floor, np.ones(2, dtype=bool), 1.0, 0.1).shape == (2, 3)
    assert with_open_tops(floor, np.ones(3, dtype=bool), None, 0.1).shape == (2, 3)
    assert with_open_tops(floor, None).shape == (2, 3)
    above = np.array([[1.0, 0.0, -0.3]])   # a point above the vehicle: already reaches past it
    assert with_open_tops(above, np.ones(1, dtype=bool), 1.0, 0.1).shape == (1, 3)
    assert math.isclose(VIEW_AZ_RAD, math.radians(45.0), abs_tol=1e-3)


def test_a_box_face_under_a_top_seen_over_is_not_extended() -> None:
    """The front face of a box seen over at its top edge: its points are open (the probe above them falls on the
    box) but the top caps them, so the box stays a box: no column at the vehicle's level, still an object below."""
    height_m = 1.0
    top = np.array([[x, y, 0.5] for x in (0.0, 0.1, 0.2) for y in (-0.1, 0.0, 0.1)])
    face = np.array([[-0.03, y, z] for y in (-0.1, 0.0, 0.1) for z in (0.6, 0.7, 0.8)])
    p = np.concatenate([top, face])
    flags = np.concatenate([np.zeros(top.shape[0], dtype=bool), np.ones(face.shape[0], dtype=bool)])
    extended = with_open_tops(p, flags, height_m, 0.1)
    assert extended.shape == p.shape
    assert object_below(extended, height_m, LandingSpotParams(), floor_margin_m=0.1) is not None
    # the same face with no top seen (a wall's foot seen from below): extended
    assert with_open_tops(face, np.ones(face.shape[0], dtype=bool), height_m, 0.1).shape[0] > face.shape[0]


def test_an_open_copy_on_a_flat_top_is_capped_by_its_seen_over_neighbours(rng: np.random.Generator) -> None:
    """A box's top 0.65 m under the vehicle, seen over, its copies scattered by the map's noise (2 cm); one copy of a
    point at the top's edge came in open (its probe fell in the projector's shadow past the edge) and stands 2 or 6 cm
    above the rest: it is the top, not a wall's foot seen from below, so no column at the vehicle's level (a LAND test's
    hover was pushed 0.5 m off the box by it, the column 0.42 m away)."""
    height_m = 1.05
    top = np.array([[x, y, 0.65] for x in np.arange(0.3, 0.8, 0.05) for y in np.arange(-0.2, 0.21, 0.05)])
    top[:, 2] += rng.normal(0.0, 0.01, top.shape[0]).clip(-0.015, 0.015)
    for copy_z_m in (0.63, 0.59):   # 2 cm above the rest; 6 cm, as a copy aged 6.5 s stood (eq. 14's noise)
        edge_copy = np.array([[0.42, -0.06, copy_z_m]])
        p = np.concatenate([top, edge_copy])
        flags = np.r_[np.zeros(top.shape[0], dtype=bool), True]
        assert with_open_tops(p, flags, height_m, 0.1).shape == p.shape
    # the control: with the top seen 15 cm lower than it (a step, not the same face) the copy is a column
    lower = top + np.array([0.0, 0.0, 0.15])
    assert with_open_tops(np.concatenate([lower, edge_copy]), flags, height_m, 0.1).shape[0] == p.shape[0] + 1


def test_a_wall_rising_from_a_table_top_keeps_its_column() -> None:
    """A wall (open: seen from below) standing on a table top the camera saw over: its points at the table's level or
    below are capped, the ones above it are not, and the wall's cells keep their column whichever point came first."""
    height_m = 1.2
    table = np.array([[x, y, 0.5] for x in (0.3, 0.35, 0.4) for y in (-0.1, 0.0, 0.1)])
    wall = np.array([[0.45, y, z] for y in (-0.1, 0.0, 0.1) for z in (0.52, 0.3, 0.1)])  # the capped one first per cell
    p = np.concatenate([table, wall])
    flags = np.r_[np.zeros(table.shape[0], dtype=bool), np.ones(wall.shape[0], dtype=bool)]
    extended = with_open_tops(p, flags, height_m, 0.1)
    columns = extended[p.shape[0]:]
    assert columns.shape[0] == 3
    assert np.allclose(columns[:, 0], 0.45) and np.allclose(columns[:, 2], 0.0)

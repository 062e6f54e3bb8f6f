"""The one judge (harness.judge): every non-floor surface, the whole flight, no blind spot near the floor."""

from __future__ import annotations

import math

import numpy as np
import pytest

from harness.judge import CLEARANCE_BOUND_M, ArenaGeometry, judge
from sim_sitl.config import RoomConfig, ScenarioConfig, SceneObject, StartPose

REST_M = 0.10   # the centre of mass above the floor at rest (half the 0.20 m body)


def arena() -> ArenaGeometry:
    """A 6 x 6 x 2.5 m room, a 1 m box whose west face is at east 0.5 m, a rug to the north; start at the centre."""
    box = SceneObject(kind="box", name="box", position_m=(0.0, 1.0, -0.5), size_m=(1.0, 1.0, 1.0))
    rug = SceneObject(kind="box", name="rug", position_m=(1.5, 0.0, -0.005), size_m=(1.0, 1.0, 0.01), surface="floor")
    return ArenaGeometry(ScenarioConfig(name="judge", room=RoomConfig(size_m=(6.0, 6.0), height_m=2.5),
                                        start=StartPose((0.0, 0.0)), objects=(box, rug)))


def straight(p0: tuple[float, float, float], p1: tuple[float, float, float], n: int = 200) -> np.ndarray:
    return np.linspace(p0, p1, n)


def test_a_descent_beside_a_box_is_judged_to_the_floor() -> None:
    """Campaigns found failures in descents beside a box: the last 0.3 m above the floor is judged like the rest.
    Local NED from the start (z = 0 at rest): climb to 1 m, slide east to 0.2 m from the box's face, descend."""
    climb = straight((0, 0, 0), (0, 0, -1.0))
    slide = straight((0, 0, -1.0), (0, 0.30, -1.0))
    down = straight((0, 0.30, -1.0), (0, 0.30, 0.0))
    P = np.vstack([climb, slide, down])
    j = judge(np.arange(len(P)) * 0.02, P, arena(), REST_M)
    assert j.min_clearance_m == pytest.approx(0.20, abs=1e-9) and j.nearest_surface == "box"
    assert not j.safe
    # the whole descent is equally close: the minimum is not hidden below 0.3 m
    low = judge(np.arange(len(down)) * 0.02, down[-20:], arena(), REST_M)
    assert low.min_clearance_m == pytest.approx(0.20, abs=1e-9)


def test_landing_on_the_floor_or_a_rug_is_landing_and_the_ceiling_counts_from_the_centre_of_mass() -> None:
    P = np.vstack([straight((0, 0, 0), (0, 0, -1.5)), straight((0, 0, -1.5), (1.5, 0, -1.5)),
                   straight((1.5, 0, -1.5), (1.5, 0, -0.01))])   # onto the rug
    j = judge(np.arange(len(P)) * 0.02, P, arena(), REST_M)
    # nearest non-floor surface: the box's corner from the start, or the ceiling at 1.5 m + 0.1 m rest height
    ceiling_m = 2.5 - (1.5 + REST_M)
    assert j.min_ceiling_m == pytest.approx(ceiling_m, abs=1e-9)
    assert j.min_clearance_m == pytest.approx(min(ceiling_m, 0.5), abs=1e-9)
    assert j.safe and j.min_clearance_m >= CLEARANCE_BOUND_M


def test_mobility_is_judged_beside_clearance() -> None:
    """A vehicle that never moved is trivially safe: the judgement says how far it went."""
    still = judge(np.arange(100) * 0.02, np.zeros((100, 3)), arena(), REST_M)
    assert still.max_excursion_m == 0.0 and still.path_length_m == 0.0
    assert still.max_height_m == pytest.approx(REST_M)
    square = np.array([[0, 0, -1], [1, 0, -1], [1, -1, -1], [0, -1, -1], [0, 0, -1]], dtype=float)
    moved = judge(np.arange(5.0), square, arena(), REST_M)
    assert moved.path_length_m == pytest.approx(4.0) and moved.max_excursion_m == pytest.approx(math.sqrt(2))


def test_no_truth_is_no_verdict() -> None:
    j = judge(np.zeros(0), np.zeros((0, 3)), arena())
    assert math.isnan(j.min_clearance_m) and j.samples == 0 and not j.safe


def test_a_partition_marked_wall_is_judged_like_any_object() -> None:
    """A procedural partition is a scene object with surface "wall": the judge counts it (it skipped it once, and a
    point 5 cm from a corridor's partition read 1.38 m clear)."""
    partition = SceneObject(kind="box", name="partition", position_m=(1.0, 0.0, -1.25), size_m=(0.1, 4.0, 2.5),
                            surface="wall")
    geo = ArenaGeometry(ScenarioConfig(name="p", room=RoomConfig(size_m=(6.0, 6.0), height_m=2.5),
                                       objects=(partition,)))
    c = geo.clearance(np.array([1.0 - 0.05 - 0.05, 0.0, -1.0]))
    assert c.surface_m == pytest.approx(0.05) and c.nearest_name == "partition"

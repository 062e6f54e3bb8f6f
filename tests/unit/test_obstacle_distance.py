"""OBSTACLE_DISTANCE shows a ground station what the avoidance keeps away from (docs/limits.md: the map's own
summary counted the odd floor particle lifted by its measurement noise, 1-2 m away, that the avoidance never acts on).
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from companion.frame_state import FrameState
from companion.height import HeightParams
from companion.obstacle_points import avoidance_points, sector_distances_m
from companion.reference_params import ReferenceParams
from perception.obstacle_map import ObstacleSectors

pytestmark = pytest.mark.unit

N = 72


def at(az_deg: float, horiz_m: float, z_m: float = 0.0) -> list[float]:
    a = math.radians(az_deg)
    return [horiz_m * math.cos(a), horiz_m * math.sin(a), z_m]


def test_each_sector_holds_its_nearest_point_in_the_band_and_keeps_the_maps_unknown() -> None:
    known = np.full(N, np.inf)
    known[40:50] = np.nan                                      # never observed
    points = np.array([at(0.0, 1.2), at(2.4, 0.9), at(2.6, 1.1), at(-90.0, 2.0, 0.3), at(-90.0, 0.2),
                       at(180.0, 1.5, -0.6), at(45.0, 1.0, 0.8), at(200.0, 0.7)])   # 200 deg: sector 40, unknown
    d = sector_distances_m(points, known, 5.0, 0.0, 0.3, band_m=0.45)
    assert d[0] == pytest.approx(0.9)                          # 0 and 2.4 deg: sector 0, the nearer
    assert d[1] == pytest.approx(1.1)                          # 2.6 deg: sector 1
    assert d[54] == pytest.approx(0.3)                         # -90 deg: 0.2 m read as the minimum distance
    assert d[36] == math.inf                                   # 0.6 m above: out of the band
    assert d[9] == math.inf                                    # 0.8 m below: out of the band
    assert d[40] == pytest.approx(0.7)                         # a point makes an unknown sector known
    assert np.isnan(d[41:50]).all() and np.isinf(d[[2, 10, 30, 60]]).all()
    # a sector layout turned by half a sector moves the points with it
    d2 = sector_distances_m(np.array([at(-1.0, 1.3), at(4.9, 0.8)]), np.full(N, np.inf), 5.0, 2.5, 0.3, band_m=0.45)
    assert d2[71] == pytest.approx(1.3) and d2[0] == pytest.approx(0.8)
    assert np.array_equal(sector_distances_m(None, known, 5.0, 0.0, 0.3, 0.45), np.where(np.isnan(known), np.nan,
                                                                                        np.inf), equal_nan=True)
    bad = np.array([[np.nan, 0.0, 0.0], [1.0, np.inf, 0.0]])
    assert np.isinf(sector_distances_m(bad, np.full(N, np.inf), 5.0, 0.0, 0.3, 0.45)).all()


def test_a_floor_particle_the_maps_summary_counts_is_not_shown_to_the_ground_station() -> None:
    """Flying 1.0 m above the floor: a floor particle lifted 0.2 m by noise, 1.5 m ahead, is in the map's own
    summary (its band is 1 m, its floor margin 0.15 m); the avoidance (band 0.45 m) never acts on it, and the
    ground station now sees the sector free. A wall 1.8 m to the left at the vehicle's height stays."""
    height_m = 1.0
    floor_particle = at(0.0, 1.5, height_m - 0.2)              # H: z down
    wall = at(90.0, 1.8, 0.1)
    floor = at(-45.0, 1.2, height_m - 0.05)
    map_summary = np.full(N, np.inf)
    map_summary[0], map_summary[18] = 1.5, 1.8                 # what perception's map reported
    map_summary[30:40] = np.nan
    out = SimpleNamespace(sectors=ObstacleSectors(0.0, map_summary, 5.0, 0.0, 0.3, 3.5))
    params = ReferenceParams()
    state = FrameState(HeightParams())
    state.avoidance_points_h_m = avoidance_points(np.array([floor_particle, wall, floor]), params, height_m)
    shown = state.obstacle_sectors(out, params).distances_m   # type: ignore[arg-type]
    assert shown[0] == math.inf and shown[18] == pytest.approx(1.8) and shown[63] == math.inf
    assert np.isnan(shown[30:40]).all()

"""The safety envelope of one flight from its truth log and its arena (pure but for reading the tlog).

The judge is :mod:`harness.judge` (the same for tests, the demo and the falsification search): the distance
from the centre of mass to the walls, the objects and the ceiling, from the truth position and the scenario's
geometry, over the whole flight. The truth position is local NED from the start, where the centre of mass
rests ``body_size_m[2] / 2`` above the floor (the generator starts every flight on the floor, not on an object).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from harness.demo.metrics import touchdown_m_s
from harness.demo.report import FlightLog
from harness.judge import ArenaGeometry, judge
from quadlink.ids import TRUTH_SENSOR_NON_FLOOR
from quadlink.mavlink.tlog import read_tlog
from sim_sitl.config import PhysicsConfig, ScenarioConfig

Array = NDArray[np.float64]


@dataclass(frozen=True)
class TruthSeries:
    t_pos_s: Array
    p_local_ned_m: Array  # N x 3, origin at the start
    t_obstacle_s: Array
    obstacle_m: Array  # nearest surface excluding floor and ceiling (truth id 1)


def truth_of_flight(flight: FlightLog) -> TruthSeries:
    """The series of a flight already parsed by the demo's report (:func:`harness.demo.report.load_flight`)."""
    return TruthSeries(flight.t_truth, flight.p_ned, flight.t_dist1, flight.dist1_m)


def read_truth(path: Path) -> TruthSeries:
    pos: list[list[float]] = []
    obs: list[list[float]] = []
    for _, m in read_tlog(path):
        kind = m.get_type()
        if kind == "LOCAL_POSITION_NED":
            pos.append([m.time_boot_ms / 1e3, m.x, m.y, m.z])
        elif kind == "DISTANCE_SENSOR" and m.id == TRUTH_SENSOR_NON_FLOOR:
            obs.append([m.time_boot_ms / 1e3, m.current_distance / 100.0])
    P = np.asarray(pos, dtype=float).reshape(-1, 4)
    O = np.asarray(obs, dtype=float).reshape(-1, 2)
    return TruthSeries(P[:, 0], P[:, 1:4], O[:, 0], O[:, 1])


@dataclass(frozen=True)
class Envelope:
    min_nonfloor_m: float  # walls, objects and ceiling
    min_obstacle_m: float  # walls and objects (truth id 1)
    min_ceiling_m: float
    t_min_s: float  # when the minimum of min_nonfloor_m happened
    surface: str  # "ceiling" or "obstacle"
    max_height_m: float  # centre of mass above the floor
    touchdown_m_s: float = math.nan  # the last landing's impact speed (:func:`touchdown_m_s`)


def envelope(truth: TruthSeries, scenario: ScenarioConfig, body_height_m: float = PhysicsConfig().body_size_m[2],
             ) -> Envelope:
    """The flight's envelope by the one judge (:mod:`harness.judge`): every non-floor surface, the whole flight."""
    if truth.t_pos_s.size == 0:
        return Envelope(math.nan, math.nan, math.nan, math.nan, "", math.nan)
    j = judge(truth.t_pos_s, truth.p_local_ned_m, ArenaGeometry(scenario), rest_height_m=body_height_m / 2)
    surface = "ceiling" if j.nearest_surface == "ceiling" else "obstacle"
    return Envelope(j.min_clearance_m, min(j.min_wall_m, j.min_object_m), j.min_ceiling_m, j.t_min_s, surface,
                    j.max_height_m, touchdown_m_s(truth.t_pos_s, truth.p_local_ned_m))

"""The safety envelope of one flight from its truth log and its arena (pure but for reading the tlog).

The SITL's truth stream carries the distance from the centre of mass to the nearest surface excluding
floor *and ceiling* (DISTANCE_SENSOR id 1) and to any surface (id 0, floor included), so neither is the
issue-14 measure "walls, obstacles and the ceiling". This module adds the ceiling from the geometry: the
room's ceiling is flat at ``room.height_m`` above the floor (objects hanging from it, soffits, are in id 1
already), and the truth position is local NED from the start, where the centre of mass rests
``body_size_m[2] / 2`` above the floor (the generator starts every flight on the floor, not on an object).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from harness.demo.metrics import interpolate
from harness.demo.report import FlightLog
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
        elif kind == "DISTANCE_SENSOR" and m.id == 1:
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


def envelope(truth: TruthSeries, scenario: ScenarioConfig, body_height_m: float = PhysicsConfig().body_size_m[2],
             ) -> Envelope:
    if truth.t_pos_s.size == 0 or truth.t_obstacle_s.size == 0:
        return Envelope(math.nan, math.nan, math.nan, math.nan, "", math.nan)
    up_m = body_height_m / 2 - truth.p_local_ned_m[:, 2]
    ceiling_m = (scenario.room.height_m - up_m) if scenario.room.ceiling else np.full(up_m.shape, math.inf)
    # on the obstacle stream's stamps (both at the truth rate, from the same SITL tick)
    ceiling_at = interpolate(truth.t_pos_s, ceiling_m, truth.t_obstacle_s)
    ceiling_at = np.where(np.isfinite(ceiling_at), ceiling_at, math.inf)
    nonfloor = np.minimum(truth.obstacle_m, ceiling_at)
    k = int(np.argmin(nonfloor))
    return Envelope(float(nonfloor[k]), float(np.min(truth.obstacle_m)), float(np.min(ceiling_m)),
                    float(truth.t_obstacle_s[k]), "ceiling" if ceiling_at[k] < truth.obstacle_m[k] else "obstacle",
                    float(np.max(up_m)))

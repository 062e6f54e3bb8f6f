"""Paper 003's experiments as campaign flights (issue 19): what each is, and its draws (pure).

An experiment flight is ``quadlink paper003 oval|hover`` (:func:`harness.demo.paper003_cli.run_paper003`) in the
experiment's own arena (the oval: ``empty``, a 10 m x 10 m room; the hover: ``paper003-hover``, the same room with
the three scripted pushes) from a drawn start pose, with the campaign's vehicle and sensor draws
(:func:`harness.campaign.draws.draw_vehicle_and_sensors`: mass x U(0.9, 1.1), camera mount, IMU bias spreads,
depth noise, the SITL's seed).

The start pose: the experiments fly relative to the take-off pose (the odometry's local NED starts there, x
along the start heading), so the vehicle's path in the arena is the start position plus the experiment's path
turned by the start yaw. The position and the yaw are drawn uniformly and redrawn until every point of that path
keeps :data:`PATH_CLEARANCE_M` from every wall and object: beyond the repulsion's influence distance, so the
safety layer never bends the experiment and the figures measure the tracker and the estimator only.

Flight ``i`` of seed ``S`` draws from ``SeedSequence(S, spawn_key=(i,))`` split as a teleop campaign's flight is
(arena, operator, vehicle, SITL): the start pose from the arena stream, the operator stream unused, so flight
``i``'s vehicle and sensors are the same in a teleop and an experiment campaign of the same seed.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from functools import cache
from typing import Any

import numpy as np
from numpy.typing import NDArray

from harness.campaign.draws import draw_vehicle_and_sensors
from harness.demo.paper003 import HOVER_SCENARIO, OVAL
from quadlink.errors import ConfigError
from sim_sitl.config import ScenarioConfig, StartPose, load_scenario
from sim_sitl.scenario_gen import clearance_2d

#: horizontal clearance of every point of the path from walls and objects: the repulsion's influence distance
#: (``reference.influence_distance_m`` 0.9 m in configs/companion.yaml) plus 0.3 m for the body and the tracking error
PATH_CLEARANCE_M = 1.2
#: the hover's pushed excursion in any horizontal direction (paper 003: ~0.7 m; 0.81 m measured; a lighter vehicle
#: goes further)
HOVER_REACH_M = 1.0
START_TRIES = 2000


@dataclass(frozen=True)
class Experiment:
    name: str  # the campaign's --experiment
    paper003: str  # ``quadlink paper003 EXPERIMENT``
    scenario: str  # the experiment's arena (scenario name or path)


EXPERIMENTS = {e.name: e for e in (Experiment("paper003-oval", "oval", "empty"),
                                   Experiment("paper003-hover", "hover", str(HOVER_SCENARIO)))}


def experiment(name: str) -> Experiment:
    try:
        return EXPERIMENTS[name]
    except KeyError:
        raise ConfigError(f"unknown experiment {name!r} (known: {', '.join(EXPERIMENTS)})") from None


@cache
def path_xy_m(paper003: str) -> NDArray[np.float64]:
    """Where the vehicle goes relative to its take-off pose (N x 2, m, x along the start heading, y right).

    The oval: the take-off point, the lead-in from it to P1 (the client holds P1; the position loop flies
    straight there) and the trajectory sampled every 0.1 s (a minimum-snap path swings outside its waypoints).
    The hover: the take-off point and a circle of :data:`HOVER_REACH_M` round it (the pushes are along the
    arena's axes, whose directions in the start frame depend on the yaw)."""
    if paper003 == "oval":
        from harness.trajectory_cli import load_trajectory_file

        _, traj = load_trajectory_file(OVAL)
        p1 = traj.sample(0.0).p_m[:2]
        lead_in = np.linspace(0.0, 1.0, 11)[:, None] * p1[None, :]
        oval = np.array([traj.sample(t).p_m[:2] for t in np.arange(0.0, traj.duration_s + 1e-9, 0.1)])
        return np.vstack([lead_in, oval])
    if paper003 == "hover":
        a = np.linspace(0.0, 2 * math.pi, 16, endpoint=False)
        return np.vstack([np.zeros((1, 2)), HOVER_REACH_M * np.column_stack([np.cos(a), np.sin(a)])])
    raise ConfigError(f"unknown paper 003 experiment {paper003!r} (oval or hover)")


def path_in_arena(start: StartPose, path_m: NDArray[np.float64]) -> NDArray[np.float64]:
    """The path (start frame, N x 2) in the arena's north/east: turned by the start yaw, moved to the start."""
    c, s = math.cos(math.radians(start.yaw_deg)), math.sin(math.radians(start.yaw_deg))
    R_arena_start = np.array([[c, -s], [s, c]])
    return np.asarray(start.position_m, dtype=float)[None, :] + path_m @ R_arena_start.T


def path_clearance_m(scenario: ScenarioConfig, start: StartPose, path_m: NDArray[np.float64]) -> float:
    """The smallest horizontal distance from the path, flown from ``start``, to a wall or object."""
    return min(clearance_2d(scenario, (float(x), float(y))) for x, y in path_in_arena(start, path_m))


def draw_start_clear_of(scenario: ScenarioConfig, path_m: NDArray[np.float64], rng: np.random.Generator,
                        clearance_m: float = PATH_CLEARANCE_M, tries: int = START_TRIES) -> tuple[StartPose, float]:
    """A start pose (position uniform in the room, yaw uniform) from which ``path_m`` keeps ``clearance_m``;
    returns it and the path's clearance. ConfigError if the arena has no such pose in ``tries`` draws."""
    nx, ny = scenario.room.size_m
    for _ in range(tries):
        x, y = rng.uniform(-nx / 2, nx / 2), rng.uniform(-ny / 2, ny / 2)
        start = StartPose(position_m=(round(float(x), 3), round(float(y), 3)),
                          yaw_deg=round(float(rng.uniform(-180.0, 180.0)), 2))
        if clearance_2d(scenario, start.position_m) < clearance_m:
            continue  # cheap reject before the whole path
        d = path_clearance_m(scenario, start, path_m)
        if d >= clearance_m:
            return start, d
    raise ConfigError(f"{scenario.name}: no start pose in {tries} draws keeps the experiment's path "
                      f"{clearance_m} m from walls and objects")


@dataclass(frozen=True)
class ExperimentDraws:
    index: int
    campaign_seed: int
    experiment: Experiment
    scenario: ScenarioConfig  # the experiment's arena with the drawn start pose
    vehicle: dict[str, Any]  # the vehicle config (YAML data) the SITL flies
    sitl: dict[str, Any]  # the SITL config (YAML data), without the file paths
    record: dict[str, Any]  # draws.json


def draw_experiment_flight(campaign_seed: int, index: int, name: str) -> ExperimentDraws:
    exp = experiment(name)
    seq = np.random.SeedSequence(campaign_seed, spawn_key=(index,))
    arena_ss, _operator_ss, vehicle_ss, sitl_ss = seq.spawn(4)
    base = load_scenario(exp.scenario)
    start, clearance = draw_start_clear_of(base, path_xy_m(exp.paper003), np.random.default_rng(arena_ss))
    scenario = dataclasses.replace(base, name=f"{name}-{campaign_seed}-{index:04d}", start=start)
    vehicle, sitl, vehicle_record = draw_vehicle_and_sensors(vehicle_ss, sitl_ss)
    record = {
        "campaign_seed": campaign_seed, "index": index, "seed_sequence": {"entropy": seq.entropy,
                                                                          "spawn_key": list(seq.spawn_key)},
        "experiment": name,
        "arena": {"layout": f"fixed:{base.name}", "room_size_m": list(scenario.room.size_m),
                  "start": {"position_m": list(start.position_m), "yaw_deg": start.yaw_deg},
                  "path_clearance_m": round(clearance, 4), "required_clearance_m": PATH_CLEARANCE_M},
        **vehicle_record,
    }
    return ExperimentDraws(index, campaign_seed, exp, scenario, vehicle, sitl, record)

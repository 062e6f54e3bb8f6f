"""perception.floor on the SITL camera's own frames (the producer's depth, its noise and its invalid pixels):
random poses in paper-arena and in procedural arenas, the measured height against the pose it was rendered at."""

from __future__ import annotations

import math

import numpy as np
import pytest

from perception.floor import measure_floor
from quadlink.frames import R_hq, Rz
from quadlink.vehicle import load_vehicle
from sim_sitl.camera_sim import RgbdCamera
from sim_sitl.config import CameraNoiseConfig, ScenarioConfig, SitlConfig, load_scenario
from sim_sitl.scenario_gen import draw_start, generate_procedural
from sim_sitl.world import World

POSES_PER_ARENA = 12


@pytest.mark.parametrize("seed", [0, 4, 5])
def test_height_from_the_sitl_camera_within_two_centimetres(seed: int) -> None:
    rng = np.random.default_rng(seed)
    scenario = load_scenario("paper-arena") if seed == 0 else generate_procedural(rng, f"floor-{seed}")[0]
    vehicle = load_vehicle()
    world = World(vehicle, SitlConfig(), scenario, np.random.default_rng(seed))
    camera = RgbdCamera(world, vehicle.camera, CameraNoiseConfig(), np.random.default_rng(seed))
    seen = 0
    try:
        seen = _fly_poses(world, camera, scenario, rng)
    finally:
        world.close()
    assert seen >= POSES_PER_ARENA * 2 // 3


def _fly_poses(world: World, camera: RgbdCamera, scenario: ScenarioConfig, rng: np.random.Generator) -> int:
    seen = 0
    for _ in range(POSES_PER_ARENA):
        start = draw_start(scenario, rng)
        height_m = float(rng.uniform(0.4, min(2.6, scenario.room.height_m - 0.35)))
        roll, pitch = (float(a) for a in rng.uniform(-0.08, 0.08, 2))
        R_ned_q = Rz(float(rng.uniform(-math.pi, math.pi))) @ R_hq(roll, pitch)
        world.reset_pose(np.array([start.position_m[0], start.position_m[1], -height_m]), R_ned_q)
        frame = camera.render(world.state, 0, 0.0)
        obs = measure_floor(frame.depth_m, frame.intrinsics, frame.R_qc, frame.p_qc_m, roll, pitch)
        if obs is not None:
            seen += 1
            assert obs.height_m == pytest.approx(height_m, abs=0.02), (start, height_m)
    return seen

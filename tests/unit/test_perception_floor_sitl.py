"""perception.floor on the SITL camera's own frames (the producer's depth, its noise and its invalid pixels):
random poses in paper-arena and in procedural arenas, the measured height against the pose it was rendered at."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from perception.floor import FloorConfig, measure_floor
from quadlink.frames import R_hq, Rx, Ry, Rz
from quadlink.vehicle import load_vehicle
from sim_sitl.camera_sim import RgbdCamera
from sim_sitl.config import CameraNoiseConfig, ScenarioConfig, SitlConfig, load_scenario
from sim_sitl.scenario_gen import draw_start, generate_procedural
from sim_sitl.world import World

POSES_PER_ARENA = 12


@pytest.mark.parametrize("seed", [0, 4, 5])
def test_height_from_the_sitl_camera_within_three_centimetres_without_bias(seed: int) -> None:
    """Each image's height within 3 cm, their mean within 1 cm: the floor's plane, fitted to noisy samples 2-4 m
    away, is tilted by their noise by a few tenths of a degree (per image up to 2.7 cm at 2.45 m; the layer's
    median in an exactly levelled H is within 2 mm, but H is never exactly level in flight: see
    test_a_mis_levelled_view...). The companion's height filter averages the images (0.5 s)."""
    rng = np.random.default_rng(seed)
    scenario = load_scenario("paper-arena") if seed == 0 else generate_procedural(rng, f"floor-{seed}")[0]
    vehicle = load_vehicle()
    world = World(vehicle, SitlConfig(), scenario, np.random.default_rng(seed))
    camera = RgbdCamera(world, vehicle.camera, CameraNoiseConfig(), np.random.default_rng(seed))
    errors_m: list[float] = []
    try:
        errors_m = _fly_poses(world, camera, scenario, rng)
    finally:
        world.close()
    assert len(errors_m) >= POSES_PER_ARENA * 2 // 3
    assert abs(float(np.mean(errors_m))) < 0.01


def _fly_poses(world: World, camera: RgbdCamera, scenario: ScenarioConfig, rng: np.random.Generator) -> list[float]:
    errors_m: list[float] = []
    for _ in range(POSES_PER_ARENA):
        start = draw_start(scenario, rng)
        height_m = float(rng.uniform(0.4, min(2.6, scenario.room.height_m - 0.35)))
        roll, pitch = (float(a) for a in rng.uniform(-0.08, 0.08, 2))
        R_ned_q = Rz(float(rng.uniform(-math.pi, math.pi))) @ R_hq(roll, pitch)
        world.reset_pose(np.array([start.position_m[0], start.position_m[1], -height_m]), R_ned_q)
        frame = camera.render(world.state, 0, 0.0)
        obs = measure_floor(frame.depth_m, frame.intrinsics, camera.R_qc, camera.p_qc_m, roll, pitch)
        if obs is not None:
            errors_m.append(obs.height_m - height_m)
            assert obs.height_m == pytest.approx(height_m, abs=0.03), (start, height_m)
    return errors_m


@pytest.mark.parametrize("seed", [0, 7])
def test_a_mis_levelled_view_through_a_mis_mounted_sitl_camera(seed: int) -> None:
    """Campaign 12's flight 4 on the SITL's own frames: the camera truly mounted 1.8 deg off about the body's x
    axis, the companion reading it through the configured mount with an attitude up to 5 deg off (the
    odometry's roll jumped 5 deg at lift-off). The floor's own plane takes out most of the error of the
    layer's median in H (several centimetres)."""
    rng = np.random.default_rng(seed)
    scenario = load_scenario("paper-arena") if seed == 0 else generate_procedural(rng, f"floor-{seed}")[0]
    vehicle = load_vehicle()
    R_true = Rx(math.radians(-1.8)) @ Ry(math.radians(-0.4)) @ vehicle.camera.R_qc_matrix
    mount = dataclasses.replace(vehicle.camera, R_qc=tuple(tuple(float(v) for v in row) for row in R_true))
    world = World(vehicle, SitlConfig(), scenario, np.random.default_rng(seed))
    camera = RgbdCamera(world, mount, CameraNoiseConfig(), np.random.default_rng(seed))
    levelled_m: list[float] = []
    in_h_m: list[float] = []
    try:
        for i in range(POSES_PER_ARENA * 2):
            start = draw_start(scenario, rng)
            height_m = float(rng.uniform(0.8, min(2.4, scenario.room.height_m - 0.45)))
            roll, pitch = (float(a) for a in rng.uniform(-0.08, 0.08, 2))
            world.reset_pose(np.array([start.position_m[0], start.position_m[1], -height_m]),
                             Rz(float(rng.uniform(-math.pi, math.pi))) @ R_hq(roll, pitch))
            frame = camera.render(world.state, i, 0.0)
            roll_read, pitch_read = (float(a) for a in np.array([roll, pitch]) + rng.uniform(-0.087, 0.087, 2))
            args = (frame.depth_m, frame.intrinsics, vehicle.camera.R_qc_matrix, vehicle.camera.p_qc, roll_read,
                    pitch_read)
            obs, in_h = measure_floor(*args), measure_floor(*args, FloorConfig(plane_fit=False))
            if obs is not None and in_h is not None and abs(in_h.height_m - height_m) < 0.3:   # (not a box top)
                levelled_m.append(obs.height_m - height_m)
                in_h_m.append(in_h.height_m - height_m)
    finally:
        world.close()
    assert len(levelled_m) >= POSES_PER_ARENA
    levelled_abs_m, in_h_abs_m = np.abs(levelled_m), np.abs(in_h_m)
    assert float(np.mean(in_h_abs_m)) > 0.04   # the error this is about
    assert float(np.mean(levelled_abs_m)) < float(np.mean(in_h_abs_m)) / 3.0
    assert float(np.median(levelled_abs_m)) < 0.01 and float(np.quantile(levelled_abs_m, 0.9)) < 0.03
    # a strip of floor at 2.3 m, levelled by its normals alone (too narrow for a plane), read 7.9 cm high
    assert float(np.max(levelled_abs_m)) < 0.1, np.round(levelled_m, 3)

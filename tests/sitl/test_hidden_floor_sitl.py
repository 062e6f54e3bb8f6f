"""perception.hidden_floor on the SITL's own Xtion frames (sim_sitl/xtion.py renders them: IR shadows, no return from
dark and specular surfaces, disparity noise), at the poses where it mattered: the dark partition of
configs/scenarios/dark-column.yaml must be found at its distance, and the projector's shadow beside the landing
tests' matte box (9 px of floor with no return beside its corner, at the pose where the CI flight over it stopped)
must not read as an object."""

from __future__ import annotations

import math

import numpy as np
import pytest

from perception.floor import measure_floor
from perception.hidden_floor import HiddenFloorConfig, hidden_floor_points_h
from quadlink.camera import CameraIntrinsics
from quadlink.config import from_dict
from quadlink.frames import Rz
from quadlink.vehicle import load_vehicle
from sim_sitl.camera_sim import RgbdCamera
from sim_sitl.config import ScenarioConfig, load_scenario, load_sitl_config
from sim_sitl.world import World

pytestmark = pytest.mark.sitl

LOW_BOX = {"name": "low-box", "description": "tests/sitl/test_landing_sitl.py's box",
           "room": {"size_m": [8.0, 8.0], "height_m": 3.0, "floor_texture": "carpet", "wall_texture": "concrete"},
           "start": {"position_m": [-1.0, 0.0], "yaw_deg": -67.5},
           "objects": [{"kind": "box", "name": "low-box", "position_m": [1.4, 0.0, -0.2], "size_m": [0.8, 0.8, 0.4],
                        "texture": "checker", "color": [0.85, 0.75, 0.4]}]}


def _hidden_at(scenario: ScenarioConfig, xy_m: tuple[float, float], yaw_deg: float, seed: int) -> np.ndarray:
    """The hidden-floor points (H) of one Xtion frame at ``xy_m``, 1.15 m up, heading ``yaw_deg`` (level)."""
    veh = load_vehicle()
    cfg = load_sitl_config()
    world = World(veh, cfg, scenario, np.random.default_rng(seed))
    try:
        world.reset_pose(np.array([xy_m[0], xy_m[1], -1.15]), Rz(math.radians(yaw_deg)))
        cam = RgbdCamera(world, veh.camera, cfg.camera_noise, np.random.default_rng(seed))
        frame = None
        for k in range(10):   # the model drops frames
            frame = cam.capture(world.state, k, 0.1 * k)
            if frame is not None:
                break
        assert frame is not None and frame.depth_m is not None
        c = veh.camera
        K = CameraIntrinsics.from_fov(c.width_px, c.height_px, c.hfov_deg, c.vfov_deg)
        R_qc, p_qc = np.array(c.R_qc), np.array(c.p_qc_m)
        floor = measure_floor(frame.depth_m, K, R_qc, p_qc, 0.0, 0.0)
        assert floor is not None and abs(floor.height_m - 1.15) < 0.05
        return hidden_floor_points_h(frame.depth_m, K, R_qc, p_qc, 0.0, 0.0, floor.height_m,
                                     config=HiddenFloorConfig(enabled=True))
    finally:
        world.close()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_dark_partition_is_found_at_its_distance(seed: int) -> None:
    """From its start the vehicle's camera looks north at the black partition's face 2.95 m away."""
    pts = _hidden_at(load_scenario("dark-column"), (-2.0, 0.0), -45.0, seed)
    assert pts.shape[0] >= 3
    # H: x along the heading (-45 deg); the partition's face is the plane x_world = 0.95, i.e. 2.95 m north
    north_m = pts[:, 0] * math.cos(math.radians(-45.0)) - pts[:, 1] * math.sin(math.radians(-45.0))
    assert np.all(north_m <= 2.95 + 0.02) and np.median(north_m) >= 2.95 - 0.3


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("x_m", [-0.3, 0.0, 0.2])
def test_the_projectors_shadow_beside_a_matte_box_is_not_an_object(seed: int, x_m: float) -> None:
    """Approaching the landing tests' box (CI stopped at x = 0.41 m, 'not over the box'): nothing hidden."""
    assert _hidden_at(from_dict(ScenarioConfig, LOW_BOX), (x_m, -0.15), -45.0, seed).shape == (0, 3)

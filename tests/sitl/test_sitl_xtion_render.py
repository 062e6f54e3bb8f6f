"""The Xtion camera model on rendered scenes: IR shadows against ray casts from the projector, glass, a black
monitor, frame drops and stamps through ``RgbdCamera.capture``, motion blur from the vehicle's rates."""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
import pybullet as p
import pytest

from quadlink.frames import Rz
from quadlink.vehicle import CameraConfig, load_vehicle
from sim_sitl.camera_sim import RgbdCamera
from sim_sitl.config import (
    CameraNoiseConfig,
    RoomConfig,
    ScenarioConfig,
    SceneObject,
    SitlConfig,
    StartPose,
    XtionConfig,
    load_scenario,
)
from sim_sitl.scene import MATERIAL_CODE
from sim_sitl.world import D, World
from sim_sitl.xtion import ir_shadow

FORWARD = ((0.0, 0.0, 1.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0))  # optical z -> body x, x -> y, y -> z
XTION = CameraNoiseConfig(model="xtion")
QUIET = dataclasses.replace(XTION, xtion=dataclasses.replace(XtionConfig(), frame_drop_probability=0.0,
                                                            stamp_jitter_s=0.0), rgb_noise_levels=0.0)


def _world(objects: tuple[SceneObject, ...], seed: int = 0) -> World:
    scenario = ScenarioConfig(name="test", room=RoomConfig(size_m=(12.0, 12.0), height_m=4.0),
                              start=StartPose((0.0, 0.0), 0.0), objects=objects)
    return World(load_vehicle(), SitlConfig(), scenario, np.random.default_rng(seed))


@pytest.fixture
def post_world():
    # a 0.3 m wide post 1.5 m ahead of the vehicle, in front of a wall board 2.7 m ahead
    w = _world((SceneObject(kind="box", name="post", position_m=(1.65, 0.0, -1.5), size_m=(0.3, 0.3, 3.0),
                            texture="checker"),
                SceneObject(kind="box", name="board", position_m=(2.75, 0.0, -1.5), size_m=(0.1, 4.0, 3.0))))
    w.reset_pose(np.array([0.0, 0.0, -1.5]), np.eye(3))
    yield w
    w.close()


@pytest.mark.parametrize("projector_x_m", [0.075, -0.075])
def test_ir_shadow_agrees_with_ray_casts_from_the_projector(post_world, projector_x_m):
    """Every pixel near the post's edges: the model calls it a hole iff a ray from the projector to its surface
    point hits something else first (pybullet's ray test, independent of the model's scanline rule)."""
    mount = CameraConfig(R_qc=FORWARD, p_qc_m=(0.0, 0.0, 0.0))
    cam = RgbdCamera(post_world, mount, QUIET, np.random.default_rng(1))
    _, z = cam.render_raw(post_world.state)
    k = cam.intrinsics
    shadow = ir_shadow(z, k, projector_x_m)
    p_ned, R_ned_c = cam.pose_ned(post_world.state)
    proj_ned = p_ned + R_ned_c @ np.array([projector_x_m, 0.0, 0.0])
    rows = range(60, 180, 6)
    cols = range(80, 240)
    starts, ends, pix = [], [], []
    for v in rows:
        for u in cols:
            point = p_ned + R_ned_c @ (z[v, u] * np.array([(u - k.cx) / k.fx, (v - k.cy) / k.fy, 1.0]))
            back = point + 0.01 * (proj_ned - point) / np.linalg.norm(proj_ned - point)  # 1 cm off the surface
            starts.append((D @ proj_ned).tolist())
            ends.append((D @ back).tolist())
            pix.append((v, u))
    hits = p.rayTestBatch(starts, ends, physicsClientId=post_world.client)
    blocked = np.array([h[0] >= 0 for h in hits])
    modelled = np.array([shadow[v, u] for v, u in pix])
    assert blocked.sum() > 100  # the post shadows a band on the board on every row
    agree = float((blocked == modelled).mean())
    assert agree > 0.985, agree  # disagreement only at a pixel's width on the band's two ends
    # on the side away from the projector: a projector on the right (+x) shadows left of the post
    post_cols = np.flatnonzero(np.abs(z[120] - 1.5) < 0.01)
    band = np.flatnonzero(shadow[120])
    if projector_x_m > 0:
        assert band.max() < post_cols.min()
    else:
        assert band.min() > post_cols.max()
    width = k.fx * abs(projector_x_m) * (1 / 1.5 - 1 / 2.7)
    assert len(band) == pytest.approx(width, abs=1.5)


def test_rendered_frame_has_holes_beside_the_post_on_one_side_only(post_world):
    mount = CameraConfig(R_qc=FORWARD, p_qc_m=(0.0, 0.0, 0.0))
    frame = RgbdCamera(post_world, mount, QUIET, np.random.default_rng(1)).render(post_world.state, 0, 0.0)
    basic = RgbdCamera(post_world, mount, CameraNoiseConfig(), np.random.default_rng(1)).render(post_world.state, 0,
                                                                                              0.0)
    row, row_basic = frame.depth_m[100:140], basic.depth_m[100:140]
    post = np.flatnonzero(np.all(np.abs(row - 1.5) < 0.05, axis=0))
    # the band is f_x b (1/1.5 - 1/2.7) = 6.4 px wide, left of the post: the default projector sits on the right
    assert np.all(row[:, post.min() - 6:post.min()] == 0)
    assert np.all(row[:, post.min() - 14:post.min() - 8] > 0)  # beyond the band: lit
    right = row[:, post.max() + 3:post.max() + 15]  # (the edge pixels themselves are grazing: invalid)
    assert np.all(right > 0) and np.all(np.abs(right - 2.7) < 0.1)
    assert np.all(row_basic[:, post.min() - 6:post.min() - 2] > 0)  # the basic model has no shadows


@pytest.fixture(scope="module")
def hazards():
    """xtion-hazards, its twin without the glass door, and its twin with every material matte (the door last in
    all three: the textures are drawn in body order, so the other bodies' textures are the same)."""
    base = load_scenario("xtion-hazards")
    door = [o for o in base.objects if o.name == "glass-door"]
    others = tuple(o for o in base.objects if o.name != "glass-door")
    base = dataclasses.replace(base, objects=others + tuple(door))
    no_door = dataclasses.replace(base, objects=others)
    matte = dataclasses.replace(base, objects=tuple(dataclasses.replace(o, material="matte") for o in base.objects))
    worlds = {name: World(load_vehicle(), SitlConfig(), s, np.random.default_rng(4))
              for name, s in (("base", base), ("no_door", no_door), ("matte", matte))}
    yield worlds
    for w in worlds.values():
        w.close()


def _look(world: World, x: float, y: float, yaw_deg: float, noise: CameraNoiseConfig,
          renderer: str = "raster") -> RgbdCamera:
    mount = CameraConfig(R_qc=FORWARD, p_qc_m=(0.0, 0.0, 0.0))
    world.reset_pose(np.array([x, y, -1.2]), Rz(math.radians(yaw_deg)))
    return RgbdCamera(world, mount, noise, np.random.default_rng(2), renderer=renderer)


@pytest.mark.parametrize("renderer", ["raster", "pybullet"])
def test_glass_door_is_invisible_in_colour_and_depth(hazards, renderer):
    """From 1.3 m in front of the door: colour and depth are those of the room without the door, and depth reaches
    past the door; with the door matte, the door plane is 1.3 m away. The body is still there for the physics."""
    views = {}
    for name in ("base", "no_door", "matte"):
        cam = _look(hazards[name], -0.3, -0.75, 0.0, QUIET, renderer)
        views[name] = cam.render_raw(hazards[name].state)
    door = (slice(40, 200), slice(130, 190))  # the doorway (0.9 m x 2.1 m) fills the centre of the view
    rgb, z = views["base"]
    assert np.array_equal(rgb, views["no_door"][0]) and np.array_equal(z, views["no_door"][1])
    assert np.all(np.abs(views["matte"][1][door] - 1.28) < 0.03)  # door face at x = 0.98 m
    assert np.all(z[door] > 2.5)  # the room behind (the north wall 4.3 m away)
    any_m, _ = hazards["base"].nearest_distances(np.array([0.95, -0.75, -1.0]))
    assert any_m < 0.05  # the physics has the door


def test_dark_monitor_and_glossy_panel_give_no_return_in_the_xtion_model(hazards):
    world = hazards["base"]
    for x, y, yaw, name in ((-1.0, 1.4, 90.0, "monitor"), (-1.5, -1.6, -90.0, "glossy-panel")):
        cam = _look(world, x, y, yaw, QUIET)
        rgb, z, material = cam.render_layers(world.state)
        code = MATERIAL_CODE["dark" if name == "monitor" else "specular"]
        on = material == code
        assert on.sum() > 2000, name  # the surface fills a good part of the view
        frame = cam.render(world.state, 0, 0.0)
        assert np.all(frame.depth_m[on] == 0), name
        basic = _look(world, x, y, yaw, CameraNoiseConfig()).render(world.state, 0, 0.0)
        assert np.mean(basic.depth_m[on] > 0) > 0.95, name  # the basic model sees it
        matte = ~on & (z > 0.6) & (z < 3.3)
        assert np.mean(frame.depth_m[matte] > 0) > 0.8, name  # the matte surroundings return


def test_pybullet_renderer_gives_the_same_materials(hazards):
    world = hazards["base"]
    cams = {r: _look(world, -1.0, 1.4, 90.0, QUIET, r) for r in ("raster", "pybullet")}
    mats = {r: c.render_layers(world.state)[2] for r, c in cams.items()}
    agree = float(np.mean(mats["raster"] == mats["pybullet"]))
    assert agree > 0.97
    assert (mats["pybullet"] == MATERIAL_CODE["dark"]).sum() > 2000


def test_capture_drops_frames_and_jitters_stamps_as_configured(post_world):
    mount = CameraConfig(R_qc=FORWARD, p_qc_m=(0.0, 0.0, 0.0), width_px=80, height_px=60)
    xt = dataclasses.replace(XtionConfig(), frame_drop_probability=0.25, stamp_jitter_s=0.003, stamp_jitter_max_s=0.009)
    cam = RgbdCamera(post_world, mount, dataclasses.replace(XTION, xtion=xt), np.random.default_rng(9))
    n = 1200
    errors = []
    dropped = 0
    for i in range(n):
        t = i / 30.0
        frame = cam.capture(post_world.state, i, t)
        if frame is None:
            dropped += 1
            continue
        assert frame.seq == i
        errors.append(frame.stamp_s - t)
    rate = dropped / n
    assert abs(rate - 0.25) < 4 * math.sqrt(0.25 * 0.75 / n)
    err = np.array(errors)
    assert err.std() == pytest.approx(0.003 * 0.9866, rel=0.08)
    assert np.abs(err).max() <= 0.009 + 1e-9
    # the basic model neither drops nor jitters
    basic = RgbdCamera(post_world, mount, CameraNoiseConfig(), np.random.default_rng(9))
    frames = [basic.capture(post_world.state, i, i / 30.0) for i in range(50)]
    assert all(f is not None and f.stamp_s == i / 30.0 for i, f in enumerate(frames))


def _gradient_energy(rgb: np.ndarray) -> float:
    grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float32)
    return float(np.mean(np.diff(grey, axis=1)[:-1] ** 2 + np.diff(grey, axis=0)[:, :-1] ** 2))


def test_blur_grows_with_the_vehicles_yaw_rate():
    """The default portrait mount over the textured office: the image gradient energy falls as the yaw rate grows;
    flying sideways blurs near surfaces more than far ones."""
    world = World(load_vehicle(), SitlConfig(), load_scenario("office"), np.random.default_rng(5))
    try:
        world.reset_pose(world.start_p_ned_m + np.array([0.0, 0.0, -1.2]), Rz(math.radians(-30.0)))
        still = world.state
        cam = RgbdCamera(world, load_vehicle().camera, QUIET, np.random.default_rng(3))
        energy = []
        for rate in (0.0, 1.0, 2.0, 4.0):
            state = dataclasses.replace(still, omega_q_rad_s=np.array([0.0, 0.0, rate]))
            energy.append(_gradient_energy(cam.render(state, 0, 0.0).rgb))
        assert energy[0] == pytest.approx(_gradient_energy(cam.render_raw(still)[0]))  # at rest: no blur
        assert energy[0] > energy[1] > energy[2] > energy[3]
        assert energy[3] < 0.6 * energy[0]
    finally:
        world.close()

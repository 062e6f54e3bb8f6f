"""The raster renderer (sim_sitl/raster.py) against pybullet's tiny renderer and against known geometry."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from quadlink.camera import CameraIntrinsics
from quadlink.errors import ConfigError
from quadlink.frames import Rz
from quadlink.vehicle import CameraConfig, load_vehicle
from sim_sitl.camera_sim import RgbdCamera, incidence_cos
from sim_sitl.config import (
    CameraNoiseConfig,
    RoomConfig,
    ScenarioConfig,
    SceneObject,
    SitlConfig,
    StartPose,
    load_scenario,
    load_sitl_config,
)
from sim_sitl.raster import EDGE_INSET_PX, EDGE_MIN_PX, RasterRenderer, _inset
from sim_sitl.scene import build_scene, scene_textures
from sim_sitl.world import World

FORWARD = ((0.0, 0.0, 1.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0))  # optical z -> body x, x -> y, y -> z
NOISE = CameraNoiseConfig()


def _Rx(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _Ry(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _valid(z: np.ndarray, k: CameraIntrinsics) -> np.ndarray:
    """The noise model's validity (range and incidence) of a noise-free depth map."""
    mount = load_vehicle().camera
    return ((z >= mount.min_range_m) & (z <= mount.max_range_m)
            & (incidence_cos(z, k) >= math.cos(math.radians(NOISE.max_incidence_deg))))


def _compare(world: World, poses: list[tuple[np.ndarray, np.ndarray]]) -> list[dict[str, float]]:
    """Noise-free depth and colour of both renderers (the vehicle's mount) at each body pose."""
    vehicle = load_vehicle()
    cams = {r: RgbdCamera(world, vehicle.camera, NOISE, np.random.default_rng(1), renderer=r)
            for r in ("pybullet", "raster")}
    k = cams["raster"].intrinsics
    out = []
    for p_ned, R_ned_q in poses:
        world.reset_pose(p_ned, R_ned_q)
        (rgb_p, z_p), (rgb_r, z_r) = (cams[r].render_raw(world.state) for r in ("pybullet", "raster"))
        v_p, v_r = _valid(z_p, k), _valid(z_r, k)
        both = v_p & v_r
        dz = np.abs(z_p - z_r)[both]
        grad = [np.abs(np.diff(rgb.astype(float).mean(axis=2), axis=1)).mean() for rgb in (rgb_p, rgb_r)]
        out.append({"agree": float((v_p == v_r).mean()), "both": float(both.mean()),
                    "median": float(np.median(dz)) if dz.size else 0.0,
                    "p95": float(np.percentile(dz, 95)) if dz.size else 0.0,
                    "grad_p": grad[0], "grad_r": grad[1],
                    "mean_p": float(rgb_p.mean()), "mean_r": float(rgb_r.mean())})
    return out


def _poses(world: World) -> list[tuple[np.ndarray, np.ndarray]]:
    """On the ground at the start, hovering and turning, tilted, and against the walls (which then pass
    behind the camera: the near-plane clipping)."""
    start = world.start_p_ned_m
    nx, ny = world.scenario.room.size_m
    yaw0 = math.radians(world.scenario.start.yaw_deg)
    up = np.array([0.0, 0.0, -1.2])
    return [
        (start, Rz(yaw0)),  # landed: camera 5 cm above the floor
        (start + up, Rz(yaw0)),
        (start + up, Rz(yaw0 + math.pi)),
        (np.array([0.0, 0.0, -1.0]), Rz(math.radians(75.0))),
        (np.array([0.5, -0.8, -1.5]), Rz(math.radians(-120.0)) @ _Ry(0.35) @ _Rx(-0.3)),  # tilted
        (np.array([-nx / 2 + 0.25, ny / 2 - 0.3, -1.0]), Rz(math.radians(20.0))),  # corner, walls beside/behind
        (np.array([0.0, -ny / 2 + 0.4, -1.2]), Rz(math.radians(-60.0))),  # along the west wall, which passes behind
        (np.array([nx / 2 - 0.3, 0.0, -2.2]), Rz(math.radians(200.0)) @ _Ry(-0.4)),  # near the ceiling, pitched up
    ]


@pytest.fixture(scope="module", params=["paper-arena", "office"])
def scenario_world(request):
    world = World(load_vehicle(), SitlConfig(), load_scenario(request.param), np.random.default_rng(3))
    yield world
    world.close()


def test_depth_and_validity_agree_with_pybullet(scenario_world):
    results = _compare(scenario_world, _poses(scenario_world))
    for i, r in enumerate(results):
        assert r["agree"] >= 0.97, (i, r)
        if r["both"] > 0.01:
            assert r["median"] <= 0.01, (i, r)
            assert r["p95"] <= 0.05, (i, r)
    assert sum(r["both"] > 0.2 for r in results) >= 4  # most poses see plenty of valid depth
    # the colour is textured like pybullet's (the raster samples the textures bilinearly at full resolution,
    # pybullet more coarsely) and about as bright (same Lambert light)
    textured = [r for r in results if r["grad_p"] > 1.0]
    assert len(textured) >= 3
    for r in textured:
        assert 0.5 * r["grad_p"] <= r["grad_r"] <= 4.0 * r["grad_p"], r
        assert r["grad_r"] > 1.5, r
    for r in results:
        assert abs(r["mean_r"] - r["mean_p"]) < 20.0, r


def test_open_room_with_a_rug_agrees_with_pybullet():
    """No ceiling or walls (the slabs are drawn as bodies; beyond them: background) and a floor-type rug
    under a box (floor-type bodies are drawn first)."""
    scenario = ScenarioConfig(
        name="open", room=RoomConfig(size_m=(6.0, 6.0), height_m=3.0, walls=False, ceiling=False),
        start=StartPose((-2.0, 0.0), 0.0),
        objects=(SceneObject(kind="box", position_m=(0.0, 0.0, -0.005), size_m=(3.0, 2.0, 0.01), texture="carpet",
                             color=(0.3, 0.4, 0.6), surface="floor"),
                 SceneObject(kind="box", position_m=(-0.5, 0.2, -0.26), size_m=(0.5, 0.5, 0.5), texture="checker"),
                 SceneObject(kind="cylinder", position_m=(1.0, -0.5, -0.5), radius_m=0.2, height_m=1.0)))
    world = World(load_vehicle(), SitlConfig(), scenario, np.random.default_rng(4))
    try:
        start = world.start_p_ned_m
        poses = [(start + np.array([0.0, 0.0, -1.0]), Rz(math.radians(a))) for a in (0.0, 50.0, 180.0)]
        for i, r in enumerate(_compare(world, poses)):
            assert r["agree"] >= 0.97, (i, r)
            if r["both"] > 0.01:
                assert r["median"] <= 0.01 and r["p95"] <= 0.05, (i, r)
    finally:
        world.close()


def _pure_renderer(objects: tuple[SceneObject, ...]) -> RasterRenderer:
    scenario = ScenarioConfig(name="test", room=RoomConfig(size_m=(12.0, 12.0), height_m=4.0), objects=objects)
    scene = build_scene(scenario)
    return RasterRenderer(scene, scene_textures(scene, np.random.default_rng(0)))


def test_box_at_known_distance_reads_that_depth():
    """A 1 m box whose near face is 2.0 m north of the camera: exact depth, edges where the pinhole puts them."""
    r = _pure_renderer((SceneObject(kind="box", position_m=(2.5, 0.0, -1.5), size_m=(1.0, 1.0, 1.0),
                                    texture="checker"),))
    k = CameraIntrinsics.from_fov(320, 240, 58.0, 45.0)
    R_ned_c = np.array(FORWARD)
    rgb, z = r.render(np.array([0.0, 0.0, -1.5]), R_ned_c, k, NOISE.near_clip_m, NOISE.far_clip_m)
    assert rgb.shape == (240, 320, 3) and rgb.dtype == np.uint8 and z.dtype == np.float32
    face = z[int(k.cy - k.fy * 0.24):int(k.cy + k.fy * 0.24), int(k.cx - k.fx * 0.24):int(k.cx + k.fx * 0.24)]
    np.testing.assert_allclose(face, 2.0, atol=1e-4)
    row = z[120]
    edge = k.cx + k.fx * 0.25  # the face spans +-0.5 m at 2 m
    assert np.all(np.abs(row[int(k.cx):math.floor(edge)] - 2.0) < 1e-4)
    assert np.all(row[math.ceil(edge) + 1:] > 2.5)
    # the textured face has gradients for photometric odometry
    grey = rgb[100:140, 140:180].astype(float).mean(axis=2)
    assert np.abs(np.diff(grey, axis=1)).mean() > 2.0


def test_floor_depth_is_the_exact_ray_depth_also_when_it_passes_behind_the_camera():
    """Looking down 30 deg from 1.5 m: floor depth per pixel is h / (R r)_down; the floor extends behind."""
    r = _pure_renderer(())
    k = CameraIntrinsics.from_fov(320, 240, 58.0, 45.0)
    R_ned_c = _Ry(math.radians(-30.0)) @ np.array(FORWARD)  # pitched 30 deg down
    h = 1.5
    _, z = r.render(np.array([0.5, -0.3, -h]), R_ned_c, k, NOISE.near_clip_m, NOISE.far_clip_m)
    u, v = np.meshgrid(np.arange(k.width), np.arange(k.height))
    rays = np.stack([(u - k.cx) / k.fx, (v - k.cy) / k.fy, np.ones_like(u, dtype=float)], axis=-1)
    down = rays @ R_ned_c[2]  # NED down component of each ray (unit optical z)
    floor = (down > 0) & (h / np.maximum(down, 1e-9) < 4.0)  # hits the floor within 4.8 m: before any wall
    assert floor.mean() > 0.3
    np.testing.assert_allclose(z[floor], (h / down)[floor], rtol=2e-5, atol=2e-5)


@pytest.mark.parametrize("gap_m", [0.0005, 0.0019, 0.0031, 0.01])
def test_a_face_seen_nearly_edge_on_draws_no_phantom_near_the_camera(gap_m):
    """A demo's approach stopped 0.45 m from nothing (two of its misses re-rendered along their true paths): the
    camera passed 1.9-3.3 mm in front of the plane of one of the column's 32 sides, 2.8 m away. That side projects
    to a sliver under a pixel wide, but its corners came out crossed, cv2 filled a line of pixels with it, and its
    plane's depth there read 0.03-0.5 m: the structured-light model's shadow of so near a "surface" hid the floor
    behind, which the hidden-floor detector took for a dark object 0.7 m ahead. Every depth the renderer gives is
    a depth of the face that fills the pixel: nothing nearer than the nearest surface in view."""
    column = SceneObject(kind="cylinder", position_m=(0.0, 0.0, -1.5), radius_m=0.25, height_m=3.0, texture="noise")
    r = _pure_renderer((column,))
    k = CameraIntrinsics.from_fov(240, 320, 45.0, 58.0)   # the vehicle's portrait QVGA
    side = [f for f in range(len(r._normal)) if r._face_body[f] == 0 and abs(r._normal[f][2]) < 1e-6][5]
    n = r._normal[side]
    corners = r._verts[side, :r._n_verts[side]]
    centre = corners.mean(axis=0)
    along = np.cross(n, (0.0, 0.0, 1.0))           # horizontal, in the side's plane
    camera = centre + 2.8 * along + gap_m * n      # 2.8 m along the plane, just in front of it
    camera[2] = -1.14
    look = centre - camera
    yaw = math.atan2(look[1], look[0])
    R_ned_c = Rz(yaw) @ _Ry(math.radians(-30.0)) @ np.array(FORWARD)   # toward the column, 30 deg down
    _, z = r.render(camera, R_ned_c, k, NOISE.near_clip_m, NOISE.far_clip_m)
    nearest_m = math.hypot(*(camera[:2] - np.array(column.position_m[:2]))) - column.radius_m
    floor_m = 1.14 * 0.9      # the floor's nearest depth in view is farther than this (looking 30 deg down)
    assert float(z.min()) > min(nearest_m, floor_m) * 0.95, f"depth {z.min():.3f} m with nothing nearer than " \
        f"{min(nearest_m, floor_m):.2f} m"


def test_renderer_is_selected_in_the_config():
    assert SitlConfig().camera.renderer == "raster"
    assert load_sitl_config().camera.renderer == "raster"
    with pytest.raises(ConfigError, match="camera.renderer"):
        from quadlink.config import from_dict

        from_dict(SitlConfig, {"camera": {"renderer": "opengl"}})


def test_camera_mount_and_noise_model_are_shared_by_both_renderers():
    """Same mount pose and the same noise model: the noisy frames differ only by the noise-free render."""
    world = World(load_vehicle(), SitlConfig(), ScenarioConfig(
        name="t", room=RoomConfig(size_m=(12.0, 12.0), height_m=4.0),
        objects=(SceneObject(kind="box", position_m=(2.5, 0.0, -1.5), size_m=(1.0, 1.0, 1.0)),)),
        np.random.default_rng(0))
    try:
        world.reset_pose(np.array([0.0, 0.0, -1.5]), np.eye(3))
        mount = CameraConfig(R_qc=FORWARD, p_qc_m=(0.0, 0.0, 0.0))
        frames = [RgbdCamera(world, mount, NOISE, np.random.default_rng(7), renderer=r).render(world.state, 0, 0.0)
                  for r in ("pybullet", "raster")]
        patch = [f.depth_m[100:140, 140:180] for f in frames]
        assert np.all(patch[0] > 0) and np.all(patch[1] > 0)
        assert patch[1].mean() == pytest.approx(2.0, abs=0.003)
        assert patch[1].std() == pytest.approx(NOISE.depth_sigma_per_m2 * 4.0, rel=0.25)
        assert abs(patch[0].mean() - patch[1].mean()) < 0.003
    finally:
        world.close()


def test_more_than_255_faces_in_view_use_the_wide_id_buffer():
    """121 small cubes in a wall of cubes 2 m ahead show ~330 faces: ids no longer fit 8 bits."""
    cubes = tuple(SceneObject(kind="box", position_m=(2.0, y, z), size_m=(0.1, 0.1, 0.1))
                  for y in np.linspace(-1.0, 1.0, 11) for z in np.linspace(-2.5, -0.5, 11))
    r = _pure_renderer(cubes)
    k = CameraIntrinsics.from_fov(320, 240, 58.0, 45.0)
    p = np.array([0.0, 0.0, -1.5])
    _, z = r.render(p, np.array(FORWARD), k, NOISE.near_clip_m, NOISE.far_clip_m)
    seen = 0
    for c in cubes:
        d = np.array(c.position_m) - p  # NED; optical x = east, y = down, z = north
        u, v = k.cx + k.fx * d[1] / (d[0] - 0.05), k.cy + k.fy * d[2] / (d[0] - 0.05)
        if 0 <= u < k.width and 0 <= v < k.height:
            assert z[round(v), round(u)] == pytest.approx(1.95, abs=1e-4), c.position_m
            seen += 1
    assert seen > 50


def test_a_small_box_hides_a_long_one_whose_bounding_box_is_nearer():
    """Painter's order by separating planes: the long oblique box's bounding box is nearer the camera than
    the small cube's, but the cube stands in front of it on the optical axis."""
    cube = SceneObject(kind="box", name="cube", position_m=(2.0, 0.0, -0.5), size_m=(0.2, 0.2, 0.2))
    long = SceneObject(kind="box", name="long", position_m=(2.0, -0.85, -0.5), size_m=(3.05, 0.1, 1.0),
                       yaw_deg=math.degrees(math.atan2(2.3, 2.0)))
    r = _pure_renderer((cube, long))
    k = CameraIntrinsics.from_fov(320, 240, 58.0, 45.0)
    p = np.array([0.0, 0.0, -0.5])
    assert r.draw_order(p) == [1, 0]  # the long box (body 1) first
    _, z = r.render(p, np.array(FORWARD), k, NOISE.near_clip_m, NOISE.far_clip_m)
    centre = z[int(k.cy) - 3:int(k.cy) + 4, int(k.cx) - 3:int(k.cx) + 4]
    np.testing.assert_allclose(centre, 1.9, atol=1e-4)
    row = z[int(k.cy), int(k.cx) + 20:]
    assert np.any((row > 2.7) & (row < 3.1))  # the long box is seen behind the cube, east of it


@pytest.mark.parametrize("name", ["paper-arena", "office", "empty"])
def test_shipped_scenarios_suit_the_raster_renderer(name, caplog):
    """No interpenetrating bodies, none reaching outside the room (the renderer would warn)."""
    scene = build_scene(load_scenario(name))
    with caplog.at_level("WARNING", logger="sim_sitl.raster"):
        RasterRenderer(scene, scene_textures(scene, np.random.default_rng(0)))
    assert not caplog.records, [r.getMessage() for r in caplog.records]


# a column's side in the paper arena, 3.4 mm from its plane and 3.9 m away (0.251 px: just past EDGE_ON_PX), as the
# demo's camera saw it at 57.50 s of a flight whose odometry then ran away (velocity 1.3 m/s while hovering)
_SLIVER_CAMERA_P_NED_M = np.array([-3.407571692162428, -0.6611196352927037, -1.1207780219045467])
_SLIVER_CAMERA_R_NED_C = np.array([[-0.5239393187457168, -0.02940159644220988, 0.8512470255644362],
                                   [0.02488702301331451, -0.9995060992658958, -0.01920443111753165],
                                   [0.8513911995086685, 0.01112306409776811, 0.5244126467402864]])
_SLIVER_UV_PX = np.array([[-318.346972953696, -50.139859596632704], [-324.1277916973314, -51.207042751344716],
                          [87.28512283242355, 25.200455550460447], [86.16392615333112, 24.98854589110492]])


def test_a_sliver_whose_inset_edges_cross_is_not_drawn():
    """That side projects to a sliver under a pixel wide. Moved 0.4 px inward, its long edges crossed: one corner
    went 490 px along the sliver, the polygon came out a bow-tie with the sign of its area kept, and cv2 filled a
    black wedge 15 rows tall across the image. The keyframe that showed it biased every alignment after it: the
    odometry slid 10 cm in 6 frames. A 2 mm move of the camera changes a few pixels, not 3,600."""
    assert np.isnan(_inset(_SLIVER_UV_PX[None], EDGE_INSET_PX)).all()
    world = World(load_vehicle(), SitlConfig(), load_scenario("paper-arena"), np.random.default_rng(3))
    try:
        r = RasterRenderer(world.scene, world.scene_textures())
        k = RgbdCamera(world, load_vehicle().camera, NOISE, np.random.default_rng(1)).intrinsics
        rgb, _ = r.render(_SLIVER_CAMERA_P_NED_M, _SLIVER_CAMERA_R_NED_C, k, NOISE.near_clip_m, NOISE.far_clip_m)
        for dy_m in (-0.002, 0.002):
            moved, _ = r.render(_SLIVER_CAMERA_P_NED_M + np.array([0.0, dy_m, 0.0]), _SLIVER_CAMERA_R_NED_C, k,
                                NOISE.near_clip_m, NOISE.far_clip_m)
            changed = int((np.abs(rgb.astype(int) - moved.astype(int)).max(axis=2) > 40).sum())
            assert changed < 100, f"{changed} pixels change in a {dy_m * 1000:+.0f} mm move"
    finally:
        world.close()


def _convex_polygon(n: int, a_px: float, b_px: float, angle_rad: float, centre: tuple[float, float],
                    phases: list[float], clockwise: bool) -> np.ndarray:
    t = np.sort(np.asarray(phases[:n]) * 2.0 * math.pi)
    pts = np.stack([a_px * np.cos(t), b_px * np.sin(t)], axis=1)
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    pts = pts @ np.array([[c, s], [-s, c]]) + np.asarray(centre)
    return pts[::-1] if clockwise else pts


@settings(max_examples=400, deadline=None)
@given(n=st.integers(3, 8), a_px=st.floats(1.0, 900.0), b_px=st.floats(1e-3, 4.0),
       angle_rad=st.floats(0.0, math.pi), centre=st.tuples(st.floats(-400.0, 700.0), st.floats(-400.0, 700.0)),
       phases=st.lists(st.floats(0.0, 1.0), min_size=8, max_size=8, unique=True), clockwise=st.booleans())
def test_an_inset_polygon_stays_inside_its_face_or_vanishes(n, a_px, b_px, angle_rad, centre, phases, clockwise):
    """Any convex polygon (long thin slivers above all), moved EDGE_INSET_PX inward: either nothing (NaN) or a
    polygon whose every corner lies inside the original (each edge's half-plane), never one thrown outside it."""
    poly = _convex_polygon(n, a_px, b_px, angle_rad, centre, phases, clockwise)
    out = _inset(poly[None], EDGE_INSET_PX)[0]
    if np.isnan(out).any():
        return
    e = np.roll(poly, -1, axis=0) - poly
    orient = np.sign(np.sum(poly[:, 0] * np.roll(poly[:, 1], -1) - np.roll(poly[:, 0], -1) * poly[:, 1]))
    if orient == 0:
        return
    length = np.hypot(e[:, 0], e[:, 1])
    edges = length >= EDGE_MIN_PX   # a shorter edge is a repeated corner (phases 0 and 1): its half-plane is noise
    for q in out:   # inside every edge's half-plane (a tolerance of a millionth of a pixel per pixel of size)
        side = orient * (e[:, 0] * (q[1] - poly[:, 1]) - e[:, 1] * (q[0] - poly[:, 0]))
        assert (side[edges] >= -1e-6 * (a_px + 1.0) * length[edges]).all(), f"corner {q} outside {poly}"

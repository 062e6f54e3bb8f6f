"""The SITL's RGB-D camera: depth of known geometry, the mount, the noise model, the stream."""

from __future__ import annotations

import math
import socket
import time
from pathlib import Path

import numpy as np
import pybullet as p
import pytest
import yaml

from quadlink import CONFIG_DIR
from quadlink.camera import CameraIntrinsics, CameraStreamClient
from quadlink.frames import Rz
from quadlink.vehicle import CameraConfig, load_vehicle
from sim_sitl.camera_sim import RgbdCamera, depth_noise_model, incidence_cos
from sim_sitl.config import CameraNoiseConfig, RoomConfig, ScenarioConfig, SceneObject, SitlConfig, StartPose
from sim_sitl.runner import Sitl, SitlOptions
from sim_sitl.world import D, World

FORWARD = ((0.0, 0.0, 1.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0))  # optical z -> body x, x -> y, y -> z


def _world(objects: tuple[SceneObject, ...]) -> World:
    scenario = ScenarioConfig(name="test", room=RoomConfig(size_m=(12.0, 12.0), height_m=4.0),
                              start=StartPose((0.0, 0.0), 0.0), objects=objects)
    return World(load_vehicle(), SitlConfig(), scenario, np.random.default_rng(0))


@pytest.fixture
def box_world():
    # a 1 m box whose near face is 2.0 m ahead (north) of the vehicle at 1.5 m height
    w = _world((SceneObject(kind="box", position_m=(2.5, 0.0, -1.5), size_m=(1.0, 1.0, 1.0), texture="checker"),
                SceneObject(kind="box", position_m=(4.5, 3.0, -1.5), size_m=(1.0, 1.0, 1.0))))
    w.reset_pose(np.array([0.0, 0.0, -1.5]), np.eye(3))
    yield w
    w.close()


def test_box_at_known_distance_reads_that_depth_within_noise(box_world):
    mount = CameraConfig(R_qc=FORWARD, p_qc_m=(0.0, 0.0, 0.0))
    noise = CameraNoiseConfig()
    cam = RgbdCamera(box_world, mount, noise, np.random.default_rng(1))
    frame = cam.render(box_world.state, 0, 0.0)
    patch = frame.depth_m[100:140, 140:180]
    sigma = noise.depth_sigma_per_m2 * 2.0 ** 2
    assert np.all(patch > 0)
    assert patch.mean() == pytest.approx(2.0, abs=4 * sigma / math.sqrt(patch.size) + 0.002)
    assert patch.std() == pytest.approx(sigma, rel=0.25)
    # the textured face has gradients for photometric odometry
    grey = frame.rgb[100:140, 140:180].astype(float).mean(axis=2)
    assert np.abs(np.diff(grey, axis=1)).mean() > 2.0
    # the box's right edge: the face spans +-0.5 m at 2 m -> columns cx +- fx * 0.25
    k = frame.intrinsics
    row = frame.depth_m[120]
    edge = k.cx + k.fx * 0.25
    assert np.all(row[int(edge) + 3:int(edge) + 20] != pytest.approx(2.0, abs=0.1))
    assert np.all(np.abs(row[int(k.cx):int(edge) - 3] - 2.0) < 0.1)


def test_out_of_range_depth_is_invalid(box_world):
    mount = CameraConfig(R_qc=FORWARD, p_qc_m=(0.0, 0.0, 0.0))
    cam = RgbdCamera(box_world, mount, CameraNoiseConfig(), np.random.default_rng(1))
    box_world.reset_pose(np.array([0.0, 0.0, -1.5]), Rz(math.radians(180)))  # facing the south wall, 6 m away
    frame = cam.render(box_world.state, 0, 0.0)
    assert np.all(frame.depth_m[100:140, 140:180] == 0.0)
    box_world.reset_pose(np.array([1.7, 0.0, -1.5]), np.eye(3))  # 0.3 m from the box: below min range
    frame = cam.render(box_world.state, 0, 0.0)
    assert np.all(frame.depth_m[100:140, 140:180] == 0.0)


@pytest.mark.parametrize("renderer", ["raster", "pybullet"])
def test_default_portrait_mount_matches_ray_casts(box_world, renderer):
    """Every valid pixel of the noise-free depth agrees with a pybullet ray cast through that pixel."""
    vehicle = load_vehicle()
    cam = RgbdCamera(box_world, vehicle.camera, CameraNoiseConfig(), np.random.default_rng(1), renderer=renderer)
    box_world.reset_pose(np.array([1.0, -1.0, -1.2]), Rz(math.radians(-10)))
    _, z = cam.render_raw(box_world.state)
    p_ned, R_ned_c = cam.pose_ned(box_world.state)
    k = cam.intrinsics
    rng = np.random.default_rng(5)
    pix = [(int(rng.integers(0, k.height)), int(rng.integers(0, k.width))) for _ in range(60)]
    starts, ends = [], []
    for v, u in pix:
        ray = np.array([(u - k.cx) / k.fx, (v - k.cy) / k.fy, 1.0])
        starts.append((D @ p_ned).tolist())
        ends.append((D @ (p_ned + 30.0 * (R_ned_c @ ray))).tolist())
    hits = p.rayTestBatch(starts, ends, physicsClientId=box_world.client)
    checked = 0
    for (v, u), hit in zip(pix, hits, strict=True):
        if hit[0] < 0:
            continue
        depth_expected = 30.0 * hit[2]  # ray has unit optical z, so distance along it scales z
        if depth_expected > 15.0:
            continue
        assert z[v, u] == pytest.approx(depth_expected, abs=0.003 + 0.001 * depth_expected), (v, u)
        checked += 1
    assert checked > 40
    # mount: 45 deg right, 30 deg down -> the optical axis points south-east... of the body: check its elevation
    axis = R_ned_c @ np.array([0.0, 0.0, 1.0])
    assert math.degrees(math.asin(axis[2])) == pytest.approx(30.0, abs=0.5)


def test_incidence_cos_of_analytic_planes():
    k = CameraIntrinsics.from_fov(320, 240, 58.0, 45.0)
    flat = np.full((240, 320), 2.0, np.float32)
    c = incidence_cos(flat, k)
    assert c[120, 160] == pytest.approx(1.0, abs=1e-4)
    u = ((np.arange(320) - k.cx) / k.fx)[None, :]
    for deg in (30.0, 60.0, 80.0):
        th = math.radians(deg)
        plane = np.broadcast_to(2.0 / (u * math.sin(th) + math.cos(th)), (240, 320)).astype(np.float32)
        assert incidence_cos(plane, k)[120, 160] == pytest.approx(math.cos(th), abs=0.01)
    cfg = CameraNoiseConfig(max_incidence_deg=75.0)
    th = math.radians(80.0)
    grazing = np.broadcast_to(2.0 / (u * math.sin(th) + math.cos(th)), (240, 320)).astype(np.float32)
    out = depth_noise_model(grazing, k, cfg, 0.5, 3.5, np.random.default_rng(0))
    assert out[120, 160] == 0.0


def test_depth_noise_grows_with_square_of_distance():
    k = CameraIntrinsics.from_fov(320, 240, 58.0, 45.0)
    cfg = CameraNoiseConfig(depth_quantum_m=0.0)
    rng = np.random.default_rng(3)
    s1 = (depth_noise_model(np.full((240, 320), 1.0, np.float32), k, cfg, 0.5, 3.5, rng) - 1.0).std()
    s3 = (depth_noise_model(np.full((240, 320), 3.0, np.float32), k, cfg, 0.5, 3.5, rng) - 3.0).std()
    assert s1 == pytest.approx(cfg.depth_sigma_per_m2, rel=0.05)
    assert s3 / s1 == pytest.approx(9.0, rel=0.05)


@pytest.mark.sitl
def test_camera_stream_in_lockstep_carries_sim_time_and_no_mount():
    opts = SitlOptions(config=SitlConfig(scenario="paper-arena"), port1=0, port2=0, camera_port=0, camera=True,
                       truth_url=None, lockstep=True, progress_every_s=60.0)
    sitl = Sitl(opts).start()
    client = CameraStreamClient(f"tcp://127.0.0.1:{sitl.camera_server.port}")
    try:
        frames = []
        deadline = time.monotonic() + 30
        while len(frames) < 6 and time.monotonic() < deadline:
            f = client.read(timeout_s=3.0)
            if f is None:
                continue
            frames.append(f)
            if len(frames) == 3:
                time.sleep(0.5)  # a slow consumer: lock-step must wait for our ack
            client.ack(f.seq)
        time.sleep(0.3)
        assert len(frames) == 6
        stamps = np.array([f.stamp_s for f in frames])
        np.testing.assert_allclose(np.diff(stamps), 1.0 / 30.0, atol=0.0021)  # board ticks are 2 ms
        assert [f.seq for f in frames] == list(range(frames[0].seq, frames[0].seq + 6))
        f = frames[-1]
        assert f.rgb.shape == (240, 320, 3) and f.depth_m.shape == (240, 320)
        np.testing.assert_array_equal(f.R_qc, np.eye(3))   # a sensor record has no mount (issue 29)
        assert f.intrinsics.fx == pytest.approx(160.0 / math.tan(math.radians(29.0)))
        assert f.rgb.astype(float).std() > 5.0  # textured
        # lock-step: sim time cannot have run past the next frame that nobody has acknowledged yet
        assert sitl.sim.t_s <= stamps[-1] + 2.0 / 30.0 + 0.011
        assert sitl.stats.camera_ack_timeouts == 0
    finally:
        client.close()
        sitl.stop()


def _free_udp_port() -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    s.settimeout(0.5)
    return s


def _turned_mount_vehicle(tmp_path: Path, yaw_deg: float) -> tuple[Path, np.ndarray]:
    """The nominal vehicle with its camera turned ``yaw_deg`` about the body's down axis (the SITL's truth)."""
    data = yaml.safe_load((CONFIG_DIR / "vehicle.yaml").read_text())
    R_true = Rz(math.radians(yaw_deg)) @ np.asarray(data["camera"]["R_qc"], dtype=float)
    data["camera"]["R_qc"] = R_true.tolist()
    path = tmp_path / "vehicle.yaml"
    path.write_text(yaml.safe_dump(data))
    return path, R_true


@pytest.mark.sitl
def test_the_companion_places_the_sitl_camera_with_its_own_calibration(tmp_path: Path) -> None:
    """Issue 29: the SITL's camera sits 3 deg off the nominal mount; the companion's camera source (the one its
    pipeline and reference law read) places every frame with the configured mount, never the simulator's."""
    from companion.cameras import open_camera

    vehicle_path, R_true = _turned_mount_vehicle(tmp_path, 3.0)
    nominal = load_vehicle()
    opts = SitlOptions(config=SitlConfig(scenario="paper-arena", vehicle=str(vehicle_path)), port1=0, port2=0,
                       camera_port=0, camera=True, truth_url=None, progress_every_s=60.0)
    sitl = Sitl(opts).start()
    camera = open_camera(f"tcp://127.0.0.1:{sitl.camera_server.port}", R_qc=nominal.camera.R_qc_matrix,
                         p_qc_m=nominal.camera.p_qc)
    try:
        np.testing.assert_allclose(sitl.camera.R_qc, R_true, atol=1e-9)   # the SITL renders through the turned mount
        frame = None
        deadline = time.monotonic() + 20
        while frame is None and time.monotonic() < deadline:
            frame = camera.read(1.0)
        assert frame is not None
        np.testing.assert_allclose(frame.R_qc, nominal.camera.R_qc_matrix, atol=1e-12)
        np.testing.assert_allclose(frame.p_qc_m, nominal.camera.p_qc, atol=1e-12)
        turned_deg = math.degrees(math.acos(np.clip((np.trace(frame.R_qc.T @ R_true) - 1) / 2, -1, 1)))
        assert turned_deg == pytest.approx(3.0, abs=0.01)   # the nominal matrix is written to 6 decimals
    finally:
        camera.close()
        sitl.stop()

"""Operator view: compensation geometry (section VI-B), rendering (decay, obstacle points), web server."""

from __future__ import annotations

import json
import math
import urllib.request

import cv2
import numpy as np
import pytest

from quadlink.camera import CameraIntrinsics
from quadlink.frames import R_hq, Rz
from quadlink.vehicle import load_vehicle
from teleop.view.compensation import (
    R_vc,
    image_centre_on_screen,
    project,
    screen_intrinsics,
    virtual_camera_R_hv,
)
from teleop.view.render import OperatorViewRenderer, Overlay
from teleop.view.server import ViewHub, ViewServer

# optical (x right, y down, z forward) -> FRD for a forward-looking landscape camera
R_QC_FORWARD = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
CAM = CameraIntrinsics.from_fov(320, 240, 58.0, 45.0)
SCREEN = screen_intrinsics(CAM, 560, 420)


@pytest.mark.parametrize("psi_s_deg", [-25.0, -5.0, 0.0, 10.0, 30.0])
def test_forward_camera_shift_is_k_px_psi(psi_s_deg):
    """For a forward-looking camera the compensation is the paper's p_x = k_px psi_s (k_px = f_x, tan for large)."""
    psi = math.radians(psi_s_deg)
    c = image_centre_on_screen(CAM, SCREEN, R_vc(R_QC_FORWARD, 0.0, 0.0, psi))
    assert c[0] - SCREEN.cx == pytest.approx(CAM.fx * math.tan(psi), abs=1e-6)
    assert c[1] - SCREEN.cy == pytest.approx(0.0, abs=1e-6)
    if abs(psi_s_deg) <= 5:
        assert c[0] - SCREEN.cx == pytest.approx(CAM.fx * psi, rel=0.01)


def test_centre_of_oscillation_stays_at_screen_centre_for_the_mk_camera(rng):
    """The tilted portrait camera of the MK-Quadro: whatever the attitude and yaw displacement, the direction
    of the centre of oscillation lands at the screen centre when psi_s, roll and pitch are compensated."""
    R_qc = load_vehicle().camera.R_qc_matrix
    d_h = R_qc[:, 2]                     # camera axis at the centre of oscillation, level body
    for _ in range(50):
        roll, pitch, psi = rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3), rng.uniform(-0.6, 0.6)
        R_h_c = Rz(psi) @ R_hq(roll, pitch) @ R_qc          # actual camera in the centre-of-oscillation frame
        d_c = R_h_c.T @ d_h                                 # what the real camera sees
        uv = project(d_c[None, :] * 2.0, R_vc(R_qc, roll, pitch, psi), SCREEN)[0]
        np.testing.assert_allclose(uv, [SCREEN.cx, SCREEN.cy], atol=1e-3)   # R_qc has 6 decimals in YAML


def test_portrait_camera_is_shown_upright():
    R_qc = load_vehicle().camera.R_qc_matrix
    R_hv = virtual_camera_R_hv(R_qc)
    np.testing.assert_allclose(R_hv.T @ R_hv, np.eye(3), atol=1e-12)
    assert np.linalg.det(R_hv) == pytest.approx(1.0)
    assert abs(R_hv[2, 0]) < 1e-12        # screen x is horizontal
    assert R_hv[2, 1] > 0.5               # screen y points (mostly) down
    # a point below the optical axis in the world appears lower on the screen
    below = R_qc[:, 2] + np.array([0.0, 0.0, 0.2])
    p_c = R_qc.T @ below
    uv = project(p_c[None, :], R_vc(R_qc, 0.0, 0.0, 0.0), SCREEN)[0]
    assert uv[1] > SCREEN.cy + 10


def test_points_behind_are_not_projected():
    uv = project(np.array([[0.0, 0.0, -1.0], [0.1, 0.0, 1.0]]), np.eye(3), SCREEN)
    assert np.all(np.isnan(uv[0])) and np.all(np.isfinite(uv[1]))


def test_renderer_draws_image_points_and_decays_background():
    renderer = OperatorViewRenderer(560, 420, decay_time_s=0.5)
    rgb = np.full((240, 320, 3), 200, np.uint8)
    ov = Overlay(obstacle_points_c_m=((0.0, 0.0, 0.6),), obstacle_warning_m=1.0)   # near: red
    img = renderer.render(rgb, CAM, R_QC_FORWARD, 0.0, 0.0, 0.0, 10.0, ov)
    assert img.shape == (420, 560, 3)
    cx, cy = 280, 210
    b, g, r = img[cy + 30, cx].astype(int)     # below the marker, on the image: grey 200
    assert abs(b - 200) <= 2 and abs(r - 200) <= 2
    # the obstacle point straight ahead: a red disc at the centre (the yellow cross is over the centre row/column)
    b, g, r = img[cy + 3, cx + 3].astype(int)
    assert r > 200 and g < 60 and b < 60
    # shifted by the pan-scan estimate: the image centre moves by f_x tan(psi)
    renderer.render(rgb, CAM, R_QC_FORWARD, 0.0, 0.0, 0.2, 10.1, Overlay())
    assert renderer.last_shift_px[0] == pytest.approx(CAM.fx * math.tan(0.2), abs=1e-6)
    # no new image for one decay time: the background fades by e^-1 (outside the last image's border lines)
    renderer2 = OperatorViewRenderer(560, 420, decay_time_s=0.5)
    renderer2.render(rgb, CAM, R_QC_FORWARD, 0.0, 0.0, 0.0, 0.0, Overlay())
    faded = renderer2.render(None, None, np.eye(3), 0.0, 0.0, 0.0, 0.5, Overlay())
    assert int(faded[cy + 40, cx + 40, 1]) == pytest.approx(200 * math.exp(-1.0), abs=2)


def test_web_server_endpoints():
    hub = ViewHub()
    server = ViewServer(hub, "127.0.0.1", 0)
    try:
        with pytest.raises(urllib.error.HTTPError):
            urllib.request.urlopen(server.url + "frame.jpg", timeout=5)
        ok, buf = cv2.imencode(".jpg", np.zeros((20, 30, 3), np.uint8))
        hub.publish(buf.tobytes())
        hub.set_status({"link": "ok", "warnings": ["x"]})
        page = urllib.request.urlopen(server.url, timeout=5).read().decode()
        assert "/frame.jpg" in page and "/status.json" in page
        jpeg = urllib.request.urlopen(server.url + "frame.jpg?t=1", timeout=5).read()
        assert cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR).shape == (20, 30, 3)
        status = json.loads(urllib.request.urlopen(server.url + "status.json", timeout=5).read())
        assert status == {"link": "ok", "warnings": ["x"]}
        with urllib.request.urlopen(server.url + "stream.mjpg", timeout=5) as resp:
            assert resp.headers["Content-Type"].startswith("multipart/x-mixed-replace")
            head = resp.read(200)
            assert head.startswith(b"--frame\r\nContent-Type: image/jpeg")
    finally:
        server.close()

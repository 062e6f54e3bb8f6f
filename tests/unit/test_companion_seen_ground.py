"""companion.seen_ground on its own: which ground the camera has looked at (issue 29)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.seen_ground import SeenGround, SeenGroundParams
from quadlink.camera_frame import CameraIntrinsics

pytestmark = pytest.mark.unit

K = CameraIntrinsics.from_fov(320, 240, 58.0, 45.0)
DOWN_RAD = math.radians(30.0)


def _mount(down_rad: float = DOWN_RAD) -> np.ndarray:
    """Camera (x right, y down, z forward) -> body (FRD), the optical axis ``down_rad`` below the nose."""
    z_c = np.array([math.cos(down_rad), 0.0, math.sin(down_rad)])
    x_c = np.array([0.0, 1.0, 0.0])
    return np.column_stack([x_c, np.cross(z_c, x_c), z_c])


def _floor_depth(height_m: float, R_qc: np.ndarray, max_range_m: float = 4.0) -> np.ndarray:
    """The depth image of a level floor ``height_m`` under the (level) body, 0 beyond ``max_range_m``."""
    v, u = np.mgrid[0:K.height, 0:K.width]
    rays = np.stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones(u.shape)], axis=-1) @ R_qc.T
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(rays[..., 2] > 1e-6, height_m / rays[..., 2], 0.0)
    rng = t * np.linalg.norm(rays, axis=-1)
    return np.where((t > 0) & (rng <= max_range_m), t, 0.0).astype(np.float32)


def test_a_camera_looking_ahead_and_down_sees_the_floor_ahead_never_under_the_vehicle() -> None:
    g = SeenGround()
    R = _mount()
    g.observe(_floor_depth(1.4, R), K, R, np.zeros(3), 0.0, 0.0, 0.0, np.zeros(3))
    assert g.unseen_fraction([0.0, 0.0, -1.4], 0.4) == pytest.approx(1.0)   # under the vehicle: not seen
    assert g.unseen_fraction([2.0, 0.0, -1.4], 0.4) == pytest.approx(0.0)   # 2 m ahead: seen
    assert g.unseen_fraction([0.0, 2.0, -1.4], 0.4) == pytest.approx(1.0)   # 2 m to the right: outside the view
    assert g.unseen_fraction([-2.0, 0.0, -1.4], 0.4) == pytest.approx(1.0)  # behind
    # turned right (yaw 90 deg), the camera sees to the world's east
    g.observe(_floor_depth(1.4, R), K, R, np.zeros(3), 0.0, 0.0, math.pi / 2, np.zeros(3))
    assert g.unseen_fraction([0.0, 2.0, -1.4], 0.4) == pytest.approx(0.0)
    # a tilt is taken into account: pitched 10 deg nose up, the floor in the image is further away
    g2 = SeenGround()
    R_up = _mount(DOWN_RAD - math.radians(10.0))     # what the camera sees with the body pitched up 10 deg
    g2.observe(_floor_depth(1.4, R_up), K, R, np.zeros(3), 0.0, math.radians(10.0), 0.0, np.zeros(3))
    assert g2.unseen_fraction([2.0, 0.0, -1.4], 0.4) == pytest.approx(0.0)
    assert g2.unseen_fraction([1.1, 0.0, -1.4], 0.2) == pytest.approx(1.0)


def test_the_take_off_spot_and_bad_input() -> None:
    g = SeenGround(SeenGroundParams(takeoff_radius_m=0.6))
    g.mark_disc([0.3, -0.2, 0.0], 0.6)
    assert g.unseen_fraction([0.3, -0.2, -1.0], 0.4) == 0.0
    assert g.unseen_fraction([1.3, -0.2, -1.0], 0.4) == 1.0
    assert g.unseen_fraction(None, 0.4) is None
    assert g.unseen_fraction([math.nan, 0.0, 0.0], 0.4) is None
    n = len(g)
    g.observe(None, K, _mount(), np.zeros(3), 0.0, 0.0, 0.0, np.zeros(3))              # no depth
    g.observe(np.zeros((240, 320), np.float32), K, _mount(), np.zeros(3), 0.0, 0.0, 0.0, np.zeros(3))  # all invalid
    g.observe(_floor_depth(1.4, _mount()), K, _mount(), np.zeros(3), math.nan, 0.0, 0.0, np.zeros(3))  # bad attitude
    assert len(g) == n
    g.clear()
    assert len(g) == 0 and g.unseen_fraction([0.3, -0.2, 0.0], 0.4) == 1.0
    with pytest.raises(ValueError):
        SeenGroundParams(max_unseen_fraction=1.0)


def test_the_unseen_ground_as_points_in_h_leads_the_way_to_seen_ground() -> None:
    """Heading east (yaw 90 deg) with the ground seen only to the north (world +x): in H the seen ground is to the
    left (H -y), and no unseen point lies there."""
    g = SeenGround()
    g.mark_disc([1.5, 0.0, 0.0], 0.8)                # seen: a disc 1.5 m north of the vehicle
    pts = g.unseen_points_h([0.0, 0.0, -1.4], math.pi / 2, 2.0, 1.1)
    assert pts.shape[1] == 3 and np.all(pts[:, 2] == 1.1)
    assert np.all(np.hypot(pts[:, 0], pts[:, 1]) <= 2.0 + 1e-9)
    near_seen = np.hypot(pts[:, 0] - 0.0, pts[:, 1] + 1.5) < 0.6
    assert not near_seen.any()
    assert (np.hypot(pts[:, 0], pts[:, 1] - 1.5) < 0.6).sum() > 50     # the unseen side (H +y, world south)

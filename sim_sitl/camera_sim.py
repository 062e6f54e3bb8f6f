"""The RGB-D camera: pybullet's CPU renderer through the mount of ``VehicleConfig.camera``.

Pure helpers (projection from intrinsics, view matrix, depth linearisation, the depth noise model)
are separate from :class:`RgbdCamera`, which renders with ``ER_TINY_RENDERER`` in the world's client.
Depth is the z coordinate in the optical frame (as structured-light sensors report), with noise
sigma = k z^2, quantised, and 0 (invalid) outside [min_range, max_range] and where the surface is
seen at a grazing angle (incidence beyond ``max_incidence_deg``, which also blanks depth edges).
"""

from __future__ import annotations

import math

import numpy as np
import pybullet as p
from numpy.typing import NDArray

from quadlink.camera import CameraIntrinsics, RgbdFrame
from quadlink.vehicle import CameraConfig
from sim_sitl.config import CameraNoiseConfig
from sim_sitl.world import D, RigidState, World

R_OPTICAL_GL = np.diag([1.0, -1.0, -1.0])  # optical (x right, y down, z fwd) -> OpenGL camera (y up, z back)


def projection_matrix_gl(k: CameraIntrinsics, near_m: float, far_m: float) -> list[float]:
    """OpenGL projection (column-major, 16 floats) that reproduces the pinhole ``k`` exactly."""
    W, H = k.width, k.height
    P = np.zeros((4, 4))
    P[0, 0] = 2.0 * k.fx / W
    P[0, 2] = 1.0 - (2.0 * k.cx + 1.0) / W
    P[1, 1] = 2.0 * k.fy / H
    P[1, 2] = -(1.0 - (2.0 * k.cy + 1.0) / H)
    P[2, 2] = -(far_m + near_m) / (far_m - near_m)
    P[2, 3] = -2.0 * far_m * near_m / (far_m - near_m)
    P[3, 2] = -1.0
    return P.T.flatten().tolist()


def view_matrix_gl(R_pb_c: NDArray[np.float64], t_pb_m: NDArray[np.float64]) -> list[float]:
    """World (pybullet) -> OpenGL camera view matrix, column-major; ``R_pb_c`` maps optical -> world."""
    R = np.asarray(R_pb_c) @ R_OPTICAL_GL
    V = np.eye(4)
    V[:3, :3] = R.T
    V[:3, 3] = -R.T @ np.asarray(t_pb_m)
    return V.T.flatten().tolist()


def linearize_depth(buffer: NDArray[np.float64], near_m: float, far_m: float) -> NDArray[np.float32]:
    """OpenGL depth buffer [0, 1] -> optical-axis depth z in metres."""
    return (far_m * near_m / (far_m - (far_m - near_m) * np.asarray(buffer, dtype=np.float64))).astype(np.float32)


def incidence_cos(z_m: NDArray[np.float32], k: CameraIntrinsics) -> NDArray[np.float64]:
    """|cos| of the angle between the viewing ray and the surface normal (normals from depth gradients)."""
    H, W = z_m.shape
    u = (np.arange(W) - k.cx) / k.fx
    v = (np.arange(H) - k.cy) / k.fy
    X = z_m * u[None, :]
    Y = z_m * v[:, None]
    Z = z_m.astype(np.float64)
    dXu, dYu, dZu = np.gradient(X, axis=1), np.gradient(Y, axis=1), np.gradient(Z, axis=1)
    dXv, dYv, dZv = np.gradient(X, axis=0), np.gradient(Y, axis=0), np.gradient(Z, axis=0)
    nx = dYu * dZv - dZu * dYv
    ny = dZu * dXv - dXu * dZv
    nz = dXu * dYv - dYu * dXv
    n_norm = np.sqrt(nx * nx + ny * ny + nz * nz) + 1e-12
    r_norm = np.sqrt(u[None, :] ** 2 + v[:, None] ** 2 + 1.0)
    dot = nx * u[None, :] + ny * v[:, None] + nz
    return np.abs(dot) / (n_norm * r_norm)


def depth_noise_model(z_m: NDArray[np.float32], k: CameraIntrinsics, cfg: CameraNoiseConfig, min_range_m: float,
                      max_range_m: float, rng: np.random.Generator) -> NDArray[np.float32]:
    """Noisy, quantised depth with 0 for invalid pixels (see module doc)."""
    z = z_m.astype(np.float64)
    noisy = z + cfg.depth_sigma_per_m2 * z * z * rng.standard_normal(z.shape)
    if cfg.depth_quantum_m > 0:
        noisy = np.round(noisy / cfg.depth_quantum_m) * cfg.depth_quantum_m
    valid = (z >= min_range_m) & (z <= max_range_m)
    valid &= incidence_cos(z_m, k) >= math.cos(math.radians(cfg.max_incidence_deg))
    return np.where(valid, noisy, 0.0).astype(np.float32)


class RgbdCamera:
    def __init__(self, world: World, mount: CameraConfig, noise: CameraNoiseConfig, rng: np.random.Generator,
                 width_px: int | None = None, height_px: int | None = None) -> None:
        self.world = world
        self.mount = mount
        self.noise = noise
        self.rng = rng
        w = width_px or mount.width_px
        h = height_px or mount.height_px
        self.intrinsics = CameraIntrinsics.from_fov(w, h, mount.hfov_deg, mount.vfov_deg)
        self._proj = projection_matrix_gl(self.intrinsics, noise.near_clip_m, noise.far_clip_m)
        self.R_qc = mount.R_qc_matrix
        self.p_qc_m = mount.p_qc

    def pose_ned(self, state: RigidState) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Camera position (arena NED) and R_ned_c (optical -> NED)."""
        return state.p_ned_m + state.R_ned_q @ self.p_qc_m, state.R_ned_q @ self.R_qc

    def render_raw(self, state: RigidState) -> tuple[NDArray[np.uint8], NDArray[np.float32]]:
        """Noise-free colour (H x W x 3) and optical-axis depth (m)."""
        p_ned, R_ned_c = self.pose_ned(state)
        view = view_matrix_gl(D @ R_ned_c, D @ p_ned)
        k = self.intrinsics
        _, _, rgba, depth_buf, _ = p.getCameraImage(
            k.width, k.height, view, self._proj, renderer=p.ER_TINY_RENDERER, shadow=0,
            lightDirection=[0.3, 0.2, 1.0], flags=p.ER_NO_SEGMENTATION_MASK, physicsClientId=self.world.client)
        rgb = np.asarray(rgba, dtype=np.uint8).reshape(k.height, k.width, 4)[:, :, :3]
        depth = linearize_depth(np.asarray(depth_buf).reshape(k.height, k.width), self.noise.near_clip_m,
                                self.noise.far_clip_m)
        return rgb, depth

    def render(self, state: RigidState, seq: int, stamp_s: float) -> RgbdFrame:
        rgb, z = self.render_raw(state)
        depth = depth_noise_model(z, self.intrinsics, self.noise, self.mount.min_range_m, self.mount.max_range_m,
                                  self.rng)
        if self.noise.rgb_noise_levels > 0:
            noisy = rgb.astype(np.float32) + self.noise.rgb_noise_levels * self.rng.standard_normal(rgb.shape,
                                                                                                   dtype=np.float32)
            rgb = np.clip(noisy, 0, 255).astype(np.uint8)
        return RgbdFrame(seq=seq, stamp_s=stamp_s, rgb=rgb, depth_m=depth, intrinsics=self.intrinsics,
                         R_qc=self.R_qc, p_qc_m=self.p_qc_m, meta={"source": "sitl", "clock": "sim"})

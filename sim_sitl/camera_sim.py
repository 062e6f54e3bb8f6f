"""The RGB-D camera through the mount of ``VehicleConfig.camera``: noise-free render, then the noise model.

Pure helpers (projection from intrinsics, view matrix, depth linearisation, the depth noise model)
are separate from :class:`RgbdCamera`, which renders with one of two renderers (``renderer``):
``raster`` (``raster.py``: pure numpy/OpenCV, ~10x faster) or ``pybullet`` (``ER_TINY_RENDERER`` in the
world's client). Both give the same geometry; only the noise-free render differs between them.
Depth is the z coordinate in the optical frame (as structured-light sensors report), with noise
sigma = k z^2, quantised, and 0 (invalid) outside [min_range, max_range] and where the surface is
seen at a grazing angle (incidence beyond ``max_incidence_deg``, which also blanks depth edges).
That is the ``basic`` model (``CameraNoiseConfig.model``); ``xtion`` (``xtion.py``) fails as the real sensor
does: disparity noise and steps, IR shadows, no return from dark/specular surfaces, frame drops
(:meth:`RgbdCamera.capture` gives None), stamp jitter and motion blur. Glass is never rendered (both models).
"""

from __future__ import annotations

import math

import numpy as np
import pybullet as p
from numpy.typing import NDArray

from quadlink.camera import CameraIntrinsics, RgbdFrame
from quadlink.vehicle import CameraConfig
from sim_sitl.config import CameraNoiseConfig, RendererName
from sim_sitl.raster import RasterRenderer
from sim_sitl.scene import MATERIAL_CODE
from sim_sitl.world import D, RigidState, World
from sim_sitl.xtion import (
    camera_velocity,
    draw_frame_dropped,
    draw_stamp_error_s,
    image_motion_px,
    max_motion_bound_px,
    motion_blur,
    xtion_depth,
)

R_OPTICAL_GL = np.diag([1.0, -1.0, -1.0])  # optical (x right, y down, z fwd) -> OpenGL camera (y up, z back)


def projection_matrix_gl(k: CameraIntrinsics, near_m: float, far_m: float) -> list[float]:
    """OpenGL projection (column-major, 16 floats) that reproduces the pinhole ``k`` exactly.

    Pixel (u, v) of the rendered image is the ray ((u - cx)/fx, (v - cy)/fy, 1), as for the real sensor;
    ``test_default_portrait_mount_matches_ray_casts`` checks it against pybullet ray casts.
    """
    W, H = k.width, k.height
    P = np.zeros((4, 4))
    P[0, 0] = 2.0 * k.fx / W
    P[0, 2] = 1.0 - 2.0 * k.cx / W  # the tiny renderer samples columns at their left edge (checked by ray casts)
    P[1, 1] = 2.0 * k.fy / H
    P[1, 2] = -(1.0 - (2.0 * k.cy + 2.0) / H)  # and rows half a pixel below their centre
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


def incidence_cos(z_m: NDArray[np.float32], k: CameraIntrinsics) -> NDArray[np.float32]:
    """|cos| of the angle between the viewing ray and the surface normal, from the depth map alone.

    With P = z r, r = ((x - cx)/fx, (y - cy)/fy, 1), the tangents P_x, P_y give the normal
    n ~ (-a, -b, a u + b v + z) with a = fx dz/dx, b = fy dz/dy (per pixel), and n . r = z, so
    cos = z / (|n| |r|). Central differences; depth edges come out grazing (invalid), as on the sensor.
    """
    z = np.asarray(z_m, dtype=np.float32)
    H, W = z.shape
    u = ((np.arange(W, dtype=np.float32) - k.cx) / k.fx)[None, :]
    v = ((np.arange(H, dtype=np.float32) - k.cy) / k.fy)[:, None]
    dz_x = np.empty_like(z)
    dz_x[:, 1:-1] = (z[:, 2:] - z[:, :-2]) * 0.5
    dz_x[:, 0] = z[:, 1] - z[:, 0]
    dz_x[:, -1] = z[:, -1] - z[:, -2]
    dz_y = np.empty_like(z)
    dz_y[1:-1] = (z[2:] - z[:-2]) * 0.5
    dz_y[0] = z[1] - z[0]
    dz_y[-1] = z[-1] - z[-2]
    a = np.float32(k.fx) * dz_x
    b = np.float32(k.fy) * dz_y
    c = a * u + b * v + z
    n2 = a * a + b * b + c * c
    r2 = u * u + v * v + np.float32(1.0)
    return z / np.sqrt(n2 * r2 + np.float32(1e-12))


class NoiseBank:
    """Standard normal noise for whole images at a fraction of the cost: a pre-drawn field twice the
    image size, read at a random offset each frame (consecutive frames are uncorrelated in practice)."""

    def __init__(self, rng: np.random.Generator, shape: tuple[int, ...]) -> None:
        self.rng = rng
        self.shape = shape
        big = (2 * shape[0], 2 * shape[1], *shape[2:])
        self.field = rng.standard_normal(big, dtype=np.float32)

    def draw(self) -> NDArray[np.float32]:
        i = int(self.rng.integers(0, self.shape[0]))
        j = int(self.rng.integers(0, self.shape[1]))
        return self.field[i:i + self.shape[0], j:j + self.shape[1]]


def depth_noise_model(z_m: NDArray[np.float32], k: CameraIntrinsics, cfg: CameraNoiseConfig, min_range_m: float,
                      max_range_m: float, rng: np.random.Generator,
                      noise: NDArray[np.float32] | None = None) -> NDArray[np.float32]:
    """Noisy, quantised depth with 0 for invalid pixels (see module doc); ``noise``: N(0, 1) per pixel."""
    z = np.asarray(z_m, dtype=np.float32)
    if noise is None:
        noise = rng.standard_normal(z.shape, dtype=np.float32)
    noisy = z + np.float32(cfg.depth_sigma_per_m2) * z * z * noise
    if cfg.depth_quantum_m > 0:
        q = np.float32(cfg.depth_quantum_m)
        noisy = np.round(noisy / q) * q
    valid = (z >= min_range_m) & (z <= max_range_m)
    valid &= incidence_cos(z_m, k) >= math.cos(math.radians(cfg.max_incidence_deg))
    return np.where(valid, noisy, 0.0).astype(np.float32)


class RgbdCamera:
    def __init__(self, world: World, mount: CameraConfig, noise: CameraNoiseConfig, rng: np.random.Generator,
                 width_px: int | None = None, height_px: int | None = None,
                 renderer: RendererName = "raster") -> None:
        self.world = world
        self.renderer = renderer
        self._raster: RasterRenderer | None = None
        if renderer == "raster":
            self._raster = RasterRenderer(world.scene, world.scene_textures())
        elif renderer == "pybullet":
            world.load_textures()
        else:
            raise ValueError(f"unknown camera renderer {renderer!r} (raster or pybullet)")
        self.mount = mount
        self.noise = noise
        self.rng = rng
        w = width_px or mount.width_px
        h = height_px or mount.height_px
        self.intrinsics = CameraIntrinsics.from_fov(w, h, mount.hfov_deg, mount.vfov_deg)
        self._proj = projection_matrix_gl(self.intrinsics, noise.near_clip_m, noise.far_clip_m)
        self.R_qc = mount.R_qc_matrix
        self.p_qc_m = mount.p_qc
        self._depth_noise = NoiseBank(rng, (h, w))
        self._rgb_noise = NoiseBank(rng, (h, w, 3))
        # the frames' fates (drops, stamp errors) in a stream of their own: a dropped frame draws no pixel noise
        self._timing_rng = rng.spawn(1)[0]
        self._period_s = 1.0 / mount.rate_hz
        self._material_lut: NDArray[np.uint8] | None = None  # pybullet body id + 1 -> material code

    def pose_ned(self, state: RigidState) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Camera position (arena NED) and R_ned_c (optical -> NED)."""
        return state.p_ned_m + state.R_ned_q @ self.p_qc_m, state.R_ned_q @ self.R_qc

    def render_raw(self, state: RigidState) -> tuple[NDArray[np.uint8], NDArray[np.float32]]:
        """Noise-free colour (H x W x 3) and optical-axis depth (m)."""
        p_ned, R_ned_c = self.pose_ned(state)
        if self._raster is not None:
            return self._raster.render(p_ned, R_ned_c, self.intrinsics, self.noise.near_clip_m, self.noise.far_clip_m)
        view = view_matrix_gl(D @ R_ned_c, D @ p_ned)
        k = self.intrinsics
        _, _, rgba, depth_buf, _ = p.getCameraImage(
            k.width, k.height, view, self._proj, renderer=p.ER_TINY_RENDERER, shadow=0,
            lightDirection=[0.3, 0.2, 1.0], flags=p.ER_NO_SEGMENTATION_MASK, physicsClientId=self.world.client)
        rgb = np.asarray(rgba, dtype=np.uint8).reshape(k.height, k.width, 4)[:, :, :3]
        depth = linearize_depth(np.asarray(depth_buf).reshape(k.height, k.width), self.noise.near_clip_m,
                                self.noise.far_clip_m)
        return rgb, depth

    def render_layers(self, state: RigidState) -> tuple[NDArray[np.uint8], NDArray[np.float32], NDArray[np.uint8]]:
        """Noise-free colour, optical-axis depth (m) and per-pixel material codes (``scene.MATERIAL_CODE``)."""
        p_ned, R_ned_c = self.pose_ned(state)
        if self._raster is not None:
            return self._raster.render_layers(p_ned, R_ned_c, self.intrinsics, self.noise.near_clip_m,
                                              self.noise.far_clip_m)
        view = view_matrix_gl(D @ R_ned_c, D @ p_ned)
        k = self.intrinsics
        _, _, rgba, depth_buf, seg = p.getCameraImage(
            k.width, k.height, view, self._proj, renderer=p.ER_TINY_RENDERER, shadow=0,
            lightDirection=[0.3, 0.2, 1.0], physicsClientId=self.world.client)
        rgb = np.asarray(rgba, dtype=np.uint8).reshape(k.height, k.width, 4)[:, :, :3]
        depth = linearize_depth(np.asarray(depth_buf).reshape(k.height, k.width), self.noise.near_clip_m,
                                self.noise.far_clip_m)
        if self._material_lut is None:  # scene bodies by id; the background (-1) and any other body: matte
            lut = np.zeros(max(self.world.materials, default=0) + 2, np.uint8)
            for body, material in self.world.materials.items():
                lut[body + 1] = MATERIAL_CODE[material]
            self._material_lut = lut
        ids = np.asarray(seg, dtype=np.int64).reshape(k.height, k.width) + 1
        ids[(ids < 0) | (ids >= len(self._material_lut))] = 0
        return rgb, depth, self._material_lut[ids]

    def _render_xtion(self, state: RigidState, stamp_s: float
                      ) -> tuple[NDArray[np.uint8], NDArray[np.float32], float]:
        """Colour (motion-blurred over the exposure), the Xtion's depth, and the jittered stamp."""
        cfg = self.noise.xtion
        rgb, z, material = self.render_layers(state)
        k = self.intrinsics
        incidence_ok = incidence_cos(z, k) >= math.cos(math.radians(self.noise.max_incidence_deg))
        depth = xtion_depth(z, material, k, cfg, self.mount.min_range_m, self.mount.max_range_m, incidence_ok,
                            self._depth_noise.draw())
        if cfg.exposure_s > 0:
            v_c, omega_c = camera_velocity(state.R_ned_q, state.v_ned_m_s, state.omega_q_rad_s, self.R_qc, self.p_qc_m)
            if max_motion_bound_px(float(z.min()), k, v_c, omega_c, cfg.exposure_s) >= cfg.blur_min_px:
                du, dv = image_motion_px(z, k, v_c, omega_c, cfg.exposure_s)
                rgb = motion_blur(rgb, du, dv, cfg)
        return rgb, depth, stamp_s + draw_stamp_error_s(self._timing_rng, cfg, self._period_s)

    def capture(self, state: RigidState, seq: int, stamp_s: float) -> RgbdFrame | None:
        """What the driver delivers for the frame due at ``stamp_s``: None when the link loses it (``xtion``
        model, ``frame_drop_probability``; nothing is rendered then), else :meth:`render`'s frame."""
        if self.noise.model == "xtion" and draw_frame_dropped(self._timing_rng, self.noise.xtion):
            return None
        return self.render(state, seq, stamp_s)

    def render(self, state: RigidState, seq: int, stamp_s: float) -> RgbdFrame:
        if self.noise.model == "xtion":
            rgb, depth, stamp_s = self._render_xtion(state, stamp_s)
        else:
            rgb, z = self.render_raw(state)
            depth = depth_noise_model(z, self.intrinsics, self.noise, self.mount.min_range_m, self.mount.max_range_m,
                                      self.rng, self._depth_noise.draw())
        if self.noise.rgb_noise_levels > 0:
            noisy = rgb.astype(np.float32) + np.float32(self.noise.rgb_noise_levels) * self._rgb_noise.draw()
            rgb = np.clip(noisy, 0, 255).astype(np.uint8)
        # no mount: where the camera sits is the vehicle's calibration, not the simulator's truth
        return RgbdFrame(seq=seq, stamp_s=stamp_s, rgb=rgb, depth_m=depth, intrinsics=self.intrinsics,
                         meta={"source": "sitl", "clock": "sim"})

"""Synthetic RGB-D frames of a textured room with exact poses (tests, benchmarks; pure numpy).

The camera looks into an axis-aligned box room (walls, floor, ceiling) whose surfaces carry a smooth
procedural texture (a sum of sinusoids of 0.08–0.6 m wavelength, so every pyramid level has gradients and
nothing aliases at QVGA). :func:`render` ray-casts one frame for a camera pose ``T_w_c`` (camera optical
frame into the world), returning colour and metric depth exactly consistent with the pose.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from quadlink.camera import CameraIntrinsics, RgbdFrame
from quadlink.lie import so3_log

# room bounds in the world frame (m): x, y, z ranges
ROOM_MIN = np.array([-2.0, -1.5, -1.2])
ROOM_MAX = np.array([2.0, 1.5, 3.5])

_WAVES = [  # (kx, ky, phase, amplitude) in rad/m on the two in-plane coordinates
    (11.0, 7.0, 0.3, 0.16), (-6.0, 13.0, 1.1, 0.12), (23.0, -17.0, 2.0, 0.08), (4.0, 3.0, 0.7, 0.10),
    (19.0, 13.0, 1.7, 0.06),
]


def _texture(a: NDArray[np.float64], b: NDArray[np.float64], face: NDArray[np.intp]) -> NDArray[np.float64]:
    val = np.full(a.shape, 0.5) + 0.03 * (face % 3)
    for i, (kx, ky, ph, amp) in enumerate(_WAVES):
        val += amp * np.sin(kx * a + ky * b + ph + 0.9 * face * (i + 1))
    return np.clip(val, 0.0, 1.0)


def render(T_w_c: NDArray[np.float64], K: CameraIntrinsics, max_depth_m: float = 8.0, supersample: int = 2
           ) -> tuple[NDArray[np.uint8], NDArray[np.float32]]:
    """Colour (H×W×3 uint8) and depth (H×W float32 m, optical-axis z) of the room from pose ``T_w_c``.

    Colour is averaged over ``supersample``² samples per pixel (a camera integrates over its pixels, and
    grazing walls would otherwise alias); depth is sampled at the pixel centre.
    """
    s = supersample
    offs = (np.arange(s) + 0.5) / s - 0.5
    u, v = np.meshgrid(np.arange(K.width, dtype=float), np.arange(K.height, dtype=float))
    acc = np.zeros(u.shape)
    for du in offs:
        for dv in offs:
            acc += _cast(T_w_c, K, u + du, v + dv)[0]
    inten = acc / (s * s)
    depth = _cast(T_w_c, K, u, v)[1]
    rgb = np.repeat((inten * 255.0 + 0.5).astype(np.uint8)[..., None], 3, axis=2)
    depth[~np.isfinite(depth) | (depth > max_depth_m)] = 0.0
    return rgb, depth


def _cast(T_w_c: NDArray[np.float64], K: CameraIntrinsics, u: NDArray[np.float64], v: NDArray[np.float64]
          ) -> tuple[NDArray[np.float64], NDArray[np.float32]]:
    """Texture intensity (0..1) and depth along the optical axis of rays through pixel coordinates (u, v)."""
    rays_c = np.stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones_like(u)], axis=-1)  # z = 1
    R, o = T_w_c[:3, :3], T_w_c[:3, 3]
    d = rays_c @ R.T
    # the wall each ray leaves the box through: per axis the bound in the ray's direction, nearest wins
    with np.errstate(divide="ignore", invalid="ignore"):
        bounds = np.where(d > 0, ROOM_MAX, ROOM_MIN)
        t_axes = (bounds - o) / d
    t_axes = np.where(np.isfinite(t_axes) & (t_axes > 1e-6), t_axes, np.inf)
    axis = np.argmin(t_axes, axis=-1)
    best_t = np.take_along_axis(t_axes, axis[..., None], axis=-1)[..., 0]
    face = 2 * axis + (np.take_along_axis(d, axis[..., None], axis=-1)[..., 0] > 0)
    p = o + d * best_t[..., None]
    a = np.where(axis == 0, p[..., 1], p[..., 0])
    b = np.where(axis == 2, p[..., 1], p[..., 2])
    depth = best_t.astype(np.float32)  # rays have unit z in the camera frame: t is the depth
    return _texture(a, b, face), depth


def render_frame(seq: int, stamp_s: float, T_w_c: NDArray[np.float64], K: CameraIntrinsics) -> RgbdFrame:
    rgb, depth = render(T_w_c, K)
    return RgbdFrame(seq, stamp_s, rgb, depth, K)


def qvga_intrinsics() -> CameraIntrinsics:
    """The vehicle camera's QVGA intrinsics (58° x 45°)."""
    return CameraIntrinsics.from_fov(320, 240, 58.0, 45.0)


def pose(R: NDArray[np.float64], t: NDArray[np.float64] | list[float]) -> NDArray[np.float64]:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


class SyntheticFlight:
    """A smooth body trajectory in the room with its exact IMU and camera poses (NED-like world).

    Body position ``p(t)`` and ZYX Euler angles are sums of sinusoids (a pan-scan yaw oscillation plus a
    slow drift); gyro and specific force are derived exactly (angular rate from the rotation's derivative,
    ``f = R^T (a - g)`` with ``g = (0, 0, 9.81)``).
    """

    def __init__(self, R_qc: NDArray[np.float64], p_qc_m: NDArray[np.float64], speed_m_s: float = 0.4,
                 yaw_amp_rad: float = 0.5, yaw_freq_hz: float = 0.25, tilt_rad: float = 0.08) -> None:
        self.R_qc = np.asarray(R_qc, dtype=float)
        self.p_qc_m = np.asarray(p_qc_m, dtype=float)
        self.speed = speed_m_s
        self.yaw_amp = yaw_amp_rad
        self.w_yaw = 2 * np.pi * yaw_freq_hz
        self.tilt = tilt_rad

    def position(self, t: float) -> NDArray[np.float64]:
        w = 0.5
        a = self.speed / w
        return np.array([a * np.sin(w * t), 0.5 * a * (1 - np.cos(w * t)), 0.2 * np.sin(0.7 * t)])

    def velocity(self, t: float) -> NDArray[np.float64]:
        w = 0.5
        a = self.speed / w
        return np.array([a * w * np.cos(w * t), 0.5 * a * w * np.sin(w * t), 0.14 * np.cos(0.7 * t)])

    def acceleration(self, t: float) -> NDArray[np.float64]:
        w = 0.5
        a = self.speed / w
        return np.array([-a * w * w * np.sin(w * t), 0.5 * a * w * w * np.cos(w * t), -0.098 * np.sin(0.7 * t)])

    def euler(self, t: float) -> tuple[float, float, float]:
        return (self.tilt * np.sin(1.3 * t), self.tilt * np.sin(0.9 * t + 0.5),
                self.yaw_amp * np.sin(self.w_yaw * t))

    def R_wq(self, t: float) -> NDArray[np.float64]:
        from quadlink.frames import R_from_euler

        return R_from_euler(*self.euler(t))

    def gyro(self, t: float, h: float = 1e-5) -> NDArray[np.float64]:

        return so3_log(self.R_wq(t - h).T @ self.R_wq(t + h)) / (2 * h)

    def specific_force(self, t: float) -> NDArray[np.float64]:
        from quadlink.frames import GRAVITY_M_S2

        return self.R_wq(t).T @ (self.acceleration(t) - np.array([0.0, 0.0, GRAVITY_M_S2]))

    def v_h(self, t: float) -> NDArray[np.float64]:
        """True velocity in H (world velocity rotated by minus the yaw)."""
        from quadlink.frames import Rz

        return Rz(self.euler(t)[2]).T @ self.velocity(t)

    def T_w_c(self, t: float) -> NDArray[np.float64]:
        R = self.R_wq(t)
        return pose(R @ self.R_qc, self.position(t) + R @ self.p_qc_m)

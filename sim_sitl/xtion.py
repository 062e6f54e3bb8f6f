"""How a structured-light RGB-D camera (Asus Xtion, Kinect v1) fails, on top of a noise-free render (pure).

``camera_sim.RgbdCamera`` applies these when ``CameraNoiseConfig.model`` is ``xtion``; every parameter is in
:class:`~sim_sitl.config.XtionConfig`, every random draw comes from the generator the caller passes.

* **Depth from disparity** (Khoshelham & Oude Elberink, Sensors 12 (2012) 1437: the disparity-depth relation
  and its error propagation): the sensor measures the disparity d = f b / z (IR camera focal length f in px,
  projector baseline b) in steps of 1/8 px with a random error sigma_d, so in depth the random error is
  z^2 sigma_d / (f b) and the steps between the depths it can report are z^2 step_d / (f b): ~1 cm at 2 m,
  ~7 cm at 5 m, not 1 mm everywhere.
* **IR shadows**: the projector sits ``projector_x_m`` beside the IR camera along its optical x axis, so the
  image rows are its epipolar lines. A point is lit iff no nearer surface lies on its projector ray; along a
  row that is a running extremum of the projector column u_p = u - f_x x_p / z (:func:`ir_shadow`): a hole
  beside every foreground edge that faces away from the projector (a projector on the right casts shadows to
  the left), f_x b (1/z_near - 1/z_far) pixels wide.
* **Materials**: dark (absorbs the IR), specular (mirrors the pattern away) and glass (the renderers do not draw
  it at all: depth and colour come from behind) give no return.
* **Valid range**: the driver reports 0 (no return) outside [min_range, max_range] of the measured depth.
* **Frames** (:func:`draw_frame_dropped`, :func:`draw_stamp_error_s`): each frame may be lost on the USB
  link (not published); the stamp a published frame carries has a clipped Gaussian error.
* **Motion blur** (:func:`image_motion_px`, :func:`motion_blur`): the colour image integrates the scene over the
  exposure; every pixel is averaged along its own image motion (rotation exactly, translation with its depth).
"""

from __future__ import annotations

import functools
import math

import cv2
import numpy as np
from numpy.typing import NDArray

from quadlink.camera import CameraIntrinsics
from sim_sitl.config import MATERIALS, XtionConfig

#: per material code (``scene.MATERIAL_CODE``): does the surface return the projected pattern
RETURNS_PATTERN = np.array([m == "matte" for m in MATERIALS], dtype=bool)
SHADOW_TOLERANCE_PX = 0.01  # a projector column this much behind the running extremum is hidden (float slack)


def disparity_depth(z_m: NDArray[np.float32], cfg: XtionConfig,
                    noise: NDArray[np.float32] | None = None) -> NDArray[np.float32]:
    """Depth as the sensor reports it: z -> d = f b / z (px), + sigma_d * ``noise`` (N(0, 1) per pixel),
    rounded to the disparity step, -> f b / d. A disparity that rounds to <= 0 gives 0 (no return)."""
    fb = np.float32(cfg.ir_focal_px * abs(cfg.projector_x_m))
    z = np.asarray(z_m, dtype=np.float32)
    with np.errstate(divide="ignore"):
        d = fb / z
    if noise is not None and cfg.disparity_sigma_px > 0:
        d += np.float32(cfg.disparity_sigma_px) * noise
    if cfg.disparity_step_px > 0:
        step = np.float32(cfg.disparity_step_px)
        d = np.round(d / step) * step
    with np.errstate(divide="ignore"):
        out = np.where(d > 0, fb / np.maximum(d, np.float32(1e-12)), np.float32(0.0))
    return out.astype(np.float32, copy=False)


def depth_step_m(z_m: float, cfg: XtionConfig) -> float:
    """The gap between the depths the sensor can report near ``z_m``: z^2 step_d / (f b) (K&OE 2012)."""
    return z_m * z_m * cfg.disparity_step_px / (cfg.ir_focal_px * abs(cfg.projector_x_m))


def depth_sigma_m(z_m: float, cfg: XtionConfig) -> float:
    """The random error of depth at ``z_m``: z^2 sigma_d / (f b) (K&OE 2012: the propagated disparity error)."""
    return z_m * z_m * cfg.disparity_sigma_px / (cfg.ir_focal_px * abs(cfg.projector_x_m))


def ir_shadow(z_m: NDArray[np.float32], k: CameraIntrinsics, projector_x_m: float) -> NDArray[np.bool_]:
    """Pixels the projector cannot light (True), from the noise-free depth seen by the IR camera ``k``.

    The projector is the IR camera moved by ``projector_x_m`` along optical x. A pixel (u, v) at depth z is at
    projector column u_p = u - f_x x_p / z on the same row. With the projector on the left (x_p < 0) a nearer
    surface shifts further right in the projector's view: a point is hidden iff some pixel left of it has a
    larger u_p (the surface between two samples is taken as continuous); the holes lie right of foreground
    edges. With x_p > 0 the same holds mirrored: holes left of foreground edges.
    """
    z = np.asarray(z_m, dtype=np.float32)
    H, W = z.shape
    s = np.float32(k.fx * projector_x_m)
    u = np.arange(W, dtype=np.float32)[None, :]
    with np.errstate(divide="ignore"):
        up = u - s / z
    if projector_x_m > 0:  # mirror: scan from the right with -u_p
        up = -up[:, ::-1]
    seen = np.maximum.accumulate(up, axis=1)
    shadow = np.zeros((H, W), dtype=bool)
    shadow[:, 1:] = seen[:, :-1] > up[:, 1:] + np.float32(SHADOW_TOLERANCE_PX)
    return shadow[:, ::-1] if projector_x_m > 0 else shadow


def xtion_depth(z_m: NDArray[np.float32], material: NDArray[np.uint8] | None, k: CameraIntrinsics,
                cfg: XtionConfig, min_range_m: float, max_range_m: float,
                incidence_ok: NDArray[np.bool_] | None = None,
                noise: NDArray[np.float32] | None = None) -> NDArray[np.float32]:
    """The depth image (m, 0 = no return) the driver gives for the noise-free depth ``z_m``.

    ``material``: per-pixel material codes (None: all matte); ``incidence_ok``: pixels not seen at a grazing
    angle (None: all); ``noise``: N(0, 1) per pixel for the disparity error (None: noise-free, for tests).
    """
    z = np.asarray(z_m, dtype=np.float32)
    measured = disparity_depth(z, cfg, noise)
    valid = (measured >= np.float32(min_range_m)) & (measured <= np.float32(max_range_m))
    valid &= ~ir_shadow(z, k, cfg.projector_x_m)
    if material is not None:
        valid &= RETURNS_PATTERN[material]
    if incidence_ok is not None:
        valid &= incidence_ok
    return np.where(valid, measured, np.float32(0.0)).astype(np.float32, copy=False)


def draw_frame_dropped(rng: np.random.Generator, cfg: XtionConfig) -> bool:
    """Whether the link loses this frame (independently, with ``frame_drop_probability``): one draw."""
    return bool(rng.random() < cfg.frame_drop_probability)


def draw_stamp_error_s(rng: np.random.Generator, cfg: XtionConfig, period_s: float) -> float:
    """The error of a published frame's stamp: N(0, stamp_jitter_s) clipped to +-min(stamp_jitter_max_s,
    0.45 period), so stamps stay in order. One draw (none when the jitter is off)."""
    if cfg.stamp_jitter_s <= 0:
        return 0.0
    bound = min(cfg.stamp_jitter_max_s, 0.45 * period_s)
    return float(np.clip(rng.normal(0.0, cfg.stamp_jitter_s), -bound, bound))


def camera_velocity(R_ned_q: NDArray[np.float64], v_ned_m_s: NDArray[np.float64], omega_q_rad_s: NDArray[np.float64],
                    R_qc: NDArray[np.float64], p_qc_m: NDArray[np.float64]
                    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The camera's linear velocity (m/s) and angular rate (rad/s), both in the optical frame C, from the body's."""
    omega_q = np.asarray(omega_q_rad_s, dtype=float)
    v_q = np.asarray(R_ned_q, dtype=float).T @ np.asarray(v_ned_m_s, dtype=float) + np.cross(omega_q, p_qc_m)
    R_cq = np.asarray(R_qc, dtype=float).T
    return R_cq @ v_q, R_cq @ omega_q


def image_motion_px(z_m: NDArray[np.float32], k: CameraIntrinsics, v_c_m_s: NDArray[np.float64],
                    omega_c_rad_s: NDArray[np.float64], duration_s: float
                    ) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """How far (px) each pixel's static scene point moves in ``duration_s`` while the camera moves (first order).

    A static point P = z (x, y, 1) moves in C as dP/dt = -v - omega x P, so
    du/dt = f_x [-w_y (1 + x^2) + w_x x y + w_z y] + f_x (-v_x + x v_z) / z, and dv/dt likewise.
    """
    z = np.asarray(z_m, dtype=np.float32)
    H, W = z.shape
    x = ((np.arange(W, dtype=np.float32) - np.float32(k.cx)) / np.float32(k.fx))[None, :]
    y = ((np.arange(H, dtype=np.float32) - np.float32(k.cy)) / np.float32(k.fy))[:, None]
    wx, wy, wz = (float(a) for a in omega_c_rad_s)
    vx, vy, vz = (float(a) for a in v_c_m_s)
    inv_z = np.float32(1.0) / np.maximum(z, np.float32(1e-3))
    ku, kv = np.float32(k.fx * duration_s), np.float32(k.fy * duration_s)
    du = ku * ((-wy * (1 + x * x) + wz * y + wx * x * y) + (x * vz - vx) * inv_z)
    dv = kv * ((wx * (1 + y * y) - wz * x - wy * x * y) + (y * vz - vy) * inv_z)
    return du.astype(np.float32, copy=False), dv.astype(np.float32, copy=False)


def max_motion_bound_px(z_min_m: float, k: CameraIntrinsics, v_c_m_s: NDArray[np.float64],
                        omega_c_rad_s: NDArray[np.float64], duration_s: float) -> float:
    """An upper bound of the largest |image motion| of :func:`image_motion_px` (cheap: no per-pixel work)."""
    x2 = (max(k.cx, k.width - 1 - k.cx) / k.fx) ** 2
    y2 = (max(k.cy, k.height - 1 - k.cy) / k.fy) ** 2
    r = math.sqrt(1.0 + x2 + y2)
    f = max(k.fx, k.fy) * duration_s
    return f * r * (r * float(np.linalg.norm(omega_c_rad_s)) + float(np.linalg.norm(v_c_m_s)) / max(z_min_m, 1e-3))


def motion_blur(rgb: NDArray[np.uint8], du_px: NDArray[np.float32], dv_px: NDArray[np.float32], cfg: XtionConfig
                ) -> NDArray[np.uint8]:
    """Average ``rgb`` along each pixel's motion over the exposure (``du/dv``: the motion during it, px), centred on
    the frame's instant: samples ``blur_sample_spacing_px`` apart along the longest smear (at least 2, at most
    ``blur_max_samples``), each a bilinear remap; unchanged below ``blur_min_px``."""
    longest = float(np.sqrt(np.max(du_px * du_px + dv_px * dv_px)))
    if longest < cfg.blur_min_px:
        return rgb
    n = int(min(cfg.blur_max_samples, max(2, math.ceil(longest / cfg.blur_sample_spacing_px))))
    H, W = du_px.shape
    u, v = _pixel_grid(W, H)
    acc = np.zeros(rgb.shape, np.float32)
    for i in range(n):
        s = (i + 0.5) / n - 0.5
        # fixed-point maps (1/32 px): remap is about twice as fast with them as with float maps
        map1, map2 = cv2.convertMaps(cv2.scaleAdd(du_px, s, u), cv2.scaleAdd(dv_px, s, v), cv2.CV_16SC2)
        cv2.accumulate(cv2.remap(rgb, map1, map2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE), acc)
    return np.asarray(cv2.convertScaleAbs(acc, alpha=1.0 / n), dtype=np.uint8)


@functools.lru_cache(maxsize=4)
def _pixel_grid(width: int, height: int) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Column and row index of every pixel (H x W float32 each; read-only, shared)."""
    u = np.arange(width, dtype=np.float32)[None, :].repeat(height, 0)
    v = np.arange(height, dtype=np.float32)[:, None].repeat(width, 1)
    u.flags.writeable = False
    v.flags.writeable = False
    return u, v

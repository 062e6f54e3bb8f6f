"""Frame preparation for the direct RGB-D odometry (:mod:`perception.odometry`): image pyramids and sampling
textures, gradients, reference points and their Jacobians, and bilinear sampling.

:func:`prepare_frame` turns one RGB-D frame into a :class:`PreparedFrame` (finest level first): intensity in
0..1, depth with invalid and out-of-range values at 0 (downscaled by DVO's valid-mean rule), and a 4-channel
texture (intensity, depth, eroded depth validity, inside) sampled by :func:`_sample`. Gradients and the
reference points (pixel selection, Jacobians of the inverse-compositional warp) are computed only when a frame
is first used as a reference, and kept on it. :func:`rotate_depth` registers an unsynchronised depth image to
the colour instant.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from perception.odometry_config import OdometryConfig
from quadlink.camera_frame import CameraIntrinsics

__all__ = ["Image", "PreparedFrame", "prepare_frame", "rotate_depth"]

_MAX_DEPTH_SLOPE = float(np.tan(np.radians(75.0)))


Image = NDArray[Any]   # float32 images (OpenCV's stubs type them loosely)


@dataclass
class _Gradients:
    """A reference level's gradients and selection score: computed only for frames that become a reference
    (a keyframe), since inverse-compositional alignment never differentiates the current frame."""

    gx: Image         # dI/du, dI/dv (Sobel)
    gy: Image
    zx: Image         # dZ/du, dZ/dv (Sobel; only meaningful where tex's valid channel is 1)
    zy: Image
    select: Image     # |dI/du| + |dI/dv| + 1e-6 where the depth is valid, inside a 2-pixel border, else 0


@dataclass
class _Level:
    K: CameraIntrinsics
    tex: Image        # H×W×4, sampled at the warped points: I, Z, valid (eroded depth validity), 1 (inside)
    gray: Image       # intensity in 0..1
    depth: Image      # metres, 0 = invalid
    grad: _Gradients | None = None   # see gradients(): filled when the level is first used as a reference

    def gradients(self) -> _Gradients:
        if self.grad is None:
            self.grad = _compute_gradients(self.gray, self.depth)
        return self.grad


@dataclass
class PreparedFrame:
    """A frame's pyramid (finest first) with its sampling textures, computed once. As a reference (keyframe)
    it also holds its gradients and its reference points with their Jacobians per level, computed on first
    use and reused by every frame aligned against it."""

    levels: list[_Level] = field(default_factory=list)
    references: dict[tuple[int, int, float, bool], _Reference] = field(default_factory=dict)
    # robust scales (s_I^2, s_Z^2) per level of the last alignment against this frame: the next frame aligned
    # against the same reference starts from them (one fixed-point step an iteration instead of five at first)
    scales: dict[int, tuple[float, float]] = field(default_factory=dict)
    depth_at_colour_instant: bool = True   # False: an unsynchronised depth image that could not be turned yet
    stamp_s: float = 0.0                   # the colour image's stamp
    depth_offset_s: float = 0.0            # the depth image's stamp minus the colour's, when the depth term is to
                                           # compare the depth instants (see align_pair); else 0

    def reference(self, level: int, max_points: int, gradient_fraction: float, affine: bool) -> _Reference:
        key = (level, max_points, gradient_fraction, affine)
        if key not in self.references:
            self.references[key] = _reference(self.levels[level], max_points, gradient_fraction, affine)
        return self.references[key]


def _gray01(rgb: NDArray[np.uint8]) -> Image:
    return np.multiply(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), np.float32(1.0 / 255.0), dtype=np.float32)


def _downsample_depth(depth: Image) -> Image:
    """Half resolution: mean of the valid depths in each 2x2 block (DVO's rule), 0 if none is valid.

    Two exact-2x INTER_AREA resizes (block means of the depth and of the validity) and one division: the
    mean of the valid depths is ``mean(Z) / mean(valid)``.
    """
    h, w = depth.shape[0] // 2 * 2, depth.shape[1] // 2 * 2
    d = depth[:h, :w]
    size = (w // 2, h // 2)
    s = cv2.resize(d, size, interpolation=cv2.INTER_AREA)
    n = cv2.resize((d > 0).view(np.uint8).astype(np.float32), size, interpolation=cv2.INTER_AREA)
    # a block without valid depth has mean(Z) = 0 too: dividing by max(mean(valid), tiny) leaves it 0
    np.maximum(n, np.float32(1e-6), out=n)
    np.divide(s, n, out=s)
    return s


_KERNEL3 = np.ones((3, 3), np.uint8)
_ONES: dict[tuple[int, ...], NDArray[np.float32]] = {}
_BORDER: dict[tuple[int, ...], NDArray[np.uint8]] = {}


def _ones(shape: tuple[int, ...]) -> NDArray[np.float32]:
    if shape not in _ONES:
        _ONES[shape] = np.ones(shape, np.float32)
    return _ONES[shape]


def _inner(shape: tuple[int, ...]) -> NDArray[np.uint8]:
    """1 inside a 2-pixel border (where the 3×3 gradients are two-sided), 0 on it."""
    if shape not in _BORDER:
        m = np.zeros(shape, np.uint8)
        m[2:-2, 2:-2] = 1.0
        _BORDER[shape] = m
    return _BORDER[shape]


def _compute_gradients(gray: Image, depth: Image) -> _Gradients:
    gx = cv2.Sobel(gray, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
    gy = cv2.Sobel(gray, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
    # meaningless where the 3×3 neighbourhood has invalid depth: such points get no depth term (tex's valid)
    zx = cv2.Sobel(depth, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
    zy = cv2.Sobel(depth, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
    # selection score: |dI/du| + |dI/dv| (plus a floor, so textureless pixels stay selectable for the
    # depth term) where the depth is valid, inside a 2-pixel border
    sel = np.abs(gx)
    sel += np.abs(gy)
    sel += np.float32(1e-6)
    sel *= cv2.bitwise_and((depth > 0).view(np.uint8), _inner(gray.shape))
    return _Gradients(gx=gx, gy=gy, zx=zx, zy=zy, select=sel)


def rotate_depth(depth: Image, K: CameraIntrinsics, R_c_d: NDArray[np.float64]) -> Image:
    """The depth image a camera turned by ``R_c_d`` (depth-time camera -> colour-time camera) would have seen.

    A rotation moves pixels by the homography ``x_d = K R_c_d^T K^-1 x_c`` whatever their depth, and turns the
    ray's z: ``Z_c = Z_d / (R_c_d^T K^-1 x_c)_z``. Bilinear samples (nearest-neighbour ones shift the depth by
    up to half a pixel, which on slanted surfaces costs the depth term more than the registration gains), kept
    only where all four neighbours are valid, so no depth mixes with an invalid one; pixels that come from
    outside the image are invalid (0)."""
    Kf = np.array([[K.fx, 0.0, K.cx], [0.0, K.fy, K.cy], [0.0, 0.0, 1.0]])
    Kinv = np.linalg.inv(Kf)
    M = Kf @ R_c_d.T @ Kinv
    h, w = depth.shape
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    out: Image = cv2.warpPerspective(depth, M, (w, h), flags=flags, borderMode=cv2.BORDER_CONSTANT,
                                     borderValue=0.0)
    valid = cv2.warpPerspective((depth > 0).view(np.uint8).astype(np.float32), M, (w, h), flags=flags,
                                borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
    out[valid < np.float32(0.999)] = 0.0
    # (R^T K^-1 x)_z = c . K^-1 x with c the third column of R_c_d: a plane in (u, v)
    a, b, c = (R_c_d[:, 2] @ Kinv).tolist()
    u = np.arange(w, dtype=np.float32) * np.float32(a)
    v = np.arange(h, dtype=np.float32) * np.float32(b) + np.float32(c)
    np.divide(out, v[:, None] + u[None, :], out=out)
    return out


def prepare_frame(rgb: NDArray[np.uint8], depth_m: NDArray[np.float32], K: CameraIntrinsics,
                  config: OdometryConfig, R_c_d: NDArray[np.float64] | None = None) -> PreparedFrame:
    """Pyramids and the sampling texture of one frame (finest level first); gradients come later, and only
    if the frame becomes a reference. ``R_c_d`` (the camera's rotation from the depth image's instant to the
    colour image's) registers an unsynchronised depth image to the colour instant (:func:`rotate_depth`)."""
    gray = _gray01(rgb)
    d = np.asarray(depth_m, dtype=np.float32)
    # NaN and inf fall outside the range too: they and out-of-range depths become 0 (invalid)
    depth = cv2.copyTo(d, cv2.inRange(d, config.min_depth_m, config.max_depth_m), np.zeros_like(d))
    if gray.shape[1] > config.working_width_px:
        factor = config.working_width_px / gray.shape[1]
        size = (config.working_width_px, round(gray.shape[0] * factor))
        gray = cv2.resize(gray, size, interpolation=cv2.INTER_AREA)
        while depth.shape[1] >= 2 * size[0]:
            depth = _downsample_depth(depth)
        if depth.shape[1] != size[0]:
            depth = cv2.resize(depth, size, interpolation=cv2.INTER_NEAREST)
        K = K.scaled(factor)
    if R_c_d is not None:
        depth = rotate_depth(depth, K, R_c_d)
    out = PreparedFrame()
    for lvl in range(config.levels):
        if lvl > 0:
            # 2x2 block means for intensity and depth alike, so K.scaled(0.5) is exact for both
            gray = cv2.resize(gray, (gray.shape[1] // 2, gray.shape[0] // 2), interpolation=cv2.INTER_AREA)
            depth = _downsample_depth(depth)
            if depth.shape != gray.shape:
                depth = cv2.resize(depth, (gray.shape[1], gray.shape[0]), interpolation=cv2.INTER_NEAREST)
            K = K.scaled(0.5)
        valid_e = cv2.erode((depth > 0).view(np.uint8), _KERNEL3).astype(np.float32)
        out.levels.append(_Level(K=K, tex=cv2.merge([gray, depth, valid_e, _ones(gray.shape)]),
                                 gray=gray, depth=depth))
    return out


def _select_pixels(level: _Level, max_points: int, gradient_fraction: float) -> NDArray[np.intp]:
    """Flat indices of the reference pixels: the strongest intensity gradients plus an even spread.

    The gradient threshold is the quantile of a 4×4-strided subsample of the image that leaves about
    ``gradient_fraction * max_points`` pixels above it (no sort of every pixel); the spread is a regular
    grid over the remaining usable pixels (for the depth term, which needs no texture).
    """
    sel = level.gradients().select
    h, w = sel.shape
    n_grad = int(max_points * gradient_fraction)
    step = 4
    sub = sel[::step, ::step]
    sub_valid = sub[sub > 0]
    if sub_valid.size == 0:
        return np.empty(0, np.intp)
    n_usable = sub_valid.size * step * step   # estimate
    if n_usable <= max_points:
        return np.flatnonzero(sel > 0)
    k = sub_valid.size - max(1, n_grad // (step * step))
    thr = np.partition(sub_valid, k)[k] if k > 0 else np.float32(0.0)
    top = np.flatnonzero(sel > thr)
    if top.size > n_grad:
        top = top[np.linspace(0, top.size - 1, n_grad).astype(np.intp)]
    n_rest = max_points - top.size
    if n_rest <= 0:
        return top
    g = max(1, int(math.sqrt(n_usable / n_rest)))
    grid = sel[::g, ::g]
    gv, gu = np.divmod(np.flatnonzero((grid > 0) & (grid <= thr)), grid.shape[1])
    rest = gv * (g * w) + gu * g
    if rest.size > n_rest:
        rest = rest[np.linspace(0, rest.size - 1, n_rest).astype(np.intp)]
    return np.concatenate([top, rest])


def _jacobian_rows(out: Image, x: Image, y: Image, z: Image, a: Image, b: Image, dz: float) -> None:
    """Write the 6 × N Jacobian rows of a residual ``f(pi(exp(xi) p))`` w.r.t. a left se(3) increment xi
    at ``p = (x, y, z)``, given the pixel gradient scaled by ``f/z``: ``a = f_u f_x / z``, ``b = f_v f_y / z``;
    ``dz`` is the residual's direct d/dz (-1 for the depth residual, whose value also moves with ``[p]_z``)."""
    c = out[2]
    np.multiply(a, x, out=c)
    c += b * y
    c /= z
    np.negative(c, out=c)
    if dz:
        c += np.float32(dz)
    out[0] = a
    out[1] = b
    np.subtract(y * c, z * b, out=out[3])       # p x (a, b, c)
    np.subtract(z * a, x * c, out=out[4])
    np.subtract(x * b, y * a, out=out[5])


@dataclass
class _Reference:
    """One level's reference points with their Jacobians, fixed for the level (inverse compositional)."""

    P: Image                  # 4 × N points in the reference camera frame, homogeneous
    I: Image                  # N intensities
    J: Image                  # 8 or 9 × 2N, columns photometric [0, N) and depth [N, 2N): rows 0-5 the pose
                              # Jacobian, with the brightness model 6-7 its Jacobian (I_ref, 1; 0 for depth),
                              # then the residuals (written each iteration; one BLAS product gives J^T W J and
                              # J^T W r), zero-padded to 8 rows
    z_ok: NDArray[np.bool_]   # N: depth gradient defined at the reference pixel (depth term usable)
    z_norm: Image             # N: (Z_med / Z)^2, the depth residual's noise normalisation
    z_med: float              # median depth of the points, m


def _reference(level: _Level, max_points: int, gradient_fraction: float, affine: bool) -> _Reference:
    idx = _select_pixels(level, max_points, gradient_fraction)
    w = level.depth.shape[1]
    v, u = np.divmod(idx, w)
    K = level.K
    grad = level.gradients()
    z = level.depth.ravel()[idx]
    x = (u.astype(np.float32) - np.float32(K.cx)) * np.float32(1.0 / K.fx) * z
    y = (v.astype(np.float32) - np.float32(K.cy)) * np.float32(1.0 / K.fy) * z
    n = idx.size
    nj = 8 if affine else 6
    # at least 8 rows: OpenBLAS's sgemm is more than twice as fast for 8 rows as for 7
    J = np.zeros((max(nj + 1, 8), 2 * n), np.float32)
    fx_z = np.float32(K.fx) / z
    fy_z = np.float32(K.fy) / z
    _jacobian_rows(J[:, :n], x, y, z, grad.gx.ravel()[idx] * fx_z, grad.gy.ravel()[idx] * fy_z, 0.0)
    zx, zy = grad.zx.ravel()[idx], grad.zy.ravel()[idx]
    _jacobian_rows(J[:, n:], x, y, z, zx * fx_z, zy * fy_z, -1.0)
    # structured-light depth noise grows with Z^2 (Khoshelham & Elberink 2012): each depth residual is scaled
    # by (Z_med / Z)^2, so near and far points weigh by their information while the robust scale (and its
    # floor) stays in metres at the median depth
    z_med = np.partition(z, n // 2)[n // 2] if n else np.float32(1.0)
    z_norm = (z_med / z) ** 2
    gray = level.gray.ravel()[idx]
    if affine:
        J[6, :n] = gray
        J[7, :n] = 1.0
    J[:6, n:] *= z_norm
    # the depth term needs a surface: a slope |dZ/du| f / Z beyond tan(75 deg) is a depth discontinuity (or a
    # grazing surface, where structured-light depth is unreliable), where Z is not differentiable
    slope2 = (zx * zx + zy * zy) * (fx_z * fx_z)
    z_ok = (level.tex.reshape(-1, 4)[idx, 2] > 0.999) & (slope2 < np.float32(_MAX_DEPTH_SLOPE**2))
    return _Reference(np.stack([x, y, z, np.ones_like(z)]), gray, J, z_ok, z_norm, float(z_med))


def _sample(tex: Image, u: NDArray[np.float32], v: NDArray[np.float32]) -> Image:
    """Bilinear samples (N×C) of a texture at pixel coordinates; outside the image every channel is 0.

    cv2.remap wants maps shorter than 32767 per side, so long point lists are folded into rows.
    """
    n = u.shape[0]
    width = 4096
    if n <= width:
        return cv2.remap(tex, u.reshape(1, -1), v.reshape(1, -1), cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_CONSTANT)[0]
    rows = -(-n // width)
    mu = np.full(rows * width, -10.0, np.float32)
    mv = mu.copy()
    mu[:n] = u
    mv[:n] = v
    out = cv2.remap(tex, mu.reshape(rows, width), mv.reshape(rows, width), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_CONSTANT)
    return out.reshape(rows * width, -1)[:n]

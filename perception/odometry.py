"""Dense RGB-D odometry in the spirit of DVO (Kerl, Sturm, Cremers, IROS 2013) — pure numpy/OpenCV.

Keyframe-based direct alignment: for a selection of reference pixels of the keyframe (strong intensity gradient
plus an even spread for the depth term) with valid depth, find the rigid motion ``T_ck_kf`` (points of the
keyframe into frame k; written ``T_ck_ckm1`` for a pair) minimising

    sum_i  w_I,i (r_I,i / s_I)^2 + lambda_Z  w_Z,i (r_Z,i / s_Z)^2  +  |log(R R_prior^T)|^2 / sigma_prior^2

with photometric residuals ``r_I = I_k(pi(T p_i)) - I_kf(x_i)``, depth residuals
``r_Z = (Z_k(pi(T p_i)) - [T p_i]_z) (Z_med / Z_i)^2`` (structured-light noise grows with Z^2; points on
depth discontinuities have no depth term), t-distribution weights (nu = 5) with the scales ``s_I, s_Z``
re-estimated each iteration (DVO's robust estimator), an optional rotation prior from the integrated gyro
(the IMU prior between frames, composed with the previous frame's pose in the keyframe), inverse-compositional
Gauss-Newton on se(3) (Jacobians of the reference points, fixed per level), coarse-to-fine over an image
pyramid, started from the previous frame's pose in the keyframe and the previous motion (constant velocity).

Inverse compositional alignment differentiates only the reference, so the keyframe's gradients, points and
Jacobians are computed once and reused by every frame aligned against it (frames that never become keyframes
get no gradients at all). A frame becomes the next keyframe after ``keyframe_max_frames`` frames, once it is
0.1 m / 5 degrees from the keyframe, or when its fitness drops; ``keyframe_max_frames = 1`` is frame-to-frame
alignment. Poses chain over keyframes: ``T_c0_ck = T_c0_kf · T_ck_kf^-1``, and the per-frame motion is
``T_ckm1_ck = T_ckm1_kf · T_ck_kf^-1`` (the difference of consecutive chained poses).

Everything is vectorised: warped samples come from one ``cv2.remap`` per iteration on a 1×N map of a
4-channel texture (intensity, depth, depth validity, inside), so no sample mixes invalid depth.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from quadlink.camera import CameraIntrinsics
from quadlink.lie import inv_T, so3_log

Mat4 = NDArray[np.float64]


@dataclass(frozen=True)
class OdometryConfig:
    """Parameters of the direct RGB-D odometry (defaults tuned on TUM fr1 and the SITL, QVGA)."""

    levels: int = 3                                  # pyramid levels (finest = input resolution)
    iterations: tuple[int, ...] = (10, 6, 2)         # Gauss-Newton iterations per level, coarse -> fine (the
                                                     # finest starts close: from the keyframe pose and the gyro)
    max_points: tuple[int, ...] = (600, 1200, 4000)  # selected reference pixels per level, coarse -> fine
    working_width_px: int = 320                      # frames wider than this are downscaled first (QVGA)
    min_depth_m: float = 0.2
    max_depth_m: float = 6.0
    depth_weight: float = 1.0                        # lambda_Z: weight of the depth term, each term being
                                                     # normalised by its robust scale (1: maximum likelihood)
    t_dof: float = 5.0                               # nu of the t-distribution weights (DVO)
    min_intensity_sigma: float = 0.004               # floors of the robust scales (about one grey level and
    min_depth_sigma_m: float = 0.0002                # a structured-light sensor's noise at 1 m) so exact
                                                     # data cannot make one term drown the other
    gradient_fraction: float = 0.2                   # share of the points picked by intensity gradient; the
                                                     # rest spread evenly: the depth term needs no texture and
                                                     # pins the translation (TUM fr1: translational RPE falls
                                                     # steadily from 0.75 to 0.1, rotational rises below ~0.2)
    imu_prior_sigma_rad: float = 0.01                # std of the gyro rotation prior between frames
    min_fitness: float = 0.3                         # inlier share below which the result is not ok
    min_points: int = 100
    max_translation_m: float = 0.5                   # per-frame sanity bounds
    max_rotation_rad: float = 0.6
    max_translation_jump_m: float = 0.03             # per-frame translation this far from the constant-velocity
                                                     # prediction is a wrong alignment (0.9 m/s gained in 33 ms
                                                     # at 30 Hz, ~3 g; SITL: a hovering vehicle "jumped" 9 cm)
    convergence_eps: float = 2e-5                    # |delta| (m, rad) below which a level stops
    coarse_convergence_px: float = 0.1               # update (in the level's pixels) below which a coarse level stops
    affine_brightness: bool = False                  # estimate a brightness gain and bias per pair (exposure)
    brightness_prior_sigma: float = 0.1              # std of the gain (about 1) and bias (about 0, intensity 0..1)
    # keyframes: frames are aligned against the last keyframe, whose gradients, points and Jacobians are computed
    # once; the current frame becomes the next keyframe after this many frames (1: frame-to-frame alignment),
    # once it has moved this far from the keyframe, or when its fitness drops below keyframe_min_fitness
    keyframe_max_frames: int = 8
    keyframe_max_translation_m: float = 0.1
    keyframe_max_rotation_rad: float = 0.087         # 5 degrees
    keyframe_min_fitness: float = 0.7
    register_depth_in_time: bool = True              # turn an unsynchronised depth image to the colour instant


@dataclass(frozen=True)
class PairResult:
    """Motion between two frames: ``T_ck_ckm1`` maps points of frame k-1 into frame k."""

    T_ck_ckm1: Mat4
    ok: bool
    fitness: float          # inlier share of the finest level's reference points
    rmse_intensity: float   # RMS photometric residual of the inliers (intensity in 0..1)
    points: int
    iterations: int
    gain: float = 1.0       # brightness model of the pair: I_k = gain I_km1 + bias
    bias: float = 0.0


@dataclass(frozen=True)
class OdometryResult:
    """Chained camera pose ``T_c0_ck`` (camera k in the first camera frame) and the last pair's quality."""

    stamp_s: float
    T_c0_ck: Mat4
    T_ckm1_ck: Mat4
    ok: bool
    fitness: float


_I3 = np.eye(3)
_MAX_DEPTH_SLOPE = float(np.tan(np.radians(75.0)))
_INLIER_INTENSITY = 0.06   # photometric error (0..1) below which a finest-level point counts for fitness
_MIN_DEPTH_OFFSET_S = 1e-3  # depth-colour offsets below this count as synchronised (2 rad/s: 0.5 px at QVGA)


def se3_exp(xi: NDArray[np.float64]) -> Mat4:
    """Exponential map of a twist (v, omega) to a 4x4 transform (scalar math: called every iteration)."""
    v0, v1, v2, w0, w1, w2 = np.asarray(xi, dtype=float).tolist()
    t2 = w0 * w0 + w1 * w1 + w2 * w2
    if t2 < 1e-18:
        a, b, c = 1.0, 0.5, 1.0 / 6.0
    else:
        theta = math.sqrt(t2)
        a = math.sin(theta) / theta
        b = (1.0 - math.cos(theta)) / t2
        c = (1.0 - a) / t2
    # W^2 = w w^T - |w|^2 I; R = I + a W + b W^2, V = I + b W + c W^2 (Rodrigues)
    x00, x11, x22 = w0 * w0 - t2, w1 * w1 - t2, w2 * w2 - t2
    x01, x02, x12 = w0 * w1, w0 * w2, w1 * w2
    R = ((1.0 + b * x00, -a * w2 + b * x01, a * w1 + b * x02),
         (a * w2 + b * x01, 1.0 + b * x11, -a * w0 + b * x12),
         (-a * w1 + b * x02, a * w0 + b * x12, 1.0 + b * x22))
    V = ((1.0 + c * x00, -b * w2 + c * x01, b * w1 + c * x02),
         (b * w2 + c * x01, 1.0 + c * x11, -b * w0 + c * x12),
         (-b * w1 + c * x02, b * w0 + c * x12, 1.0 + c * x22))
    t = [Vr[0] * v0 + Vr[1] * v1 + Vr[2] * v2 for Vr in V]
    return np.array([[*R[0], t[0]], [*R[1], t[1]], [*R[2], t[2]], [0.0, 0.0, 0.0, 1.0]])


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


def _turn(rate_rad_s: NDArray[np.float64], depth_offset_s: float) -> NDArray[np.float64] | None:
    """``R_c_d`` of :func:`rotate_depth`: R_c(t) c(t + offset) = exp(offset w^) maps depth-instant points into the
    colour-instant camera; None when it moves the image by less than a tenth of a pixel."""
    w = rate_rad_s * depth_offset_s
    if float(np.linalg.norm(w)) * 300.0 < 0.1:          # ~f at QVGA: under 0.1 px
        return None
    return se3_exp(np.concatenate([np.zeros(3), w]))[:3, :3]


class RgbdOdometry:
    """Keyframe-based direct RGB-D odometry producing the chained camera pose ``T_c0_ck``.

    Each frame is aligned against the current keyframe (``T_ck_kf``), started from the previous frame's pose
    relative to it composed with the constant-velocity guess, and the gyro's rotation since the previous
    frame composed with that pose as the prior. Poses chain over keyframes: ``T_c0_ck = T_c0_kf · T_kf_ck``,
    and the motion since the previous frame is ``T_ckm1_ck = T_ckm1_kf · T_kf_ck``.
    """

    def __init__(self, config: OdometryConfig | None = None) -> None:
        self.config = config or OdometryConfig()
        self._kf: PreparedFrame | None = None    # the keyframe: reference of every alignment
        self._prev: PreparedFrame | None = None  # the previous frame (fallback reference if the keyframe fails)
        self._T_c0_kf = np.eye(4)
        self._T_kf_ckm1 = np.eye(4)              # previous frame in the keyframe
        self._kf_frames = 0                      # frames aligned against the keyframe so far
        self._T_c0_ck = np.eye(4)
        self._stamp_s = 0.0
        self._last_motion: tuple[Mat4, float] | None = None   # last good T_ck_ckm1 and its frame interval
        self.keyframes = 0                       # keyframes taken since the start (statistics)
        self.rejected_jumps = 0                  # alignments refused by max_translation_jump_m

    def reset(self) -> None:
        self._kf = self._prev = None
        self._T_c0_kf = np.eye(4)
        self._T_kf_ckm1 = np.eye(4)
        self._kf_frames = 0
        self._T_c0_ck = np.eye(4)
        self._last_motion = None

    @property
    def T_c0_ck(self) -> Mat4:
        return self._T_c0_ck.copy()

    def process(self, stamp_s: float, rgb: NDArray[np.uint8], depth_m: NDArray[np.float32], K: CameraIntrinsics,
                R_ckm1_ck_prior: NDArray[np.float64] | None = None, depth_offset_s: float = 0.0) -> OdometryResult:
        """Add a frame; ``R_ckm1_ck_prior`` is the camera rotation since the last frame from the gyro;
        ``depth_offset_s`` = depth stamp - colour stamp (``stamp_s``) for sensors whose depth and colour are not
        taken at once (Kinect v1: up to 20 ms): the depth is turned to the colour instant by the rotation rate
        (the gyro's, else the last motion's), see :func:`rotate_depth`.

        If the alignment against the keyframe fails, the previous frame is tried as the reference (when it is
        not the keyframe). A failed alignment keeps the last pose (turned by the gyro's rotation, if any) and
        reports ``ok=False``; the frame becomes the keyframe. The first frame defines C0.
        """
        cfg = self.config
        # an unsynchronised depth image is turned to the colour instant once the rotation rate is known; a frame
        # and its reference must agree (both turned, or both not: then both terms measure the motion between
        # the same instants), so while the keyframe could not be turned the frame is not turned either
        register = abs(depth_offset_s) >= _MIN_DEPTH_OFFSET_S and cfg.register_depth_in_time
        dt_s = stamp_s - self._stamp_s
        rate = self._rotation_rate(dt_s, R_ckm1_ck_prior) if register else None
        turn = register and rate is not None and (self._kf is None or self._kf.depth_at_colour_instant)
        cur = prepare_frame(rgb, depth_m, K, cfg, _turn(rate, depth_offset_s) if turn and rate is not None else None)
        cur.depth_at_colour_instant = turn or not register
        if self._kf is None:
            self._set_keyframe(cur)
            self._prev = cur
            self._stamp_s = stamp_s
            return OdometryResult(stamp_s, self._T_c0_ck.copy(), np.eye(4), True, 1.0)
        T_pred = self._predict(dt_s)                  # T_ck_ckm1 guess
        T_ckm1_kf = inv_T(self._T_kf_ckm1)
        R_kf_ck_prior = None if R_ckm1_ck_prior is None else self._T_kf_ckm1[:3, :3] @ R_ckm1_ck_prior
        pair = self.align(self._kf, cur, R_kf_ck_prior, T_ckm1_kf if T_pred is None else T_pred @ T_ckm1_kf,
                          self._T_kf_ckm1)
        T_kf_ck: Mat4 | None = None
        if pair.ok:
            T_kf_ck = inv_T(pair.T_ck_ckm1)
            T_ckm1_ck = T_ckm1_kf @ T_kf_ck
        elif self._prev is not None and self._prev is not self._kf:
            pair = self.align(self._prev, cur, R_ckm1_ck_prior, T_pred)
            T_ckm1_ck = inv_T(pair.T_ck_ckm1)
        if pair.ok and T_pred is not None and cfg.max_translation_jump_m > 0.0:
            # a multirotor cannot change its velocity by more than a few g: a per-frame translation far from the
            # constant-velocity one is an alignment in a wrong basin, however good its photometric fit
            t_pred = inv_T(T_pred)[:3, 3]
            if float(np.linalg.norm(T_ckm1_ck[:3, 3] - t_pred)) > cfg.max_translation_jump_m:
                self.rejected_jumps += 1
                pair = dataclasses.replace(pair, ok=False)
                T_kf_ck = None
        if not pair.ok:
            T_ckm1_ck = np.eye(4)
            if R_ckm1_ck_prior is not None:
                T_ckm1_ck[:3, :3] = R_ckm1_ck_prior
        self._last_motion = (inv_T(T_ckm1_ck), dt_s) if pair.ok else None
        self._prev = cur
        self._stamp_s = stamp_s
        self._kf_frames += 1
        if T_kf_ck is not None:
            self._T_c0_ck = self._T_c0_kf @ T_kf_ck
            self._T_kf_ckm1 = T_kf_ck
            if self._keyframe_is_due(T_kf_ck, pair.fitness):
                self._set_keyframe(cur)
        else:   # the keyframe failed: this frame, whatever its own pose's quality, becomes the next one
            self._T_c0_ck = self._T_c0_ck @ T_ckm1_ck
            self._set_keyframe(cur)
        if register and not cur.depth_at_colour_instant and self._last_motion is not None:
            # the rate is known now (at the start, after a failure): this frame, turned, becomes the keyframe
            rate = self._rotation_rate(0.0, None)
            if rate is not None:
                cur = prepare_frame(rgb, depth_m, K, cfg, _turn(rate, depth_offset_s))
                cur.depth_at_colour_instant = True
                self._prev = cur
                self._set_keyframe(cur)
        return OdometryResult(stamp_s, self._T_c0_ck.copy(), T_ckm1_ck, pair.ok, pair.fitness)

    def _rotation_rate(self, dt_s: float, R_ckm1_ck_prior: NDArray[np.float64] | None
                       ) -> NDArray[np.float64] | None:
        """The camera's rotation rate (rad/s, camera frame): the gyro's since the last frame when given, else
        the last tracked motion's (constant angular velocity over a few ms); None when unknown."""
        if R_ckm1_ck_prior is not None and self._kf is not None and dt_s > 0.0:
            return so3_log(np.asarray(R_ckm1_ck_prior, dtype=float)) / dt_s
        if self._last_motion is not None and self._last_motion[1] > 0.0:
            T_last, dt = self._last_motion                   # T_ck_ckm1 of the last pair
            return so3_log(T_last[:3, :3].T) / dt            # rotation of T_ckm1_ck per second
        return None

    def _set_keyframe(self, frame: PreparedFrame) -> None:
        self._kf = frame
        self._T_c0_kf = self._T_c0_ck.copy()
        self._T_kf_ckm1 = np.eye(4)
        self._kf_frames = 0
        self.keyframes += 1

    def _keyframe_is_due(self, T_kf_ck: Mat4, fitness: float) -> bool:
        """Whether the current frame should replace the keyframe: enough frames, motion (the overlap shrinks
        and the warp's linearisation about the keyframe degrades) or a fitness drop (occlusions, exposure)."""
        cfg = self.config
        return (self._kf_frames >= cfg.keyframe_max_frames or fitness < cfg.keyframe_min_fitness
                or float(np.linalg.norm(T_kf_ck[:3, 3])) > cfg.keyframe_max_translation_m
                or float(np.linalg.norm(so3_log(T_kf_ck[:3, :3]))) > cfg.keyframe_max_rotation_rad)

    def _predict(self, dt_s: float) -> Mat4 | None:
        """Constant-velocity guess of ``T_ck_ckm1`` (DVO's motion prior as the starting point): the last pair's
        twist scaled to this frame interval; None after a failure or for a non-positive interval."""
        if self._last_motion is None:
            return None
        T_last, dt_last = self._last_motion
        if dt_s <= 0.0 or dt_last <= 0.0:
            return None
        f = min(dt_s / dt_last, 3.0)
        w = so3_log(T_last[:3, :3]) * f
        T = se3_exp(np.concatenate([np.zeros(3), w]))
        T[:3, 3] = T_last[:3, 3] * f
        return T

    def align(self, ref: PreparedFrame, cur: PreparedFrame, R_ckm1_ck_prior: NDArray[np.float64] | None = None,
              T_init: Mat4 | None = None, T_ref_ckm1: Mat4 | None = None) -> PairResult:
        """Estimate ``T_ck_ckm1`` between two prepared frames (coarse to fine Gauss-Newton); the reference
        ``ref`` plays frame k-1 (it is the keyframe in :meth:`process`, the names are those of a pair).

        ``T_ref_ckm1`` (the previous frame in a keyframe reference) makes the per-frame sanity bounds apply to
        the motion since the previous frame, ``T_ck_ref · T_ref_ckm1``, instead of the motion from ``ref``.

        Inverse compositional (Baker & Matthews 2004): the Jacobians are those of the reference frame's
        points and gradients, fixed per level, and an increment ``xi`` updates ``T <- T exp(xi)^-1``. The
        residuals keep their definitions, so a converged solution satisfies the same equations; per
        iteration only the warp, one texture sample and the weights are recomputed.
        """
        cfg = self.config
        T = np.eye(4) if T_init is None else T_init.copy()
        R_prior = None
        if R_ckm1_ck_prior is not None:
            R_prior = np.asarray(R_ckm1_ck_prior, dtype=float).T   # rotation of T_ck_ckm1
            T[:3, :3] = R_prior   # the gyro's rotation is a better start than any guess
        info_prior = 1.0 / cfg.imu_prior_sigma_rad**2
        # brightness I_k = gain I_km1 + bias (auto exposure), estimated with the motion (as DSO's affine model)
        gain, bias = 1.0, 0.0
        info_ab = 1.0 / cfg.brightness_prior_sigma**2
        use_depth = cfg.depth_weight > 0
        n_levels = min(cfg.levels, len(ref.levels), len(cur.levels))
        total_iters = 0
        fitness, rmse_i, n_points = 0.0, math.nan, 0
        for li in range(n_levels - 1, -1, -1):
            k = n_levels - 1 - li  # coarse -> fine index into the per-level tuples
            iters = cfg.iterations[min(k, len(cfg.iterations) - 1)]
            max_pts = cfg.max_points[min(k, len(cfg.max_points) - 1)]
            lc = cur.levels[li]
            rp = ref.reference(li, max_pts, cfg.gradient_fraction, cfg.affine_brightness)
            N = n_points = rp.I.shape[0]
            if N < cfg.min_points:
                if li == 0:
                    fitness = 0.0
                continue
            K = lc.K
            Kf = np.array([[K.fx, 0.0, K.cx], [0.0, K.fy, K.cy], [0.0, 0.0, 1.0]])
            s2_i, s2_z = ref.scales.get(li, (0.0, 0.0))
            s2_imin, s2_zmin = cfg.min_intensity_sigma**2, cfg.min_depth_sigma_m**2
            nu, nu1 = np.float32(cfg.t_dof), np.float32(cfg.t_dof + 1.0)
            # the finest level iterates to convergence_eps; a coarser level only has to land inside the next
            # level's basin and stops once an update moves the points by less than coarse_convergence_px of its
            # own pixels (the next level refines with twice the resolution anyway)
            eps_level = cfg.convergence_eps
            px_per_rad = 0.0 if li == 0 else math.sqrt(K.fx * K.fy)
            J = rp.J
            Jw = np.empty_like(J)
            # both residual kinds in one vector: photometric [0, N), depth [N, 2N)
            nj = 8 if cfg.affine_brightness else 6
            r = J[nj]
            pred = np.empty(N, np.float32)   # reference intensities under the brightness model
            r2 = np.empty(2 * N, np.float32)
            wr = np.empty(2 * N, np.float32)
            use = np.empty(2 * N, bool)   # residual usable (inside, valid depth)
            ok_i, ok_z = use[:N], use[N:]
            Ph = np.empty((3, N), np.float32)
            iz = np.empty(N, np.float32)
            u = np.empty(N, np.float32)
            v = np.empty(N, np.float32)
            evaluated = False
            for _ in range(iters):
                total_iters += 1
                # homogeneous pixels of the warped points: K (R p + t), p homogeneous
                np.matmul((Kf @ T[:3]).astype(np.float32), rp.P, out=Ph)
                z = Ph[2]
                np.greater(z, np.float32(1e-3), out=ok_i)
                np.maximum(z, np.float32(1e-3), out=iz)
                np.reciprocal(iz, out=iz)
                np.multiply(Ph[0], iz, out=u)
                np.multiply(Ph[1], iz, out=v)
                s = _sample(lc.tex, u, v)
                ok_i &= s[:, 3] > 0.999
                n_i = int(np.count_nonzero(ok_i))
                if n_i < cfg.min_points:
                    evaluated = False
                    break
                evaluated = True
                np.greater(s[:, 2], 0.999, out=ok_z)
                ok_z &= ok_i
                ok_z &= rp.z_ok
                n_z = int(np.count_nonzero(ok_z)) if use_depth else 0
                if n_z < cfg.min_points:
                    ok_z[:] = False
                    n_z = 0
                if nj > 6:
                    np.multiply(rp.I, np.float32(gain), out=pred)
                    pred += np.float32(bias)
                    np.subtract(s[:, 0], pred, out=r[:N])
                else:
                    np.subtract(s[:, 0], rp.I, out=r[:N])
                np.subtract(s[:, 1], z, out=r[N:])
                r[N:] *= rp.z_norm
                r *= use
                np.multiply(r, r, out=r2)
                # t-distribution weights with scales re-estimated by fixed-point steps (DVO): 4 from the plain
                # mean square at a level's first iteration against a new reference, then one an iteration from
                # the previous scales (the scales converge with the motion; against a reference aligned before,
                # from its last scales)
                if s2_i <= 0.0:
                    s2_i = max(float(r2[:N].sum(dtype=np.float64)) / n_i, s2_imin)
                    s2_z = max(float(r2[N:].sum(dtype=np.float64)) / max(n_z, 1), s2_zmin)
                    steps = 4
                else:
                    steps = 1
                for step in range(steps + 1):
                    np.multiply(r2[:N], np.float32(1.0 / s2_i), out=wr[:N])
                    np.multiply(r2[N:], np.float32(1.0 / s2_z), out=wr[N:])
                    wr += nu
                    np.divide(nu1, wr, out=wr)
                    if step < steps:
                        s2_i = max(float(np.dot(wr[:N], r2[:N])) / n_i, s2_imin)
                        if n_z:
                            s2_z = max(float(np.dot(wr[N:], r2[N:])) / n_z, s2_zmin)
                wr[:N] *= np.float32(1.0 / s2_i)
                wr[N:] *= np.float32(cfg.depth_weight / s2_z)
                wr *= use
                # normal equations of the linearised residuals r - J xi: one BLAS product gives J^T W J and
                # J^T W r (row 6 of J holds r); solved in float64
                np.multiply(J, wr, out=Jw)
                M = (Jw @ J.T).astype(np.float64)
                H = M[:nj, :nj]
                g = M[:nj, nj].copy()
                if nj > 6:
                    # the brightness model's weak priors: gain about 1, bias about 0 (as DSO)
                    H[6, 6] += info_ab
                    H[7, 7] += info_ab
                    g[6] += info_ab * (1.0 - gain)
                    g[7] -= info_ab * bias
                if R_prior is not None:
                    # prior residual log(R R_prior^T) moves by -R xi_w under T <- T exp(xi)^-1
                    r_p = so3_log(T[:3, :3] @ R_prior.T)
                    H[3:, 3:] += info_prior * _I3
                    g[3:] += info_prior * (T[:3, :3].T @ r_p)
                # symmetric positive definite: Cholesky (cv2.solve is far cheaper than numpy's per call)
                solved, sol = cv2.solve(H, g.reshape(nj, 1), flags=cv2.DECOMP_CHOLESKY)
                if not solved:
                    break
                sol = np.asarray(sol, dtype=np.float64).ravel()
                delta = sol[:6]
                d2 = float(delta @ delta)
                if not math.isfinite(d2):
                    break
                T = T @ se3_exp(-delta)
                if nj > 6:
                    gain += float(sol[6])
                    bias += float(sol[7])
                if d2 < eps_level**2:
                    break
                if px_per_rad and px_per_rad * (math.sqrt(float(delta[3:] @ delta[3:]))
                                                + math.sqrt(float(delta[:3] @ delta[:3])) / rp.z_med) \
                        < cfg.coarse_convergence_px:
                    break
            if evaluated:
                ref.scales[li] = (s2_i, s2_z)
            if li == 0:
                # quality of the last evaluated iteration (the final update is below the convergence limit)
                if evaluated:
                    inl = ok_i & (r2[:N] < np.float32(_INLIER_INTENSITY**2))
                    n_inl = int(np.count_nonzero(inl))
                    fitness = n_inl / N
                    rmse_i = math.sqrt(float(np.dot(r2[:N], inl)) / n_inl) if n_inl else math.nan
                else:
                    fitness = 0.0
        T_step = T if T_ref_ckm1 is None else T @ T_ref_ckm1   # the motion since the previous frame
        ok = (fitness >= cfg.min_fitness and n_points >= cfg.min_points
              and bool(np.all(np.isfinite(T)))
              and float(np.linalg.norm(T_step[:3, 3])) <= cfg.max_translation_m
              and float(np.linalg.norm(so3_log(T_step[:3, :3]))) <= cfg.max_rotation_rad)
        return PairResult(T, ok, fitness, rmse_i, n_points, total_iters, gain, bias)

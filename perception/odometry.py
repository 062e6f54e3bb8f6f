"""Dense RGB-D odometry in the spirit of DVO (Kerl, Sturm, Cremers, IROS 2013) — pure numpy/OpenCV.

Frame-to-frame direct alignment: for a selection of reference pixels (strong intensity gradient plus an
even spread for the depth term) with valid depth, find the rigid motion ``T_ck_ckm1`` (points of frame
k-1 into frame k) minimising

    sum_i  w_I,i (r_I,i / s_I)^2 + lambda_Z  w_Z,i (r_Z,i / s_Z)^2  +  |log(R R_prior^T)|^2 / sigma_prior^2

with photometric residuals ``r_I = I_k(pi(T p_i)) - I_km1(x_i)``, depth residuals
``r_Z = Z_k(pi(T p_i)) - [T p_i]_z``, t-distribution weights (nu = 5) with the scales ``s_I, s_Z``
re-estimated each iteration (DVO's robust estimator), an optional rotation prior from the integrated gyro
(the IMU prior between frames), Gauss-Newton on a left se(3) increment, coarse-to-fine over an image
pyramid. The camera pose is chained: ``T_c0_ck = T_c0_ckm1 · T_ck_ckm1^-1``.

Everything is vectorised: warped samples come from ``cv2.remap`` on a 1×N map (bilinear, with a validity
channel so no sample mixes invalid depth), Jacobians are closed-form rows.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from quadlink.camera import CameraIntrinsics

Mat4 = NDArray[np.float64]


@dataclass(frozen=True)
class OdometryConfig:
    """Parameters of the direct RGB-D odometry (defaults tuned on TUM fr1 and the SITL, QVGA)."""

    levels: int = 3                                  # pyramid levels (finest = input resolution)
    iterations: tuple[int, ...] = (10, 6, 3)         # Gauss-Newton iterations per level, coarse -> fine
    max_points: tuple[int, ...] = (600, 1200, 4000)  # selected reference pixels per level, coarse -> fine
    working_width_px: int = 320                      # frames wider than this are downscaled first (QVGA)
    min_depth_m: float = 0.2
    max_depth_m: float = 6.0
    depth_weight: float = 0.3                        # lambda_Z: weight of the (normalised) depth term
    t_dof: float = 5.0                               # nu of the t-distribution weights (DVO)
    min_intensity_sigma: float = 0.004               # floors of the robust scales (about one grey level and
    min_depth_sigma_m: float = 0.0002                # a structured-light sensor's noise at 1 m) so exact
                                                     # data cannot make one term drown the other
    gradient_fraction: float = 0.75                  # share of the points picked by intensity gradient
    imu_prior_sigma_rad: float = 0.01                # std of the gyro rotation prior between frames
    min_fitness: float = 0.3                         # inlier share below which the result is not ok
    min_points: int = 100
    max_translation_m: float = 0.5                   # per-frame sanity bounds
    max_rotation_rad: float = 0.6
    convergence_eps: float = 2e-5                    # |delta| (m, rad) below which the finest level stops


@dataclass(frozen=True)
class PairResult:
    """Motion between two frames: ``T_ck_ckm1`` maps points of frame k-1 into frame k."""

    T_ck_ckm1: Mat4
    ok: bool
    fitness: float          # inlier share of the finest level's reference points
    rmse_intensity: float   # RMS photometric residual of the inliers (intensity in 0..1)
    points: int
    iterations: int


@dataclass(frozen=True)
class OdometryResult:
    """Chained camera pose ``T_c0_ck`` (camera k in the first camera frame) and the last pair's quality."""

    stamp_s: float
    T_c0_ck: Mat4
    T_ckm1_ck: Mat4
    ok: bool
    fitness: float


_I3 = np.eye(3)


def se3_exp(xi: NDArray[np.float64]) -> Mat4:
    """Exponential map of a twist (v, omega) to a 4x4 transform."""
    v = xi[:3]
    w0, w1, w2 = float(xi[3]), float(xi[4]), float(xi[5])
    theta = math.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
    W = np.array([[0.0, -w2, w1], [w2, 0.0, -w0], [-w1, w0, 0.0]])
    if theta < 1e-9:
        R = _I3 + W
        V = _I3 + 0.5 * W
    else:
        a = math.sin(theta) / theta
        b = (1.0 - math.cos(theta)) / theta**2
        c = (1.0 - a) / theta**2
        W2 = W @ W
        R = _I3 + a * W + b * W2
        V = _I3 + b * W + c * W2
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = V @ v
    return T


def so3_log(R: NDArray[np.float64]) -> NDArray[np.float64]:
    """Rotation vector of a rotation matrix."""
    c = max(-1.0, min(1.0, (float(np.trace(R)) - 1.0) / 2.0))
    theta = math.acos(c)
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if theta < 1e-7:
        return 0.5 * w
    if math.pi - theta < 1e-5:
        rv, _ = cv2.Rodrigues(R)
        return np.asarray(rv, dtype=float).ravel()
    return theta / (2.0 * math.sin(theta)) * w


def inv_T(T: Mat4) -> Mat4:
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


Image = NDArray[Any]   # float32 images (OpenCV's stubs type them loosely)


@dataclass
class _Level:
    K: CameraIntrinsics
    intensity_tex: Image   # H×W×4: I, dI/du, dI/dv, 1
    depth_tex: Image       # H×W×4: Z, dZ/du, dZ/dv, valid (eroded)
    gray: Image
    depth: Image
    grad_mag: Image


@dataclass
class PreparedFrame:
    """A frame's pyramid (finest first) with gradient textures, computed once and reused as reference."""

    levels: list[_Level] = field(default_factory=list)


def _gray01(rgb: NDArray[np.uint8]) -> Image:
    return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float32) * np.float32(1.0 / 255.0)


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
    out = np.zeros_like(s)
    np.divide(s, n, out=out, where=n > 0)
    return out


_KERNEL3 = np.ones((3, 3), np.uint8)
_ONES: dict[tuple[int, ...], NDArray[np.float32]] = {}


def _ones(shape: tuple[int, ...]) -> NDArray[np.float32]:
    if shape not in _ONES:
        _ONES[shape] = np.ones(shape, np.float32)
    return _ONES[shape]


def prepare_frame(rgb: NDArray[np.uint8], depth_m: NDArray[np.float32], K: CameraIntrinsics,
                  config: OdometryConfig) -> PreparedFrame:
    """Pyramids, gradients and remap textures of one frame (finest level first)."""
    gray = _gray01(rgb)
    d = np.asarray(depth_m, dtype=np.float32)
    # NaN and inf fail both comparisons: one pass turns them and out-of-range depths into 0 (invalid)
    depth = np.where((d >= config.min_depth_m) & (d <= config.max_depth_m), d, np.float32(0.0))
    if gray.shape[1] > config.working_width_px:
        factor = config.working_width_px / gray.shape[1]
        size = (config.working_width_px, round(gray.shape[0] * factor))
        gray = cv2.resize(gray, size, interpolation=cv2.INTER_AREA)
        while depth.shape[1] >= 2 * size[0]:
            depth = _downsample_depth(depth)
        if depth.shape[1] != size[0]:
            depth = cv2.resize(depth, size, interpolation=cv2.INTER_NEAREST)
        K = K.scaled(factor)
    out = PreparedFrame()
    for lvl in range(config.levels):
        if lvl > 0:
            # 2x2 block means for intensity and depth alike, so K.scaled(0.5) is exact for both
            gray = cv2.resize(gray, (gray.shape[1] // 2, gray.shape[0] // 2), interpolation=cv2.INTER_AREA)
            depth = _downsample_depth(depth)
            if depth.shape != gray.shape:
                depth = cv2.resize(depth, (gray.shape[1], gray.shape[0]), interpolation=cv2.INTER_NEAREST)
            K = K.scaled(0.5)
        gx = cv2.Sobel(gray, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
        gy = cv2.Sobel(gray, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
        valid_e = cv2.erode((depth > 0).view(np.uint8), _KERNEL3).astype(np.float32)
        zx = cv2.multiply(cv2.Sobel(depth, cv2.CV_32F, 1, 0, ksize=3, scale=0.125), valid_e)
        zy = cv2.multiply(cv2.Sobel(depth, cv2.CV_32F, 0, 1, ksize=3, scale=0.125), valid_e)
        out.levels.append(_Level(
            K=K,
            intensity_tex=cv2.merge([gray, gx, gy, _ones(gray.shape)]),
            depth_tex=cv2.merge([depth, zx, zy, valid_e]),
            gray=gray, depth=depth, grad_mag=np.abs(gx) + np.abs(gy)))
    return out


def _select_points(level: _Level, max_points: int, gradient_fraction: float
                   ) -> tuple[NDArray[np.float64], Image]:
    """Reference points (N×3, camera frame) and their intensities: strongest gradients plus an even spread."""
    d = level.depth
    valid = d > 0
    # skip a 2-pixel border where gradients are one-sided
    valid[:2, :] = False
    valid[-2:, :] = False
    valid[:, :2] = False
    valid[:, -2:] = False
    idx = np.flatnonzero(valid)
    if idx.size > max_points:
        g = level.grad_mag.ravel()[idx]
        n_grad = int(max_points * gradient_fraction)
        top = np.argpartition(-g, n_grad)[:n_grad]
        rest_mask = np.ones(idx.size, bool)
        rest_mask[top] = False
        rest = np.flatnonzero(rest_mask)
        n_rest = max_points - n_grad
        spread = rest[np.linspace(0, rest.size - 1, n_rest).astype(np.intp)] if rest.size > n_rest else rest
        idx = idx[np.concatenate([top, spread])]
    w = d.shape[1]
    v, u = np.divmod(idx, w)
    z = d.ravel()[idx].astype(np.float64)
    K = level.K
    pts = np.column_stack([(u - K.cx) / K.fx * z, (v - K.cy) / K.fy * z, z])
    return pts, level.gray.ravel()[idx]


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


def _t_weights_masked(r2: NDArray[np.float32], n_valid: int, nu: float, s2_start: float, s2_min: float,
                      out: NDArray[np.float32]) -> float:
    """t-distribution weights (DVO) of squared residuals ``r2`` into ``out``; returns the scale s^2.

    Invalid entries have ``r2 = 0`` and are not counted in ``n_valid``. The scale is re-estimated by a few
    fixed-point steps (4 from the plain mean square, 2 from the previous iteration's scale).
    """
    s2 = s2_start if s2_start > 0 else max(float(r2.sum(dtype=np.float64)) / n_valid, s2_min)
    a = np.float32(nu + 1.0)
    for _ in range(2 if s2_start > 0 else 4):
        np.multiply(r2, np.float32(1.0 / s2), out=out)
        out += np.float32(nu)
        np.divide(a, out, out=out)
        s2 = max(float(np.dot(out, r2)) / n_valid, s2_min)
    np.multiply(r2, np.float32(1.0 / s2), out=out)
    out += np.float32(nu)
    np.divide(a, out, out=out)
    return s2


def _fill_rows(out: NDArray[np.float32], x: NDArray[np.float32], y: NDArray[np.float32], z: NDArray[np.float32],
               iz: NDArray[np.float32], a: NDArray[np.float32], b: NDArray[np.float32], dz: float,
               tmp: NDArray[np.float32]) -> None:
    """Write the 6 × N Jacobian rows (left se(3) increment) of a residual with pixel gradient scaled by
    ``f/z``: ``a = g_u f_x / z``, ``b = g_v f_y / z``; ``dz`` is the residual's direct d/dz (-1 for depth).

    ``a`` and ``b`` may alias ``out[0]`` and ``out[1]``; ``tmp`` is scratch of length N."""
    c = out[2]
    np.multiply(a, x, out=c)
    np.multiply(b, y, out=tmp)
    c += tmp
    c *= iz
    np.negative(c, out=c)
    if dz:
        c += np.float32(dz)
    if a is not out[0]:
        out[0] = a
    if b is not out[1]:
        out[1] = b
    np.multiply(y, c, out=out[3])       # P x g
    np.multiply(z, b, out=tmp)
    out[3] -= tmp
    np.multiply(z, a, out=out[4])
    np.multiply(x, c, out=tmp)
    out[4] -= tmp
    np.multiply(x, b, out=out[5])
    np.multiply(y, a, out=tmp)
    out[5] -= tmp


class RgbdOdometry:
    """Frame-to-frame direct RGB-D odometry producing the chained camera pose ``T_c0_ck``."""

    def __init__(self, config: OdometryConfig | None = None) -> None:
        self.config = config or OdometryConfig()
        self._ref: PreparedFrame | None = None
        self._T_c0_ck = np.eye(4)

    def reset(self) -> None:
        self._ref = None
        self._T_c0_ck = np.eye(4)

    @property
    def T_c0_ck(self) -> Mat4:
        return self._T_c0_ck.copy()

    def process(self, stamp_s: float, rgb: NDArray[np.uint8], depth_m: NDArray[np.float32], K: CameraIntrinsics,
                R_ckm1_ck_prior: NDArray[np.float64] | None = None) -> OdometryResult:
        """Add a frame; ``R_ckm1_ck_prior`` is the camera rotation since the last frame from the gyro.

        A failed alignment keeps the last pose (and drops the reference to this frame) and reports
        ``ok=False``; the first frame defines C0.
        """
        cur = prepare_frame(rgb, depth_m, K, self.config)
        if self._ref is None:
            self._ref = cur
            return OdometryResult(stamp_s, self._T_c0_ck.copy(), np.eye(4), True, 1.0)
        pair = self.align(self._ref, cur, R_ckm1_ck_prior)
        self._ref = cur
        if pair.ok:
            T_ckm1_ck = inv_T(pair.T_ck_ckm1)
        elif R_ckm1_ck_prior is not None:
            T_ckm1_ck = np.eye(4)
            T_ckm1_ck[:3, :3] = R_ckm1_ck_prior
        else:
            T_ckm1_ck = np.eye(4)
        self._T_c0_ck = self._T_c0_ck @ T_ckm1_ck
        return OdometryResult(stamp_s, self._T_c0_ck.copy(), T_ckm1_ck, pair.ok, pair.fitness)

    def align(self, ref: PreparedFrame, cur: PreparedFrame, R_ckm1_ck_prior: NDArray[np.float64] | None = None,
              T_init: Mat4 | None = None) -> PairResult:
        """Estimate ``T_ck_ckm1`` between two prepared frames (coarse to fine Gauss-Newton)."""
        cfg = self.config
        T = np.eye(4) if T_init is None else T_init.copy()
        R_prior = None
        if R_ckm1_ck_prior is not None:
            R_prior = np.asarray(R_ckm1_ck_prior, dtype=float).T   # rotation of T_ck_ckm1
            if T_init is None:
                T[:3, :3] = R_prior
        info_prior = 1.0 / cfg.imu_prior_sigma_rad**2
        use_depth = cfg.depth_weight > 0
        n_levels = min(cfg.levels, len(ref.levels), len(cur.levels))
        total_iters = 0
        fitness, rmse_i, n_points = 0.0, math.nan, 0
        for li in range(n_levels - 1, -1, -1):
            k = n_levels - 1 - li  # coarse -> fine index into the per-level tuples
            iters = cfg.iterations[min(k, len(cfg.iterations) - 1)]
            max_pts = cfg.max_points[min(k, len(cfg.max_points) - 1)]
            lr, lc = ref.levels[li], cur.levels[li]
            P0, I0 = _select_points(lr, max_pts, cfg.gradient_fraction)
            n_points = P0.shape[0]
            if n_points < cfg.min_points:
                continue
            K = lc.K
            s2_i = s2_z = 0.0
            eps_level = cfg.convergence_eps * (2.0**li)   # coarse levels only need to land in the basin
            N = n_points
            P0t = np.ascontiguousarray(P0.T, dtype=np.float32)   # 3×N rows: contiguous float32 vector ops
            I0f = I0.astype(np.float32)
            fx, fy = np.float32(K.fx), np.float32(K.fy)
            cx, cy = np.float32(K.cx), np.float32(K.cy)
            # one Jacobian for both residual kinds: rows [0, N) photometric, [N, 2N) depth (6 × 2N, row-major),
            # float32 (the 6×6 normal equations are accumulated by BLAS and solved in float64)
            J = np.empty((6, 2 * N), np.float32)
            Jw = np.empty_like(J)
            r = np.empty(2 * N, np.float32)
            r2 = np.empty(2 * N, np.float32)
            wr = np.empty(2 * N, np.float32)
            P = np.empty((3, N), np.float32)
            iz = np.empty(N, np.float32)
            u = np.empty(N, np.float32)
            v = np.empty(N, np.float32)
            tmp = np.empty(N, np.float32)
            for _ in range(iters):
                total_iters += 1
                np.matmul(T[:3, :3].astype(np.float32), P0t, out=P)
                P += T[:3, 3:4].astype(np.float32)
                x, y, z = P[0], P[1], P[2]
                front = z > 1e-3
                np.maximum(z, np.float32(1e-3), out=iz)
                np.divide(np.float32(1.0), iz, out=iz)
                np.multiply(x, iz, out=u)
                u *= fx
                u += cx
                np.multiply(y, iz, out=v)
                v *= fy
                v += cy
                si = _sample(lc.intensity_tex, u, v)
                sd = _sample(lc.depth_tex, u, v)
                ok_i = (si[:, 3] > 0.999) & front
                n_i = int(np.count_nonzero(ok_i))
                if n_i < cfg.min_points:
                    break
                ok_z = ok_i & (sd[:, 3] > 0.999) if use_depth else np.zeros(N, bool)
                n_z = int(np.count_nonzero(ok_z))
                ri, wi = r[:N], wr[:N]
                np.subtract(si[:, 0], I0f, out=ri)
                ri *= ok_i
                np.multiply(ri, ri, out=r2[:N])
                s2_i = _t_weights_masked(r2[:N], n_i, cfg.t_dof, s2_i, cfg.min_intensity_sigma**2, wi)
                wi *= ok_i
                wi *= np.float32(1.0 / s2_i)
                np.multiply(iz, fx, out=u)     # u, v are free after sampling: f/z
                np.multiply(iz, fy, out=v)
                Ji = J[:, :N]
                np.multiply(si[:, 1], u, out=Ji[0])
                np.multiply(si[:, 2], v, out=Ji[1])
                _fill_rows(Ji, x, y, z, iz, Ji[0], Ji[1], 0.0, tmp)
                if n_z >= cfg.min_points:
                    rz, wz = r[N:], wr[N:]
                    np.subtract(sd[:, 0], z, out=rz)
                    rz *= ok_z
                    np.multiply(rz, rz, out=r2[N:])
                    s2_z = _t_weights_masked(r2[N:], n_z, cfg.t_dof, s2_z, cfg.min_depth_sigma_m**2, wz)
                    wz *= ok_z
                    wz *= np.float32(cfg.depth_weight / s2_z)
                    Jz = J[:, N:]
                    np.multiply(sd[:, 1], u, out=Jz[0])
                    np.multiply(sd[:, 2], v, out=Jz[1])
                    _fill_rows(Jz, x, y, z, iz, Jz[0], Jz[1], -1.0, tmp)
                else:
                    r[N:] = 0.0
                    wr[N:] = 0.0
                    J[:, N:] = 0.0
                np.multiply(J, wr, out=Jw)
                H = (Jw @ J.T).astype(np.float64)
                g = (Jw @ r).astype(np.float64)
                if R_prior is not None:
                    r_p = so3_log(T[:3, :3] @ R_prior.T)
                    H[3:, 3:] += info_prior * _I3
                    g[3:] += info_prior * r_p
                # 6×6 symmetric positive definite: Cholesky (cv2.solve is far cheaper than numpy's per call)
                solved, sol = cv2.solve(H, -g.reshape(6, 1), flags=cv2.DECOMP_CHOLESKY)
                if not solved:
                    break
                delta = np.asarray(sol, dtype=np.float64).ravel()
                if not np.all(np.isfinite(delta)):
                    break
                T = se3_exp(delta) @ T
                if float(delta @ delta) < eps_level**2:
                    break
            if li == 0:
                fitness, rmse_i = self._quality(P0, I0, lc, T)
        ok = (fitness >= cfg.min_fitness and n_points >= cfg.min_points
              and float(np.linalg.norm(T[:3, 3])) <= cfg.max_translation_m
              and float(np.linalg.norm(so3_log(T[:3, :3]))) <= cfg.max_rotation_rad
              and bool(np.all(np.isfinite(T))))
        return PairResult(T, ok, fitness, rmse_i, n_points, total_iters)

    @staticmethod
    def _quality(P0: NDArray[np.float64], I0: NDArray[np.float64], lc: _Level, T: Mat4,
                 inlier_intensity: float = 0.06) -> tuple[float, float]:
        """Share of reference points landing inside with a photometric error below ``inlier_intensity``."""
        K = lc.K
        h, w = lc.gray.shape
        P = P0 @ T[:3, :3].T + T[:3, 3]
        front = P[:, 2] > 1e-3
        z = np.where(front, P[:, 2], 1.0)
        u = (K.fx * P[:, 0] / z + K.cx).astype(np.float32)
        v = (K.fy * P[:, 1] / z + K.cy).astype(np.float32)
        inside = front & (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
        si = _sample(lc.intensity_tex, u, v)[:, 0]
        r = np.abs(si.astype(np.float64) - I0)
        inl = inside & (r < inlier_intensity)
        if P0.shape[0] == 0:
            return 0.0, math.nan
        rmse = float(np.sqrt(np.mean(r[inl] ** 2))) if inl.any() else math.nan
        return float(inl.mean()), rmse

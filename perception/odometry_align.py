"""Photometric and geometric alignment of one frame against a reference (:mod:`perception.odometry`'s pair step).

:func:`align_pair` estimates ``T_ck_ckm1`` between two prepared frames (:mod:`perception.odometry_frame`):
robust (t-distribution) photometric and depth residuals, an optional gyro rotation prior and an optional affine
brightness model, minimised by inverse-compositional Gauss-Newton on se(3), coarse to fine. Warped samples come
from one ``cv2.remap`` per iteration of the 4-channel texture, so no sample mixes invalid depth.
:func:`se3_exp` is the exponential map of its update (scalar math: called every iteration).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from perception.odometry_config import OdometryConfig
from perception.odometry_frame import PreparedFrame, _sample
from quadlink.lie import so3_log

__all__ = ["Mat4", "PairResult", "align_pair", "se3_exp"]

Mat4 = NDArray[np.float64]


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
    # Gauss-Newton information (6×6, 1/m² and 1/rad²) of the finest level's last iteration about the twist
    # xi of T_km1_k <- exp(xi) T_km1_k (the inverse-compositional update); None if not evaluated
    information: NDArray[np.float64] | None = None


_I3 = np.eye(3)


def _skew(v: NDArray[np.float64]) -> NDArray[np.float64]:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
_INLIER_INTENSITY = 0.06   # photometric error (0..1) below which a finest-level point counts for fitness


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


_MAX_DEPTH_SCALE = 3.0   # Kinect v1: offsets within +-20 ms of frames 33 ms apart give 0..2


def _depth_translation_scale(ref: PreparedFrame, cur: PreparedFrame) -> float:
    """The depth images' translation over the colour images' between two frames whose depth images were taken
    ``depth_offset_s`` from their colour images: at constant velocity the camera moves ``v (dt + d_cur - d_ref)``
    between the depth instants and ``v dt`` between the colour ones (the rotation is registered per frame by
    rotate_depth); 1 when synchronised or the interval is unknown."""
    dt = cur.stamp_s - ref.stamp_s
    d = cur.depth_offset_s - ref.depth_offset_s
    if d == 0.0 or dt <= 1e-3:
        return 1.0
    return float(np.clip(1.0 + d / dt, 0.0, _MAX_DEPTH_SCALE))


def align_pair(ref: PreparedFrame, cur: PreparedFrame, config: OdometryConfig,
               R_ckm1_ck_prior: NDArray[np.float64] | None = None, T_init: Mat4 | None = None,
               T_ref_ckm1: Mat4 | None = None, T_motion_prior: Mat4 | None = None) -> PairResult:
    """Estimate ``T_ck_ckm1`` between two prepared frames (coarse to fine Gauss-Newton); the reference
    ``ref`` plays frame k-1 (it is the keyframe in :meth:`perception.odometry.RgbdOdometry.process`, the names
    are those of a pair).

    ``T_ref_ckm1`` (the previous frame in a keyframe reference) makes the per-frame sanity bounds apply to
    the motion since the previous frame, ``T_ck_ref · T_ref_ckm1``, instead of the motion from ``ref``.

    Frames whose depth images were not taken at their colour instants (``depth_offset_s`` on the frames; their
    rotation is registered per frame by :func:`perception.odometry_frame.rotate_depth`) have the depth term compare
    the two depth instants' geometry: at constant velocity between the frames its translation is
    ``(dt + d_cur - d_ref) / dt`` times the colour images' (:func:`_depth_translation_scale`).

    ``T_motion_prior`` (a prediction of the result ``T_ck_ref``, the constant-velocity one) adds DVO's motion
    prior on the translation: ``|t(T T_prior^-1)|^2 / motion_prior_sigma_m^2`` (Kerl, Sturm, Cremers 2013, the
    prior term of their MAP estimate; here on the translation only, which the photometric term pins least).

    Inverse compositional (Baker & Matthews 2004): the Jacobians are those of the reference frame's
    points and gradients, fixed per level, and an increment ``xi`` updates ``T <- T exp(xi)^-1``. The
    residuals keep their definitions, so a converged solution satisfies the same equations; per
    iteration only the warp, one texture sample and the weights are recomputed.
    """
    cfg = config
    T = np.eye(4) if T_init is None else T_init.copy()
    depth_scale = _depth_translation_scale(ref, cur)
    R_prior = None
    if R_ckm1_ck_prior is not None:
        # the nearest rotation (SVD): a prior composed of rounded or calibrated matrices is off SO(3) by ~1e-6
        # per frame, and a start that is not rigid stays so (the updates are rigid) and accumulates along the
        # keyframe chain
        U, _, Vt = np.linalg.svd(np.asarray(R_ckm1_ck_prior, dtype=float))
        R_prior = (U @ Vt).T   # rotation of T_ck_ckm1
        T[:3, :3] = R_prior   # the gyro's rotation is a better start than any guess
    info_prior = 1.0 / cfg.imu_prior_sigma_rad**2
    T_mp = T_motion_prior if T_motion_prior is not None and cfg.motion_prior_sigma_m > 0.0 else None
    info_motion = 1.0 / cfg.motion_prior_sigma_m**2 if T_mp is not None else 0.0
    # brightness I_k = gain I_km1 + bias (auto exposure), estimated with the motion (as DSO's affine model)
    gain, bias = 1.0, 0.0
    info_ab = 1.0 / cfg.brightness_prior_sigma**2
    use_depth = cfg.depth_weight > 0
    n_levels = min(cfg.levels, len(ref.levels), len(cur.levels))
    total_iters = 0
    fitness, rmse_i, n_points = 0.0, math.nan, 0
    information: NDArray[np.float64] | None = None
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
        if depth_scale != 1.0:
            # the depth term's translation is depth_scale times the colour images': its Jacobian's translation
            # columns scale with it (a right perturbation p -> p - w x p - v moves the depth warp by p - w x p - s v)
            J = J.copy()
            J[:3, N:] *= np.float32(depth_scale)
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
            if depth_scale != 1.0:
                # the depth images' points, moved by the depth instants' translation: K (R p + s t)
                Ph_d = Ph + (Kf @ ((depth_scale - 1.0) * T[:3, 3])).astype(np.float32)[:, None]
                z = Ph_d[2]   # the depth residual's predicted depth: the depth instant's
                izd = np.reciprocal(np.maximum(z, np.float32(1e-3)))
                s_d = _sample(lc.tex, Ph_d[0] * izd, Ph_d[1] * izd)
                np.greater(s_d[:, 2], 0.999, out=ok_z)
                ok_z &= s_d[:, 3] > 0.999
                depth_samples = s_d[:, 1]
            else:
                np.greater(s[:, 2], 0.999, out=ok_z)
                depth_samples = s[:, 1]
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
            np.subtract(depth_samples, z, out=r[N:])
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
            if T_mp is not None:
                # translation of E = T T_mp^-1 moves under T <- T exp(xi)^-1 = exp(-Ad_T xi) T by -A xi, A the
                # translation rows of Ad_T: [R, [t]x R]
                R_T, t_T = T[:3, :3], T[:3, 3]
                r_m = t_T - R_T @ T_mp[:3, :3].T @ T_mp[:3, 3]
                A = np.hstack([R_T, _skew(t_T) @ R_T])
                H[:6, :6] += info_motion * (A.T @ A)
                g[:6] += info_motion * (A.T @ r_m)
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
                information = H[:6, :6].copy()
                rmse_i = math.sqrt(float(np.dot(r2[:N], inl)) / n_inl) if n_inl else math.nan
            else:
                fitness = 0.0
    T_step = T if T_ref_ckm1 is None else T @ T_ref_ckm1   # the motion since the previous frame
    ok = (fitness >= cfg.min_fitness and n_points >= max(cfg.min_points, cfg.min_reference_points)
          and bool(np.all(np.isfinite(T)))
          and float(np.linalg.norm(T_step[:3, 3])) <= cfg.max_translation_m
          and float(np.linalg.norm(so3_log(T_step[:3, :3]))) <= cfg.max_rotation_rad)
    return PairResult(T, ok, fitness, rmse_i, n_points, total_iters, gain, bias, information)

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

Modules: the parameters in :mod:`perception.odometry_config`, frame preparation (pyramids, textures, gradients,
reference points) in :mod:`perception.odometry_frame`, the pair alignment in :mod:`perception.odometry_align`,
and the keyframe tracker :class:`RgbdOdometry` here; every public name is importable from this module.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from perception.odometry_align import Mat4, PairResult, align_pair, se3_exp
from perception.odometry_config import OdometryConfig
from perception.odometry_frame import Image, PreparedFrame, prepare_frame, rotate_depth
from quadlink.camera_frame import CameraIntrinsics
from quadlink.lie import inv_T, skew, so3_log

__all__ = ["Image", "Mat4", "OdometryConfig", "OdometryCounts", "OdometryResult", "PairResult", "PreparedFrame",
           "RgbdOdometry", "prepare_frame", "rotate_depth", "se3_exp"]


@dataclass(frozen=True)
class OdometryCounts:
    """What the odometry did with the frames that were not plainly aligned, since it started: bridged by the
    motion prior (``fallbacks``), held without one (``lost``), alignments refused by the jump gate
    (``rejected_jumps``) and frames aligned again from rest (``restarts``)."""

    fallbacks: int = 0
    lost: int = 0
    rejected_jumps: int = 0
    restarts: int = 0

    def summary(self) -> str:
        return (f"bridged {self.fallbacks}, held {self.lost}, jumps refused {self.rejected_jumps}, "
                f"restarts {self.restarts}")

    def since(self, earlier: OdometryCounts) -> OdometryCounts:
        """The frames counted since ``earlier`` (a counter that went down was reset in between: all of its count is
        new)."""
        def d(now: int, then: int) -> int:
            return now - then if now >= then else now
        return OdometryCounts(d(self.fallbacks, earlier.fallbacks), d(self.lost, earlier.lost),
                              d(self.rejected_jumps, earlier.rejected_jumps), d(self.restarts, earlier.restarts))

    def plus(self, other: OdometryCounts) -> OdometryCounts:
        return OdometryCounts(self.fallbacks + other.fallbacks, self.lost + other.lost,
                              self.rejected_jumps + other.rejected_jumps, self.restarts + other.restarts)


@dataclass(frozen=True)
class OdometryResult:
    """Chained camera pose ``T_c0_ck`` (camera k in the first camera frame) and the last pair's quality.

    ``ok``: the frame was aligned. A frame whose alignment failed or was refused is not ok; its motion
    ``T_ckm1_ck`` is then the motion prior's when there is one (``fallback``: the gyro's rotation and the
    constant-velocity translation, or the constant-velocity motion alone), else the identity (the pose holds).
    """

    stamp_s: float
    T_c0_ck: Mat4
    T_ckm1_ck: Mat4
    ok: bool
    fitness: float
    fallback: bool = False


_MIN_DEPTH_OFFSET_S = 1e-3  # depth-colour offsets below this count as synchronised (2 rad/s: 0.5 px at QVGA)


def _turn(rate_rad_s: NDArray[np.float64], depth_offset_s: float) -> NDArray[np.float64] | None:
    """``R_c_d`` of :func:`rotate_depth`: R_c(t) c(t + offset) = exp(offset w^) maps depth-instant points into the
    colour-instant camera; None when it moves the image by less than a tenth of a pixel."""
    w = rate_rad_s * depth_offset_s
    if float(np.linalg.norm(w)) * 300.0 < 0.1:          # ~f at QVGA: under 0.1 px
        return None
    return se3_exp(np.concatenate([np.zeros(3), w]))[:3, :3]


def _covariance(information: NDArray[np.float64] | None) -> NDArray[np.float64] | None:
    """Covariance of an alignment from its Gauss-Newton information; None if missing or singular."""
    if information is None:
        return None
    try:
        return np.asarray(np.linalg.inv(information), dtype=np.float64)
    except np.linalg.LinAlgError:
        return None


def _fusion_step(T_a: Mat4, cov_a: NDArray[np.float64], T_b: Mat4, cov_b: NDArray[np.float64], max_step_m: float
                 ) -> tuple[NDArray[np.float64], NDArray[np.float64]] | None:
    """The left perturbation (in the reference's frame) that takes ``T_a`` to the information-weighted mean of two
    estimates of one pose, and the summed information: ``step`` is the share of ``log(T_b T_a^-1)`` that ``T_b``'s
    information carries. None when the step leaves the segment between them or moves more than ``max_step_m``
    (an ill-conditioned information, an estimate in another basin)."""
    delta = _se3_log(T_b @ inv_T(T_a))
    info_b = np.linalg.inv(cov_b)
    info = np.linalg.inv(cov_a) + info_b
    step = np.asarray(np.linalg.solve(info, info_b @ delta), dtype=np.float64)
    reach_m = min(max_step_m, float(np.linalg.norm(delta[:3])) + 1e-9)
    if not np.all(np.isfinite(step)) or float(np.linalg.norm(step[:3])) > reach_m \
            or float(np.linalg.norm(step[3:])) > float(np.linalg.norm(delta[3:])) + 1e-9:
        return None
    return step, info


def fuse_poses(T_a: Mat4, cov_a: NDArray[np.float64], T_b: Mat4, cov_b: NDArray[np.float64], max_step_m: float
               ) -> tuple[Mat4, NDArray[np.float64]] | None:
    """The information-weighted mean of two estimates of one pose (covariances of left perturbations in the
    reference's frame) and its covariance: ``exp(step) T_a`` (:func:`_fusion_step`; None where it is)."""
    fused = _fusion_step(T_a, cov_a, T_b, cov_b, max_step_m)
    if fused is None:
        return None
    step, info = fused
    return se3_exp(step) @ T_a, np.asarray(np.linalg.inv(info), dtype=np.float64)


def _adjoint(T: Mat4) -> NDArray[np.float64]:
    """6×6 adjoint of ``T`` for twists (v, w): ``T exp(x) T^-1 = exp(Ad x)``; moves a covariance between frames."""
    R = T[:3, :3]
    Ad = np.zeros((6, 6))
    Ad[:3, :3] = Ad[3:, 3:] = R
    Ad[:3, 3:] = skew(T[:3, 3]) @ R
    return Ad


def _se3_log(T: Mat4) -> NDArray[np.float64]:
    """Twist (v, w) of a rigid transform, the inverse of :func:`se3_exp`: ``v = V(w)^-1 t``."""
    w = so3_log(T[:3, :3])
    t2 = float(w @ w)
    W = skew(w)
    if t2 < 1e-12:
        c = 1.0 / 12.0
    else:
        th = math.sqrt(t2)
        c = (1.0 - th * math.sin(th) / (2.0 * (1.0 - math.cos(th)))) / t2
    return np.concatenate([(np.eye(3) - 0.5 * W + c * (W @ W)) @ T[:3, 3], w])


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
        self._kf_prev: PreparedFrame | None = None   # the keyframe before it (second reference of the next one)
        self._T_kfprev_kf = np.eye(4)            # the keyframe in the one before, and that pose's covariance
        self._cov_kfprev_kf = np.zeros((6, 6))   # (twist of a left perturbation, in kf_prev's frame)
        self._prev: PreparedFrame | None = None  # the previous frame (fallback reference if the keyframe fails)
        self._T_c0_kf = np.eye(4)
        self._T_kf_ckm1 = np.eye(4)              # previous frame in the keyframe
        self._cov_kf_ckm1: NDArray[np.float64] | None = None   # its covariance (frame_fusion)
        self._kf_frames = 0                      # frames aligned against the keyframe so far
        self._T_c0_ck = np.eye(4)
        self._stamp_s = 0.0
        self._last_motion: tuple[Mat4, float] | None = None   # last good T_ck_ckm1 and its frame interval
        self.keyframes = 0                       # keyframes taken since the start (statistics)
        self.rejected_jumps = 0                  # alignments refused by max_translation_jump_m
        self.refined_keyframes = 0               # keyframes fused with a second alignment (keyframe_refinement)
        self.rejected_refinements = 0            # fusions refused by the step gate (see _refine)
        self.fallbacks = 0                       # frames not aligned, bridged by the motion prior
        self.restarts = 0                        # frames aligned again from rest (restart_from_rest)
        self.fused_frames = 0                    # frames fused with an alignment against the previous (frame_fusion)
        self.lost = 0                            # frames not aligned and without a motion prior (pose held)
        self._bridged = 0                        # consecutive bridged frames (the constant velocity's age)
        self._bridged_s = 0.0                    # time from the last aligned frame to the previous frame
        self._refused_v_m_s: NDArray[np.float64] | None = None   # the previous frame's alignment, if refused

    def reset(self) -> None:
        self._kf = self._prev = self._kf_prev = None
        self._T_c0_kf = np.eye(4)
        self._T_kf_ckm1 = np.eye(4)
        self._kf_frames = 0
        self._T_c0_ck = np.eye(4)
        self._last_motion = None
        self._bridged = 0
        self._bridged_s = 0.0
        self._refused_v_m_s = None

    @property
    def T_c0_ck(self) -> Mat4:
        return self._T_c0_ck.copy()

    @property
    def counts(self) -> OdometryCounts:
        return OdometryCounts(self.fallbacks, self.lost, self.rejected_jumps, self.restarts)

    def process(self, stamp_s: float, rgb: NDArray[np.uint8], depth_m: NDArray[np.float32], K: CameraIntrinsics,
                R_ckm1_ck_prior: NDArray[np.float64] | None = None, depth_offset_s: float = 0.0) -> OdometryResult:
        """Add a frame; ``R_ckm1_ck_prior`` is the camera rotation since the last frame from the gyro;
        ``depth_offset_s`` = depth stamp - colour stamp (``stamp_s``) for sensors whose depth and colour are not
        taken at once (Kinect v1: up to 20 ms): the depth is turned to the colour instant by the rotation rate
        (the gyro's, else the last motion's), see :func:`rotate_depth`, and the depth term measures the
        translation between the depth instants (``register_depth_translation``, see :func:`align_pair`).

        If the alignment against the keyframe fails, the previous frame is tried as the reference (when it is
        not the keyframe). A frame whose alignment fails or is refused (fast rotation, blur, little depth) reports
        ``ok=False`` and moves by the motion prior (``fallback=True``, counted in ``fallbacks``): the gyro's
        rotation when given, and the constant-velocity prediction of the last aligned motion (its rotation too
        without a gyro), for at most ``max_bridged_frames`` frames in a row; without either the pose holds
        (counted in ``lost``). So the velocity the poses imply does not jump. The frame becomes the keyframe and
        tracking re-initialises from it. The first frame defines C0.
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
        # the depth term compares the depth instants (align_pair) when the depth image is unsynchronised
        depth_term_offset_s = depth_offset_s if register and cfg.register_depth_translation else 0.0
        cur.stamp_s, cur.depth_offset_s = stamp_s, depth_term_offset_s
        if self._kf is None:
            self._set_keyframe(cur)
            self._prev = cur
            self._stamp_s = stamp_s
            return OdometryResult(stamp_s, self._T_c0_ck.copy(), np.eye(4), True, 1.0)
        T_pred = self._predict(dt_s)                  # T_ck_ckm1 guess
        T_ckm1_kf = inv_T(self._T_kf_ckm1)
        R_kf_ck_prior = None if R_ckm1_ck_prior is None else self._T_kf_ckm1[:3, :3] @ R_ckm1_ck_prior
        T_start = T_ckm1_kf if T_pred is None else T_pred @ T_ckm1_kf
        # the constant-velocity prediction is a prior only when it comes from aligned frames
        T_mp = T_start if T_pred is not None and self._bridged == 0 else None
        pair = self.align(self._kf, cur, R_kf_ck_prior, T_start, self._T_kf_ckm1, T_mp)
        restarted = False
        if cfg.restart_from_rest and T_pred is not None and pair.fitness < cfg.keyframe_min_fitness:
            # a poor fit from the constant-velocity start may be a wrong basin that the start itself carries on
            # (a periodic texture: one period a frame, 2 m/s for a 7 cm stripe at 30 Hz, fit after fit): aligned
            # again from rest (the previous frame's pose, the gyro's rotation), a good fit there wins
            alt = self.align(self._kf, cur, R_kf_ck_prior, T_ckm1_kf, self._T_kf_ckm1)
            # from rest, the jump gate's bound applies to the motion itself: no faster than that from standstill
            step_m = float(np.linalg.norm((T_ckm1_kf @ inv_T(alt.T_ck_ckm1))[:3, 3]))
            if alt.ok and alt.fitness >= cfg.keyframe_min_fitness \
                    and (cfg.max_translation_jump_m <= 0.0 or step_m <= cfg.max_translation_jump_m):
                pair, restarted = alt, True
                self.restarts += 1
        T_kf_ck: Mat4 | None = None
        if pair.ok:
            T_kf_ck = inv_T(pair.T_ck_ckm1)
            T_ckm1_ck = T_ckm1_kf @ T_kf_ck
        elif self._prev is not None and self._prev is not self._kf:
            pair = self.align(self._prev, cur, R_ckm1_ck_prior, T_pred)
            T_ckm1_ck = inv_T(pair.T_ck_ckm1)
        refused_v_m_s: NDArray[np.float64] | None = None
        if pair.ok and T_pred is not None and cfg.max_translation_jump_m > 0.0 \
                and not restarted:   # a restart is not measured against the constant velocity it overturns
            # a multirotor cannot change its velocity by more than a few g: a per-frame translation far from the
            # constant-velocity one is an alignment in a wrong basin, however good its photometric fit. Through
            # bridged frames the velocity is the last aligned one carried on, so the bound also holds after them
            t_pred, t_m = inv_T(T_pred)[:3, 3], T_ckm1_ck[:3, 3]
            bound_m = self._jump_bound_m(dt_s)
            # unless the frame before was refused and this one agrees with it: two alignments in a row that
            # agree with each other and not with the carried velocity say the carried one was wrong
            seconded = self._refused_v_m_s is not None \
                and float(np.linalg.norm(t_m - self._refused_v_m_s * dt_s)) <= bound_m
            if float(np.linalg.norm(t_m - t_pred)) > bound_m and not seconded:
                self.rejected_jumps += 1
                pair = dataclasses.replace(pair, ok=False)
                T_kf_ck = None
                refused_v_m_s = t_m / dt_s
        self._refused_v_m_s = refused_v_m_s
        bridged = False
        if pair.ok:
            self._bridged = 0
            self._bridged_s = 0.0
            self._last_motion = (inv_T(T_ckm1_ck), dt_s)
        else:
            T_ckm1_ck, bridged = self._motion_prior(T_pred, R_ckm1_ck_prior)
            if bridged:
                self.fallbacks += 1
                self._bridged += 1
                self._bridged_s += max(dt_s, 0.0)
            else:
                self.lost += 1
            # the constant velocity carries on through bridged frames (and ends with them)
            self._last_motion = (inv_T(T_ckm1_ck), dt_s) if bridged and T_pred is not None else None
        cov_kf_ck_now = None
        if T_kf_ck is not None and cfg.frame_fusion:
            cov_kf_ck_now = _covariance(pair.information)
            if self._prev is not None and self._prev is not self._kf and self._cov_kf_ckm1 is not None \
                    and cov_kf_ck_now is not None and self._has_depth(self._prev):
                T_kf_ck, cov_kf_ck_now = self._fuse_previous(cur, T_kf_ck, cov_kf_ck_now, T_ckm1_kf,
                                                             R_ckm1_ck_prior)
                T_ckm1_ck = T_ckm1_kf @ T_kf_ck
                self._last_motion = (inv_T(T_ckm1_ck), dt_s)
        self._cov_kf_ckm1 = cov_kf_ck_now
        self._prev = cur
        self._stamp_s = stamp_s
        self._kf_frames += 1
        if T_kf_ck is not None:
            self._T_c0_ck = self._T_c0_kf @ T_kf_ck
            self._T_kf_ckm1 = T_kf_ck
            if self._keyframe_is_due(T_kf_ck, pair.fitness) and self._has_depth(cur):
                cov_kf_ck = _covariance(pair.information)
                if cfg.keyframe_refinement and self._kf_prev is not None and cov_kf_ck is not None:
                    T_kf_ck = self._refine(cur, T_kf_ck, cov_kf_ck, T_ckm1_kf, R_ckm1_ck_prior)
                    T_ckm1_ck = T_ckm1_kf @ T_kf_ck
                    self._T_c0_ck = self._T_c0_kf @ T_kf_ck
                    self._last_motion = (inv_T(T_ckm1_ck), dt_s)
                self._set_keyframe(cur, T_kf_ck, cov_kf_ck)
        else:
            # the keyframe failed: this frame, whatever its own pose's quality, becomes the next one (tracking
            # re-initialises from it), unless it lacks the depth to be a reference (a dropout, a frame facing
            # beyond the sensor's range): then the keyframe stays and the bridged pose is this frame's in it
            self._T_c0_ck = self._T_c0_ck @ T_ckm1_ck
            if self._has_depth(cur):
                self._set_keyframe(cur)
            else:
                self._T_kf_ckm1 = inv_T(self._T_c0_kf) @ self._T_c0_ck
        if register and not cur.depth_at_colour_instant and self._last_motion is not None:
            # the rate is known now (at the start, after a failure): this frame, turned, becomes the keyframe
            rate = self._rotation_rate(0.0, None)
            if rate is not None:
                cur = prepare_frame(rgb, depth_m, K, cfg, _turn(rate, depth_offset_s))
                cur.depth_at_colour_instant = True
                cur.stamp_s, cur.depth_offset_s = stamp_s, depth_term_offset_s
                self._prev = cur
                self._set_keyframe(cur)
        return OdometryResult(stamp_s, self._T_c0_ck.copy(), T_ckm1_ck, pair.ok, pair.fitness, bridged)

    def _motion_prior(self, T_pred: Mat4 | None, R_ckm1_ck_prior: NDArray[np.float64] | None
                      ) -> tuple[Mat4, bool]:
        """``T_ckm1_ck`` of a frame that could not be aligned, and whether a motion prior gave it: the gyro's
        rotation (when given) and the constant-velocity prediction (its translation; its rotation too without a
        gyro) while the bridge is at most ``max_bridged_frames`` long; the identity without either."""
        T = np.eye(4)
        bridged = False
        if T_pred is not None and self._bridged < self.config.max_bridged_frames:
            T = inv_T(T_pred)
            bridged = True
        if R_ckm1_ck_prior is not None:
            T[:3, :3] = R_ckm1_ck_prior
            bridged = True
        return T, bridged

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

    def _refine(self, cur: PreparedFrame, T_kf_ck: Mat4, cov_kf_ck: NDArray[np.float64], T_ckm1_kf: Mat4,
                R_ckm1_ck_prior: NDArray[np.float64] | None) -> Mat4:
        """``T_kf_ck`` of a frame about to become the keyframe, fused with a second alignment against the
        keyframe before (a window of three keyframes, as DVO-SLAM's local refinement).

        The chain ``kf_prev -> kf -> ck`` carries the errors of two alignments, the direct ``kf_prev -> ck``
        its own: their information-weighted mean cuts the error each keyframe hands on, which on fast rotation
        is translation traded for rotation. The chain's estimate is a few pixels at most from the answer, inside
        the finest level's basin, so the second alignment runs on the finest level alone with the coarsest
        level's iteration budget (on fast rotation it mostly uses all of it: see perception/README.md). It is
        used only if its fitness would keep ``kf_prev`` a keyframe (``keyframe_min_fitness``): with less overlap
        its error is not the one its information describes (TUM teddy: 0.0053 -> 0.0057 m RPE without it).
        """
        assert self._kf_prev is not None
        cfg = self.config
        T_p_kf = self._T_kfprev_kf
        T_p_ck_chain = T_p_kf @ T_kf_ck
        T_p_ckm1 = T_p_kf @ inv_T(T_ckm1_kf)
        R_prior = None if R_ckm1_ck_prior is None else T_p_ckm1[:3, :3] @ R_ckm1_ck_prior
        finest = dataclasses.replace(cfg, levels=1, iterations=(max(cfg.iterations),),
                                     max_points=cfg.max_points[-1:])
        pair = align_pair(self._kf_prev, cur, finest, R_prior, inv_T(T_p_ck_chain), T_p_ckm1)
        cov_direct = _covariance(pair.information)
        if not pair.ok or cov_direct is None or pair.fitness < cfg.keyframe_min_fitness:
            return T_kf_ck
        Ad = _adjoint(T_p_kf)
        cov_chain = self._cov_kfprev_kf + Ad @ cov_kf_ck @ Ad.T
        # direct minus chain as a left perturbation in kf_prev's frame, weighted by the direct's share. The fused
        # pose lies between the two estimates, a few pixels from the chain's: a step beyond the jump gate's
        # translation or the delta itself (an ill-conditioned information, a direct alignment in another basin)
        # is not a refinement (a SITL flight with the pan-scan off diverged to 40 m without this gate)
        fused = _fusion_step(T_p_ck_chain, cov_chain, inv_T(pair.T_ck_ckm1), cov_direct, cfg.max_translation_jump_m)
        if fused is None:
            self.rejected_refinements += 1
            return T_kf_ck
        step = fused[0]
        self.refined_keyframes += 1
        # the step moved into kf's frame, applied to the frame's own pose in kf: the same pose as
        # inv(T_p_kf) exp(step) T_p_kf T_kf_ck, but that product's inv_T (R^T) of T_p_kf is an inverse only for an
        # orthonormal R, so its rounding entered twice and the result became the next T_p_kf: the rotation's
        # departure from SO(3) doubled at every refined keyframe (1e-16 to 0.06 in 47 of them, the SITL's
        # 40 m divergence; test_refined_keyframes_keep_the_chained_pose_rigid)
        return se3_exp(_adjoint(inv_T(T_p_kf)) @ step) @ T_kf_ck

    def _fuse_previous(self, cur: PreparedFrame, T_kf_ck: Mat4, cov_kf_ck: NDArray[np.float64], T_ckm1_kf: Mat4,
                       R_ckm1_ck_prior: NDArray[np.float64] | None) -> tuple[Mat4, NDArray[np.float64]]:
        """``T_kf_ck`` and its covariance fused with a second estimate, the previous frame's pose in the keyframe
        times an alignment against the previous frame (``frame_fusion``): the per-frame form of :meth:`_refine`'s
        window, which brings each frame the constraint to its neighbour that a gyro's prior otherwise gives. The
        second alignment runs on the finest level from the chain's estimate with the coarsest level's iteration
        budget (fewer left `fr1_xyz`'s rotation where it was); the same step gate as :meth:`_refine`."""
        assert self._prev is not None and self._cov_kf_ckm1 is not None
        cfg = self.config
        T_kf_ckm1 = inv_T(T_ckm1_kf)
        T_ckm1_ck_chain = T_ckm1_kf @ T_kf_ck
        finest = dataclasses.replace(cfg, levels=1, iterations=(max(cfg.iterations),),
                                     max_points=cfg.max_points[-1:])
        pair = align_pair(self._prev, cur, finest, R_ckm1_ck_prior, inv_T(T_ckm1_ck_chain), None)
        cov_direct = _covariance(pair.information)
        if not pair.ok or cov_direct is None:
            return T_kf_ck, cov_kf_ck
        Ad = _adjoint(T_kf_ckm1)
        fused = fuse_poses(T_kf_ck, cov_kf_ck, T_kf_ckm1 @ inv_T(pair.T_ck_ckm1),
                           self._cov_kf_ckm1 + Ad @ cov_direct @ Ad.T, cfg.max_translation_jump_m)
        if fused is None:
            return T_kf_ck, cov_kf_ck
        self.fused_frames += 1
        return fused

    def _set_keyframe(self, frame: PreparedFrame, T_kf_frame: Mat4 | None = None,
                      cov_kf_frame: NDArray[np.float64] | None = None) -> None:
        """Make ``frame`` the keyframe. Given its pose in the current keyframe and that pose's covariance, the
        current keyframe stays as the second reference of the next one (:meth:`_refine`); else (start,
        failure) there is none."""
        if T_kf_frame is not None and cov_kf_frame is not None:
            self._kf_prev, self._T_kfprev_kf, self._cov_kfprev_kf = self._kf, T_kf_frame, cov_kf_frame
        else:
            self._kf_prev = None
        self._kf = frame
        self._T_c0_kf = self._T_c0_ck.copy()
        self._T_kf_ckm1 = np.eye(4)
        self._kf_frames = 0
        self.keyframes += 1

    def _has_depth(self, frame: PreparedFrame) -> bool:
        """Whether a frame has the valid depth a reference needs (``min_reference_points`` at the finest level):
        a frame without is never made the keyframe, every frame aligned against it would fail."""
        return int(np.count_nonzero(frame.levels[0].depth)) >= self.config.min_reference_points

    def _keyframe_is_due(self, T_kf_ck: Mat4, fitness: float) -> bool:
        """Whether the current frame should replace the keyframe: enough frames, motion (the overlap shrinks
        and the warp's linearisation about the keyframe degrades) or a fitness drop (occlusions, exposure)."""
        cfg = self.config
        return (self._kf_frames >= cfg.keyframe_max_frames or fitness < cfg.keyframe_min_fitness
                or float(np.linalg.norm(T_kf_ck[:3, 3])) > cfg.keyframe_max_translation_m
                or float(np.linalg.norm(so3_log(T_kf_ck[:3, :3]))) > cfg.keyframe_max_rotation_rad)

    def _jump_bound_m(self, dt_s: float) -> float:
        """How far a frame's translation may be from the constant-velocity prediction (the jump gate): the fixed
        ``max_translation_jump_m``, or, when it is more (long or bridged intervals), how far ``max_acceleration_m_s2``
        takes the step off the prediction: the carried velocity is the last aligned pair's mean, half its interval
        old, and the time since that pair runs on through the bridged frames: ``a (t + dt) (t + dt + dt_last) / 2``
        (``a dt^2`` at a steady rate). ``dt_last`` is the interval of the last motion carried: the aligned pair's,
        or after bridged frames the last bridged frame's (the same at a steady rate)."""
        cfg = self.config
        dt_last = self._last_motion[1] if self._last_motion is not None else 0.0
        t_s = self._bridged_s + max(dt_s, 0.0)
        return max(cfg.max_translation_jump_m, 0.5 * cfg.max_acceleration_m_s2 * t_s * (t_s + dt_last))

    def _predict(self, dt_s: float) -> Mat4 | None:
        """Constant-velocity guess of ``T_ck_ckm1`` (DVO's motion prior as the starting point): the last pair's
        twist scaled to this frame interval; None after a failure or for a non-positive interval."""
        if self._last_motion is None:
            return None
        T_last, dt_last = self._last_motion
        if dt_s <= 0.0 or dt_last <= 0.0:
            return None
        # the velocity is carried at its value whatever the interval: a starved reader's long or irregular
        # intervals, and bridged frames, scale the motion, not the velocity
        f = dt_s / dt_last
        w = so3_log(T_last[:3, :3]) * f
        T = se3_exp(np.concatenate([np.zeros(3), w]))
        T[:3, 3] = T_last[:3, 3] * f
        return T
    def align(self, ref: PreparedFrame, cur: PreparedFrame, R_ckm1_ck_prior: NDArray[np.float64] | None = None,
              T_init: Mat4 | None = None, T_ref_ckm1: Mat4 | None = None, T_motion_prior: Mat4 | None = None
              ) -> PairResult:
        """Estimate ``T_ck_ckm1`` between two prepared frames with this odometry's configuration
        (:func:`perception.odometry_align.align_pair`)."""
        return align_pair(ref, cur, self.config, R_ckm1_ck_prior, T_init, T_ref_ckm1, T_motion_prior)

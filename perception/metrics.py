"""Trajectory metrics as the TUM RGB-D benchmark tools define them (pure).

* RPE (``evaluate_rpe.py``): for every pair (i, j) with t_j - t_i = delta (default 1 s, or per frame),
  E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j); translational error |trans(E)|, rotational error angle(E). Reported
  here per second (divided by the pair's time span), RMSE and median.
  :func:`rpe_window` is the benchmark's standard figure: the error of every pair (i, j) whose stamps are
  ``delta_s`` apart (1 s: the drift per second; the frame interval: per-frame RPE), not divided by the
  time span, RMSE over all such pairs (Sturm et al. 2012, eqs. 1-3, with Delta in seconds as
  ``evaluate_rpe.py --fixed_delta --delta 1 --delta_unit s``). ``tests/test_perception_metrics.py`` checks it
  and :func:`ate` against ``evo`` on the shared TUM sequences.
* ATE (``evaluate_ate.py``): after Horn's closed-form least-squares alignment (rotation + translation, no
  scale) of the estimated positions to the ground truth, RMSE of the position differences.

Poses are 4x4 camera-to-world matrices. The ground truth (100 Hz motion capture) is interpolated at the
frame stamps (:func:`interpolate_poses`: positions linearly, rotations by slerp) where its samples around the
stamp are at most ``max_gap_s`` apart; :func:`associate_stamps` (nearest stamp) is kept for pre-associated data.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from quadlink.lie import inv_T, rotation_angle_rad

Poses = NDArray[np.float64]


@dataclass(frozen=True)
class RpeResult:
    pairs: int
    trans_rmse_m_s: float
    trans_median_m_s: float
    rot_rmse_deg_s: float
    rot_median_deg_s: float


@dataclass(frozen=True)
class WindowRpeResult:
    """RPE over pairs ``delta_s`` apart: errors per pair (not per second), RMSE and median."""

    pairs: int
    delta_s: float
    trans_rmse_m: float
    trans_median_m: float
    rot_rmse_deg: float
    rot_median_deg: float


@dataclass(frozen=True)
class AteResult:
    pairs: int
    rmse_m: float
    median_m: float
    max_m: float


def associate_stamps(stamps_est: NDArray[np.float64], stamps_gt: NDArray[np.float64],
                     max_dt_s: float = 0.02) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Indices (est, gt) of nearest-stamp matches within ``max_dt_s``."""
    gt = np.asarray(stamps_gt, dtype=float)
    ie, ig = [], []
    for i, t in enumerate(np.asarray(stamps_est, dtype=float)):
        j = int(np.argmin(np.abs(gt - t)))
        if abs(gt[j] - t) <= max_dt_s:
            ie.append(i)
            ig.append(j)
    return np.asarray(ie, dtype=np.intp), np.asarray(ig, dtype=np.intp)


def rpe(stamps: NDArray[np.float64], est: Poses, gt: Poses, delta_s: float | None = None) -> RpeResult:
    """Relative pose error per second on associated poses (same length, same stamps).

    ``delta_s=None`` compares consecutive frames (the frame-to-frame drift of odometry, TUM's
    ``--delta 1 --delta_unit f``); otherwise pairs ``delta_s`` apart, as ``--delta_unit s``.
    """
    stamps = np.asarray(stamps, dtype=float)
    t_err, r_err = [], []
    for i in range(len(stamps)):
        if delta_s is None:
            j = i + 1
            if j >= len(stamps):
                break
        else:
            j = int(np.searchsorted(stamps, stamps[i] + delta_s))
            if j >= len(stamps):
                break
        dt = stamps[j] - stamps[i]
        if dt <= 0:
            continue
        E = inv_T(inv_T(gt[i]) @ gt[j]) @ (inv_T(est[i]) @ est[j])
        t_err.append(float(np.linalg.norm(E[:3, 3])) / dt)
        r_err.append(math.degrees(rotation_angle_rad(E[:3, :3])) / dt)
    if not t_err:
        return RpeResult(0, math.nan, math.nan, math.nan, math.nan)
    t = np.asarray(t_err)
    r = np.asarray(r_err)
    return RpeResult(len(t), float(np.sqrt(np.mean(t**2))), float(np.median(t)),
                     float(np.sqrt(np.mean(r**2))), float(np.median(r)))


def horn_align(model: NDArray[np.float64], data: NDArray[np.float64]
               ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Rotation R and translation t minimising sum |R data_i + t - model_i|^2 (Horn 1987, via SVD)."""
    mu_m = model.mean(axis=0)
    mu_d = data.mean(axis=0)
    W = (model - mu_m).T @ (data - mu_d)
    U, _, Vt = np.linalg.svd(W)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    return R, mu_m - R @ mu_d


def ate(est: Poses, gt: Poses) -> AteResult:
    """Absolute trajectory error of associated poses after Horn alignment of the positions."""
    p_est = np.asarray(est)[:, :3, 3]
    p_gt = np.asarray(gt)[:, :3, 3]
    if len(p_est) < 3:
        return AteResult(len(p_est), math.nan, math.nan, math.nan)
    R, t = horn_align(p_gt, p_est)
    err = np.linalg.norm((p_est @ R.T + t) - p_gt, axis=1)
    return AteResult(len(err), float(np.sqrt(np.mean(err**2))), float(np.median(err)), float(err.max()))


def pose_pairs(stamps: NDArray[np.float64], delta_s: float, tol_s: float | None = None) -> NDArray[np.intp]:
    """Index pairs (i, j), j the frame whose stamp is nearest ``t_i + delta_s`` (TUM's ``evaluate_rpe.py``
    with ``--fixed_delta``), kept when it is within ``tol_s`` of it (default: half the median frame interval,
    so the partner is unambiguous and no pair runs past the end of the sequence), shape (n, 2)."""
    t = np.asarray(stamps, dtype=float)
    if t.size < 2:
        return np.empty((0, 2), np.intp)
    if tol_s is None:
        tol_s = 0.5 * float(np.median(np.diff(t)))
    target = t + delta_s
    j = np.clip(np.searchsorted(t, target), 1, t.size - 1)
    j = np.where(np.abs(t[j - 1] - target) <= np.abs(t[j] - target), j - 1, j)
    keep = (np.abs(t[j] - target) <= tol_s) & (j > np.arange(t.size))
    return np.stack([np.flatnonzero(keep), j[keep]], axis=1).astype(np.intp)


def relative_errors(est: Poses, gt: Poses, pairs: NDArray[np.intp]
                    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Translational (m) and rotational (deg) error of each pair: ``E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j)``."""
    t_err = np.empty(len(pairs))
    r_err = np.empty(len(pairs))
    for n, (i, j) in enumerate(pairs):
        E = inv_T(inv_T(gt[i]) @ gt[j]) @ (inv_T(est[i]) @ est[j])
        t_err[n] = float(np.linalg.norm(E[:3, 3]))
        r_err[n] = math.degrees(rotation_angle_rad(E[:3, :3]))
    return t_err, r_err


def rpe_window(stamps: NDArray[np.float64], est: Poses, gt: Poses, delta_s: float = 1.0,
               tol_s: float | None = None) -> WindowRpeResult:
    """RPE of all pairs ``delta_s`` apart (see :func:`pose_pairs`): RMSE and median, m and deg."""
    pairs = pose_pairs(stamps, delta_s, tol_s)
    if len(pairs) == 0:
        return WindowRpeResult(0, delta_s, math.nan, math.nan, math.nan, math.nan)
    t, r = relative_errors(np.asarray(est), np.asarray(gt), pairs)
    return WindowRpeResult(len(pairs), delta_s, float(np.sqrt(np.mean(t**2))), float(np.median(t)),
                           float(np.sqrt(np.mean(r**2))), float(np.median(r)))


def interpolate_poses(stamps_gt: NDArray[np.float64], poses_gt: Poses, stamps: NDArray[np.float64],
                      max_gap_s: float = 0.02) -> tuple[NDArray[np.bool_], Poses]:
    """Ground-truth poses at ``stamps``: positions linearly, rotations by slerp between the two samples around
    each stamp. Returns (ok mask, poses of the ok stamps); a stamp is not ok outside the ground truth's span or
    where its two samples are more than ``max_gap_s`` apart (motion-capture dropouts: TUM's tools accept a
    nearest sample within twice the 100 Hz interval, 20 ms)."""
    from scipy.spatial.transform import Rotation, Slerp

    sg = np.asarray(stamps_gt, dtype=float)
    st = np.asarray(stamps, dtype=float)
    order = np.argsort(sg)
    sg, pg = sg[order], np.asarray(poses_gt)[order]
    k = np.searchsorted(sg, st, side="right")          # sg[k-1] <= t < sg[k]
    inside = (k > 0) & (k < sg.size)
    exact = np.isin(st, sg)
    k_safe = np.clip(k, 1, sg.size - 1)
    gap = sg[k_safe] - sg[k_safe - 1]
    ok = exact | (inside & (gap <= max_gap_s))
    ks = k_safe[ok]
    t0, t1 = sg[ks - 1], sg[ks]
    a = np.clip((st[ok] - t0) / np.maximum(t1 - t0, 1e-12), 0.0, 1.0)
    out = np.repeat(np.eye(4)[None], int(ok.sum()), axis=0)
    out[:, :3, 3] = pg[ks - 1, :3, 3] * (1.0 - a)[:, None] + pg[ks, :3, 3] * a[:, None]
    rots = Rotation.from_matrix(pg[:, :3, :3])
    out[:, :3, :3] = Slerp(sg, rots)(np.clip(st[ok], sg[0], sg[-1])).as_matrix()
    return ok, out

"""Trajectory metrics as the TUM RGB-D benchmark tools define them (pure).

* RPE (``evaluate_rpe.py``): for every pair (i, j) with t_j - t_i = delta (default 1 s, or per frame),
  E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j); translational error |trans(E)|, rotational error angle(E). Reported
  here per second (divided by the pair's time span), RMSE and median.
* ATE (``evaluate_ate.py``): after Horn's closed-form least-squares alignment (rotation + translation, no
  scale) of the estimated positions to the ground truth, RMSE of the position differences.

Poses are 4x4 camera-to-world matrices; associations are by nearest stamp within ``max_dt_s``.
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

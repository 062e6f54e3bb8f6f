"""Trajectory metrics (perception.metrics): ground-truth interpolation, TUM's pairs by time, and agreement with
``evo`` (the field's evaluation library) on the committed TUM clips (``tests/data/tum``), both computed from one
estimated trajectory of our odometry."""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import TUM_CLIPS, tum_clip_path

from perception import cli, metrics
from perception.odometry import se3_exp
from perception.synthetic import pose


def _screw(t: float) -> np.ndarray:
    """A constant-rate screw motion: rotation about a fixed axis at 1 rad/s, translation 0.3 m/s along it, so
    slerp + linear interpolation between any two samples is exact."""
    axis = np.array([0.2, -0.5, 0.84])
    axis /= np.linalg.norm(axis)
    return pose(se3_exp(np.concatenate([np.zeros(3), axis * t]))[:3, :3], 0.3 * t * axis)


def test_interpolation_is_exact_on_a_screw_motion_and_skips_gaps() -> None:
    stamps_gt = np.concatenate([np.arange(0.0, 0.5, 0.01), np.arange(0.6, 1.0, 0.01)])   # a 100 ms dropout
    poses_gt = np.array([_screw(t) for t in stamps_gt])
    stamps = np.array([-0.05, 0.0, 0.123, 0.2555, 0.53, 0.77, 0.995, 1.2])
    ok, poses = metrics.interpolate_poses(stamps_gt, poses_gt, stamps, max_gap_s=0.02)
    assert ok.tolist() == [False, True, True, True, False, True, False, False]
    for t, T in zip(stamps[ok], poses, strict=True):
        assert np.allclose(T, _screw(t), atol=1e-9), t
    # the nearest sample, as before, is off by up to half a sample of motion: interpolation is the fix
    near = poses_gt[np.argmin(np.abs(stamps_gt - 0.2555))]
    assert np.linalg.norm(near[:3, 3] - _screw(0.2555)[:3, 3]) > 1e-3


def test_pairs_by_time_follow_tums_nearest_rule() -> None:
    stamps = np.array([0.0, 0.032, 0.068, 0.1, 0.133, 0.2, 0.231, 0.265])   # one dropped frame after 0.133
    pairs = metrics.pose_pairs(stamps, 0.1)
    # nearest stamp to t_i + 0.1 within half the median interval (about 16 ms)
    assert pairs.tolist() == [[0, 3], [1, 4], [3, 5], [4, 6]]   # 2 and 5: nothing within 16 ms
    assert metrics.pose_pairs(stamps, 10.0).shape == (0, 2)


def test_window_rpe_is_not_divided_by_time() -> None:
    stamps = np.arange(0, 3.0, 1 / 30)
    gt = np.array([_screw(t) for t in stamps])
    est = gt.copy()
    est[:, 0, 3] += 0.01 * np.sin(stamps)       # a slow position error
    r = metrics.rpe_window(stamps, est, gt, 1.0)
    pairs = metrics.pose_pairs(stamps, 1.0)
    assert r.pairs == len(pairs) == 60
    # E's translation is R_gt_i^T times the difference of the position errors (rotation-invariant norm)
    expected = np.abs(0.01 * (np.sin(stamps[pairs[:, 1]]) - np.sin(stamps[pairs[:, 0]])))
    assert r.trans_rmse_m == pytest.approx(float(np.sqrt(np.mean(expected**2))), rel=1e-9)
    assert r.rot_rmse_deg < 1e-9


def _run(seq: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Our odometry on a committed TUM clip once: stamps, estimate and ground truth at the frames inside the
    ground truth's span (interpolated across its dropouts too: both metrics get the same arrays)."""
    folder = tum_clip_path(seq)
    run = cli.run_sequence(cli.load_frames(folder), "ours", seq)
    gt = cli.ground_truth_at(folder, run.stamps_s, max_gap_s=math.inf)
    assert gt is not None
    ok, gt_poses = gt
    assert ok.sum() >= 10
    return run.stamps_s[ok], run.T_c0_ck[ok], gt_poses


@pytest.mark.parametrize("seq", TUM_CLIPS)
def test_metrics_agree_with_evo_on_the_tum_clips(seq: str) -> None:
    evo_metrics = pytest.importorskip("evo.core.metrics")
    from evo.core.trajectory import PoseTrajectory3D

    stamps, est, gt = _run(seq)
    traj_est = PoseTrajectory3D(poses_se3=list(est), timestamps=stamps)
    traj_ref = PoseTrajectory3D(poses_se3=list(gt), timestamps=stamps)

    # ATE: Horn (rigid, no scale) against evo's Umeyama alignment without scale, then APE translation RMSE
    ours_ate = metrics.ate(est, gt)
    aligned = PoseTrajectory3D(poses_se3=list(est), timestamps=stamps)
    aligned.align(traj_ref, correct_scale=False)
    ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    ape.process_data((traj_ref, aligned))
    evo_ate = ape.get_statistic(evo_metrics.StatisticsType.rmse)
    assert ours_ate.rmse_m == pytest.approx(evo_ate, rel=1e-6, abs=1e-9)
    assert ours_ate.rmse_m > 1e-4                      # a real trajectory error, not a trivial zero

    frame_dt = float(np.median(np.diff(stamps)))
    # per frame, several frames (on fr1_rpy the sensor's dropped frames make pairs of different frame offsets),
    # and TUM's 1 s where the trajectory is long enough
    windows = [("per frame", frame_dt), ("0.2 s", 0.2)] + ([("1 s", 1.0)] if stamps[-1] - stamps[0] > 1.5 else [])
    for label, delta_s in windows:
        pairs = metrics.pose_pairs(stamps, delta_s)
        # most frames have a partner (the fr1_rpy clip: 4 of its 9 intervals are doubled by dropped frames)
        assert len(pairs) >= 0.5 * np.count_nonzero(stamps <= stamps[-1] - delta_s), label
        ours = metrics.rpe_window(stamps, est, gt, delta_s)
        t_ours, r_ours = metrics.relative_errors(est, gt, pairs)
        # evo's RPE counts the window in frames. Our pairs are chosen by time (TUM's rule), so where frames
        # were dropped (fr1_rpy: 12 colour frames without depth) the partner 1 s ahead is fewer frames ahead:
        # evo computes every pair (i, i + d) for each offset d that occurs, and ours must be among them
        for relation, per_pair, rmse in ((evo_metrics.PoseRelation.translation_part, t_ours, ours.trans_rmse_m),
                                         (evo_metrics.PoseRelation.rotation_angle_deg, r_ours, ours.rot_rmse_deg)):
            evo_errors = np.full(len(pairs), np.nan)
            offsets = pairs[:, 1] - pairs[:, 0]
            for d in np.unique(offsets).tolist():
                rpe = evo_metrics.RPE(relation, delta=d, delta_unit=evo_metrics.Unit.frames, all_pairs=True)
                rpe.process_data((traj_ref, traj_est))
                assert len(rpe.error) == len(stamps) - d, label
                sel = offsets == d
                evo_errors[sel] = np.asarray(rpe.error)[pairs[sel, 0]]     # evo's pair i is (i, i + d)
                if sel.all() and len(pairs) == len(stamps) - d:            # the same pairs: evo's own RMSE too
                    assert rmse == pytest.approx(rpe.get_statistic(evo_metrics.StatisticsType.rmse), rel=1e-6)
            assert np.allclose(per_pair, evo_errors, rtol=1e-6, atol=1e-9), label
            assert rmse == pytest.approx(float(np.sqrt(np.mean(evo_errors**2))), rel=1e-9), label
        assert ours.trans_rmse_m > 1e-4, label

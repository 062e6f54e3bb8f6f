"""The leave-one-out machinery of perception.odometry_loo: the grid, the shipping rule, the target arithmetic and
the CLI's refusal of fewer than three sequences (the held-out run itself is benchmarks/bench_perception.py's)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from click.testing import CliRunner

from perception import metrics, odometry_loo
from perception.cli import SequenceMetrics, SequenceRun
from perception.cli import command as vo_eval
from perception.odometry import OdometryConfig


def test_grid_configs_cover_the_grid_and_overrides_win() -> None:
    grid = {"keyframe_max_frames": (4, 8), "gradient_fraction": (0.2, 0.5)}
    configs = odometry_loo.grid_configs(OdometryConfig(), grid, {})
    assert len(configs) == 4
    assert {(c.keyframe_max_frames, c.gradient_fraction) for _, c in configs} == {(4, 0.2), (4, 0.5), (8, 0.2),
                                                                                  (8, 0.5)}
    fixed = odometry_loo.grid_configs(OdometryConfig(), grid, {"keyframe_max_frames": 1})
    assert len(fixed) == 2 and all(c.keyframe_max_frames == 1 for _, c in fixed)
    assert all("keyframe_max_frames" not in chosen for chosen, _ in fixed)


def _split(held: str, **chosen: object) -> odometry_loo.SplitResult:
    return odometry_loo.SplitResult("ours", held, dict(chosen), 0.0, None)  # type: ignore[arg-type]


def test_a_value_ships_only_when_a_majority_of_the_splits_chose_it() -> None:
    base = OdometryConfig(keyframe_max_frames=8, gradient_fraction=0.2)
    two_of_three = [_split("a", keyframe_max_frames=4, gradient_fraction=0.5),
                    _split("b", keyframe_max_frames=4, gradient_fraction=0.2),
                    _split("c", keyframe_max_frames=8, gradient_fraction=0.35)]
    assert odometry_loo.consensus(two_of_three, base=base) == {"keyframe_max_frames": 4, "gradient_fraction": 0.2}
    split_three_ways = [_split("a", gradient_fraction=0.5), _split("b", gradient_fraction=0.35),
                        _split("c", gradient_fraction=0.1)]
    assert odometry_loo.consensus(split_three_ways, base=base) == {"gradient_fraction": 0.2}   # the default


def _scored(t_frame: float, r_frame: float, cpu_ms: float, failures: int = 0) -> odometry_loo.Scored:
    w = metrics.WindowRpeResult
    m = SequenceMetrics(10, w(0, 1.0, np.nan, np.nan, np.nan, np.nan), w(9, 0.033, t_frame, t_frame, r_frame, r_frame),
                        metrics.AteResult(10, 0.01, 0.01, 0.02))
    run = SequenceRun("s", "m", np.zeros(10), np.zeros((10, 4, 4)), failures, np.full(9, cpu_ms), np.full(9, cpu_ms))
    return odometry_loo.Scored(run, m)


def test_targets_compare_with_the_better_peer_and_the_faster_peer() -> None:
    peers = [_scored(0.004, 0.3, 15.0), _scored(0.006, 0.2, 10.0)]
    met = odometry_loo.targets(_scored(0.0031, 0.2, 5.0), peers)
    assert met["translation RPE frame"] == (0.0031 / 0.004, 0.8, True)
    assert met["rotation RPE frame"][2] and met["time per frame"] == (0.5, 0.5, True)
    assert "translation RPE 1 s" not in met                    # no pair 1 s apart: not judged
    missed = odometry_loo.targets(_scored(0.0033, 0.21, 5.1, failures=1), peers)
    assert not any(ok for _, _, ok in missed.values())


def test_vo_eval_leave_one_out_needs_three_sequences(tmp_path: Path) -> None:
    res = CliRunner().invoke(vo_eval, ["--leave-one-out", str(tmp_path), str(tmp_path)])
    assert res.exit_code != 0 and "three sequences" in res.output

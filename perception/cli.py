"""``quadlink vo-eval PATH [PATH ...]``: run an RGB-D odometry on TUM-format sequences and print TUM's metrics.

Each sequence's colour and depth frames are associated by nearest stamp (TUM's ``associate.py`` rule, at most
20 ms apart, or the folder's ``associations.txt``; the colour stamp is the frame's), the odometry runs on every
frame, and the ground truth (``groundtruth.txt``) is interpolated at the colour stamps (frames in a gap of the
truth longer than twice its median sample interval, 20 ms for TUM's 100 Hz motion capture, are left out of the
metrics). Metrics (:mod:`perception.metrics`, checked against ``evo`` in the tests):
RPE over 1 s windows (translation m, rotation deg; RMSE over all pairs 1 s apart), ATE RMSE after Horn
alignment (rigid, no scale), per-frame RPE (consecutive frames; RMSE), and the wall and CPU time per frame.
Without ``groundtruth.txt`` only the trajectory and timing are produced.
"""

from __future__ import annotations

import logging
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import click
import cv2
import numpy as np
from numpy.typing import NDArray

from perception import metrics
from perception.odometry import OdometryConfig, OdometryResult, RgbdOdometry
from quadlink.camera import RgbdFrame
from quadlink.datasets.tum import TumSequence, read_tum_trajectory, write_tum_trajectory
from quadlink.errors import QuadlinkError

log = logging.getLogger(__name__)

METHODS = ("ours", "opencv", "open3d")
GT_MAX_GAP_S = 0.02   # ground-truth samples around a frame at most this far apart (TUM: twice the 100 Hz interval)


def make_odometry(method: str):  # type: ignore[no-untyped-def]
    """An odometry object with ``process(stamp, rgb, depth, K, R_prior)`` for a method name."""
    if method == "ours":
        return RgbdOdometry()
    from perception import baselines

    if method == "open3d":
        return baselines.Open3dOdometry()
    if method == "opencv":
        return baselines.OpenCvOdometry()
    raise QuadlinkError(f"unknown odometry method {method!r} ({', '.join(METHODS)})")


@dataclass(frozen=True)
class SequenceRun:
    """One method's trajectory on one sequence, with its per-frame cost (the first frame excluded).

    ``failures``: frames that were not aligned and got no pose from a motion prior (the pose held);
    ``fallbacks``: frames that were not aligned and were bridged by the motion prior (ours only)."""

    name: str
    method: str
    stamps_s: NDArray[np.float64]     # colour stamps
    T_c0_ck: NDArray[np.float64]      # (N, 4, 4)
    failures: int
    wall_ms: NDArray[np.float64]
    cpu_ms: NDArray[np.float64]
    fallbacks: int = 0


@dataclass(frozen=True)
class SequenceMetrics:
    """TUM's metrics of a run against its ground truth interpolated at the colour stamps."""

    frames_evaluated: int
    rpe_1s: metrics.WindowRpeResult
    rpe_frame: metrics.WindowRpeResult
    ate: metrics.AteResult


def run_sequence(frames: list[RgbdFrame], method: str, name: str = "",
                 config: OdometryConfig | None = None) -> SequenceRun:
    """Run ``method`` on the frames (already loaded, so reading files is not timed). Ours also gets each
    frame's depth-minus-colour stamp offset (``meta["depth_offset_s"]``, see :func:`load_frames`) and runs with
    ``config`` (default: :class:`OdometryConfig`'s defaults)."""
    odometry = RgbdOdometry(config) if method == "ours" else make_odometry(method)
    stamps, poses, wall, cpu = [], [], [], []
    failures = fallbacks = 0
    for frame in frames:
        if frame.depth_m is None:
            raise QuadlinkError(f"{name}: frame {frame.seq} has no depth")
        extra = {"depth_offset_s": frame.meta.get("depth_offset_s", 0.0)} if method == "ours" else {}
        t0, c0 = time.perf_counter(), time.process_time()
        result: OdometryResult = odometry.process(frame.stamp_s, frame.rgb, frame.depth_m, frame.intrinsics,
                                                  **extra)
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
        fallbacks += 1 if result.fallback else 0
        failures += 0 if result.ok or result.fallback else 1
        stamps.append(frame.stamp_s)
        poses.append(result.T_c0_ck)
    return SequenceRun(name, method, np.asarray(stamps), np.asarray(poses), failures,
                       np.asarray(wall[1:] or wall) * 1e3, np.asarray(cpu[1:] or cpu) * 1e3, fallbacks)


def truth_gap_s(stamps_gt_s: NDArray[np.float64]) -> float:
    """The longest gap between two truth samples a frame's truth is interpolated across: twice the truth's own
    median sample interval, at least :data:`GT_MAX_GAP_S` (TUM's 100 Hz motion capture: 20 ms, so a dropout
    leaves its frames out; a clip that keeps only one row per frame, as ``tests/data/tum/fr1_xyz``, is sampled at
    the frame rate)."""
    steps = np.diff(np.sort(np.asarray(stamps_gt_s, dtype=float)))
    return max(GT_MAX_GAP_S, 2.0 * float(np.median(steps))) if steps.size else GT_MAX_GAP_S


def ground_truth_at(folder: Path, stamps_s: NDArray[np.float64], max_gap_s: float | None = None
                    ) -> tuple[NDArray[np.bool_], NDArray[np.float64]] | None:
    """(mask of the stamps with ground truth, its poses there), or None without ``groundtruth.txt``; the
    interpolation's longest gap is ``max_gap_s``, by default :func:`truth_gap_s` of the file."""
    gt_file = folder / "groundtruth.txt"
    if not gt_file.is_file():
        return None
    gs, gp = read_tum_trajectory(gt_file)
    return metrics.interpolate_poses(gs, gp, stamps_s, truth_gap_s(gs) if max_gap_s is None else max_gap_s)


def evaluate(run: SequenceRun, ok: NDArray[np.bool_], gt: NDArray[np.float64]) -> SequenceMetrics:
    """Metrics on the frames with ground truth (``ok``); pairs are chosen by time among them."""
    st, est = run.stamps_s[ok], run.T_c0_ck[ok]
    if len(st) < 3:
        raise QuadlinkError(f"{run.name}: fewer than three frames have ground truth")
    frame_dt = float(np.median(np.diff(run.stamps_s)))
    return SequenceMetrics(len(st), metrics.rpe_window(st, est, gt, 1.0),
                           metrics.rpe_window(st, est, gt, frame_dt), metrics.ate(est, gt))


def load_frames(path: Path, overrides: dict[str, float | None] | None = None, max_frames: int | None = None
                ) -> list[RgbdFrame]:
    """The associated frames of a TUM folder, each with ``meta["depth_offset_s"]``: its depth image's stamp
    (from ``depth.txt``) minus its colour stamp (Kinect v1 takes them up to 20 ms apart)."""
    source = TumSequence(path, overrides or {}, max_frames=max_frames)
    p = source.params
    log.info("sequence %s: %d frames, fx %.1f fy %.1f cx %.1f cy %.1f, depth scale %.0f/m",
             path, len(source), p.fx, p.fy, p.cx, p.cy, p.depth_scale)
    frames = list(source.frames())
    for f in frames:
        f.meta["depth_offset_s"] = f.meta["depth_stamp_s"] - f.stamp_s
    return frames


def leave_one_out_report(paths: list[Path], progress: Callable[[str], None] | None = None) -> str:
    """Issue 33's held-out table (:mod:`perception.odometry_loo`) for three or more TUM folders: each sequence
    held out in turn, ours with its parameters chosen on the others, OpenCV and Open3D on the same frames."""
    from perception import odometry_loo as loo

    if len(paths) < 3:
        raise QuadlinkError("--leave-one-out needs at least three sequences (choose on two, score on the third)")
    sequences, peers = [], {}
    for path in paths:
        frames = load_frames(path)
        stamps = np.array([f.stamp_s for f in frames])
        gt = ground_truth_at(path, stamps)
        if gt is None:
            raise QuadlinkError(f"{path}: --leave-one-out needs groundtruth.txt")
        seq = loo.EvalSequence(path.name, frames, *gt)
        sequences.append(seq)
        peers[seq.name] = {p: loo.run_scored(seq, p) for p in loo.PEERS}
        if progress:
            progress(f"{path.name}: {len(frames)} frames, peers done")
    results = loo.leave_one_out(sequences, peers, progress=progress)
    grid = "; ".join(f"{k} in {{{', '.join(map(str, v))}}}" for k, v in loo.GRID.items())
    ship = ", ".join(f"{k}={v}" for k, v in loo.consensus(results).items())
    return (f"Searched (each split, each variant): {grid}; every other parameter at its default.\n"
            f"Majority of the splits for ours (the shipping rule): {ship}.\n\n" + loo.markdown_table(results, peers))


def _fmt(x: float, spec: str) -> str:
    return "-" if not math.isfinite(x) else format(x, spec)


HEADER = (f"{'sequence':20s} {'method':7s} {'frames':>8s} {'RPE1s m':>8s} {'RPE1s deg':>9s} {'pairs':>5s} "
          f"{'ATE m':>7s} {'RPEfr mm':>8s} {'RPEfr deg':>9s} {'ms/fr':>6s} {'CPU ms':>6s} {'fails':>5s} {'fallb':>5s}")


def table_row(run: SequenceRun, m: SequenceMetrics | None) -> str:
    n = f"{m.frames_evaluated if m else 0}/{len(run.stamps_s)}"
    nan = math.nan
    r1, rf, a = (m.rpe_1s, m.rpe_frame, m.ate) if m else (None, None, None)
    return (f"{run.name[:20]:20s} {run.method:7s} {n:>8s} {_fmt(r1.trans_rmse_m if r1 else nan, '8.4f')} "
            f"{_fmt(r1.rot_rmse_deg if r1 else nan, '9.3f')} {r1.pairs if r1 else 0:5d} "
            f"{_fmt(a.rmse_m if a else nan, '7.4f')} {_fmt(rf.trans_rmse_m * 1e3 if rf else nan, '8.2f')} "
            f"{_fmt(rf.rot_rmse_deg if rf else nan, '9.3f')} {float(np.median(run.wall_ms)):6.1f} "
            f"{float(np.median(run.cpu_ms)):6.1f} {run.failures:5d} {run.fallbacks:5d}")


@click.command(help=__doc__)
@click.argument("paths", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("--out", type=click.Path(path_type=Path), default=None,
              help="write the trajectory (TUM format): a file for one sequence and method, else a directory "
                   "(SEQUENCE_METHOD.txt)")
@click.option("--fx", type=float, default=None, help="override focal length x (px)")
@click.option("--fy", type=float, default=None, help="override focal length y (px)")
@click.option("--cx", type=float, default=None, help="override principal point x (px)")
@click.option("--cy", type=float, default=None, help="override principal point y (px)")
@click.option("--depth-scale", type=float, default=None, help="override depth units per metre (TUM: 5000)")
@click.option("--method", "methods", type=click.Choice(METHODS), multiple=True, default=("ours",),
              show_default=True, help="odometry method (repeat for several)")
@click.option("--max-frames", type=int, default=None, help="use only the first N frames")
@click.option("--threads", type=int, default=1, show_default=True, help="OpenCV threads (timing is per thread)")
@click.option("--leave-one-out", "loo", is_flag=True,
              help="issue 33's held-out table: each sequence held out in turn, ours with its parameters chosen on "
                   "the others (a small grid, perception/odometry_loo.py), beside OpenCV and Open3D; needs three or "
                   "more sequences with ground truth (the other options but --threads are ignored)")
def command(paths: tuple[Path, ...], out: Path | None, fx: float | None, fy: float | None, cx: float | None,
            cy: float | None, depth_scale: float | None, methods: tuple[str, ...], max_frames: int | None,
            threads: int, loo: bool) -> None:
    cv2.setNumThreads(threads)
    os.environ.setdefault("OMP_NUM_THREADS", str(threads))
    if loo:
        try:
            click.echo(leave_one_out_report(list(paths), progress=lambda msg: log.info("%s", msg)))
        except QuadlinkError as exc:
            raise click.ClickException(str(exc)) from exc
        return
    overrides = {"fx": fx, "fy": fy, "cx": cx, "cy": cy, "depth_scale": depth_scale}
    several = len(paths) * len(methods) > 1
    if out is not None and several:
        out.mkdir(parents=True, exist_ok=True)
    click.echo("RPE1s: RMSE over all frame pairs 1 s apart; ATE: RMSE after Horn alignment (no scale); RPEfr: "
               f"consecutive frames; ms/fr wall and CPU ms: median per frame (threads: {threads})")
    click.echo(HEADER)
    for path in paths:
        frames = load_frames(path, overrides, max_frames)
        for method in methods:
            run = run_sequence(frames, method, path.name)
            gt = ground_truth_at(path, run.stamps_s)
            m = None if gt is None else evaluate(run, *gt)
            click.echo(table_row(run, m))
            if gt is None:
                click.echo(f"  no {path / 'groundtruth.txt'}: metrics skipped")
            if out is not None:
                target = out / f"{path.name}_{method}.txt" if several else out
                write_tum_trajectory(target, run.stamps_s, run.T_c0_ck)
                log.info("trajectory written to %s", target)

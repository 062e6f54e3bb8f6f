"""``quadlink vo-eval PATH``: run an RGB-D odometry on a TUM-format sequence and print RPE/ATE.

Metrics as the TUM RGB-D benchmark tools define them (see :mod:`perception.metrics`): RPE between
consecutive frames, per second (translational m/s, rotational deg/s; RMSE and median), ATE RMSE after
Horn alignment. Needs ``groundtruth.txt`` in the folder for the metrics; without it only the trajectory
and timing are produced.
"""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path

import click
import cv2
import numpy as np

from perception import metrics
from perception.odometry import OdometryResult, RgbdOdometry
from quadlink.datasets.tum import TumSequence, read_tum_trajectory, write_tum_trajectory
from quadlink.errors import QuadlinkError

log = logging.getLogger(__name__)


def make_odometry(method: str):  # type: ignore[no-untyped-def]
    """An odometry object with ``process(stamp, rgb, depth, K, R_prior)`` for a method name."""
    if method == "ours":
        return RgbdOdometry()
    from perception import baselines

    if method == "open3d":
        return baselines.Open3dOdometry()
    if method == "opencv":
        return baselines.OpenCvOdometry()
    raise QuadlinkError(f"unknown odometry method {method!r} (ours, open3d, opencv)")


@click.command(help=__doc__)
@click.argument("path", type=click.Path(path_type=Path))
@click.option("--out", type=click.Path(path_type=Path), default=None, help="write the trajectory (TUM format)")
@click.option("--fx", type=float, default=None, help="override focal length x (px)")
@click.option("--fy", type=float, default=None, help="override focal length y (px)")
@click.option("--cx", type=float, default=None, help="override principal point x (px)")
@click.option("--cy", type=float, default=None, help="override principal point y (px)")
@click.option("--depth-scale", type=float, default=None, help="override depth units per metre (TUM: 5000)")
@click.option("--method", type=click.Choice(["ours", "open3d", "opencv"]), default="ours", show_default=True)
@click.option("--max-frames", type=int, default=None, help="use only the first N frames")
@click.option("--threads", type=int, default=1, show_default=True, help="OpenCV threads (timing is per thread)")
def command(path: Path, out: Path | None, fx: float | None, fy: float | None, cx: float | None, cy: float | None,
            depth_scale: float | None, method: str, max_frames: int | None, threads: int) -> None:
    cv2.setNumThreads(threads)
    os.environ.setdefault("OMP_NUM_THREADS", str(threads))
    source = TumSequence(path, {"fx": fx, "fy": fy, "cx": cx, "cy": cy, "depth_scale": depth_scale},
                             max_frames=max_frames)
    p = source.params
    log.info("sequence %s: %d frames, fx %.1f fy %.1f cx %.1f cy %.1f, depth scale %.0f/m, method %s",
             path, len(source), p.fx, p.fy, p.cx, p.cy, p.depth_scale, method)
    odometry = make_odometry(method)
    stamps: list[float] = []
    poses: list[np.ndarray] = []
    times_s: list[float] = []
    cpu_s: list[float] = []
    failures = 0
    size = (0, 0)
    width = getattr(getattr(odometry, "config", None), "working_width_px", None) or getattr(
        odometry, "working_width_px", 0)
    for frame in source.frames():
        if frame.depth_m is None:
            raise QuadlinkError(f"{path}: frame {frame.seq} has no depth")
        t0, c0 = time.perf_counter(), time.process_time()
        result: OdometryResult = odometry.process(frame.stamp_s, frame.rgb, frame.depth_m, frame.intrinsics)
        times_s.append(time.perf_counter() - t0)
        cpu_s.append(time.process_time() - c0)
        failures += 0 if result.ok else 1
        stamps.append(frame.stamp_s)
        size = (frame.rgb.shape[1], frame.rgb.shape[0])
        poses.append(result.T_c0_ck)
        if frame.seq % 100 == 0 and frame.seq:
            log.info("frame %d / %d", frame.seq, len(source))
    est = np.asarray(poses)
    st = np.asarray(stamps)
    click.echo(f"sequence: {path}  frames: {len(st)}  method: {method}  failed alignments: {failures}")
    gt_file = path / "groundtruth.txt"
    if gt_file.is_file():
        gs, gp = read_tum_trajectory(gt_file)
        ie, ig = metrics.associate_stamps(st, gs)
        if len(ie) < 2:
            raise QuadlinkError(f"{gt_file}: fewer than two ground-truth poses match the frame stamps")
        r = metrics.rpe(st[ie], est[ie], gp[ig])
        a = metrics.ate(est[ie], gp[ig])
        click.echo(f"RPE (consecutive frames, {r.pairs} pairs): translational RMSE {r.trans_rmse_m_s:.4f} m/s, "
                   f"median {r.trans_median_m_s:.4f} m/s; rotational RMSE {r.rot_rmse_deg_s:.3f} deg/s, "
                   f"median {r.rot_median_deg_s:.3f} deg/s")
        click.echo(f"ATE ({a.pairs} poses, Horn-aligned): RMSE {a.rmse_m:.4f} m, median {a.median_m:.4f} m, "
                   f"max {a.max_m:.4f} m")
    else:
        click.echo(f"no {gt_file.name}: metrics skipped")
    per_frame_ms = np.asarray(times_s[1:] or times_s) * 1e3
    cpu_ms = np.asarray(cpu_s[1:] or cpu_s) * 1e3
    click.echo(f"time per frame: median {np.median(per_frame_ms):.1f} ms, mean {np.mean(per_frame_ms):.1f} ms, "
               f"max {np.max(per_frame_ms):.1f} ms wall; median {np.median(cpu_ms):.1f} ms CPU "
               f"(threads: {threads}; frames {size[0]}x{size[1]}, odometry at <= {width} px wide)")
    if out is not None:
        write_tum_trajectory(out, st, est)
        click.echo(f"trajectory written to {out}")

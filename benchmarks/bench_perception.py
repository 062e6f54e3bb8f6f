"""Perception figures (issues 5, 20): odometry accuracy and speed against open3d and OpenCV, obstacle-map update
time, and the whole pipeline's CPU cost per second of flight.

Run: ``.venv/bin/python benchmarks/bench_perception.py [--passes N] [--synthetic-frames N] [--only-odometry]
[--data DIR] [--markdown FILE]``

* Odometry, held out (issue 33): every tunable parameter of a small grid chosen on two of the three shared TUM
  sequences and scored on the third, for each split and each method variant (:mod:`perception.odometry_loo`), beside
  OpenCV and Open3D on the same frames in this process, one thread: the markdown table of ``docs/reference/odometry.md``
  (``--markdown FILE`` writes it to FILE too). This is the odometry's figure; the table below it is not held out.
* Odometry, on the same frames in one run, 640×480 in and 320×240 inside, on one thread
  (``cv2.setNumThreads(1)``, ``OMP_NUM_THREADS=1``): ours (perception.odometry, DVO-style) vs OpenCV's
  ``cv2.Odometry`` (RGB_DEPTH) vs open3d's tensor ``rgbd_odometry_multi_scale`` (Hybrid), on the three shared
  TUM sequences (``../shared/data/tum_fr1_xyz_head`` at the benchmark's own stamps, i.e. the project's fixture
  ``tests/data/tum/fr1_xyz``, ``tum_fr1_rpy_mid``, ``tum_fr3_teddy_head``: colour and
  depth associated, truth interpolated at the colour stamps, exactly as ``quadlink vo-eval``, whose functions
  this calls) and a synthetic textured-room sequence with exact truth. TUM's metrics (RPE over 1 s windows,
  ATE after Horn alignment, per-frame RPE), median CPU ms per frame (``time.process_time``: the CPU cost,
  robust to the shared machine's load; best of ``--passes`` passes), and ours / peer ratios.
  Targets (issue 20): on ``tum_fr1_rpy_mid`` RPE1s <= 0.025 m and <= 2.4 deg; time <= 0.5x the faster peer. The
  shipped defaults were chosen with these sequences in view: not a held-out figure (see the held-out table).
* Obstacle map: sector extraction + eq. (14) time update + measurement + 72-sector summary per QVGA frame.
  Target <= 2 ms.
* ``--sitl-oval SEEDS``: paper 003's oval (take-off, lead-in, the 9 s oval at up to 1 m/s, pan-scan off) in the
  in-process SITL flown on truth, the pipeline's position drift against the truth with the keyframe window
  off and on (issue 20: the window's SITL drift), per seed; nothing else runs.
* ``--sitl-seconds 60``: velocity in H vs SITL truth on an in-process SITL flight (pybullet, IMU and depth
  noise models), both estimators. Target: RMSE per axis <= 0.05 m/s.
* Pipeline: ``PerceptionPipeline`` on a synthetic pan-scanning flight (500 Hz IMU + 30 Hz QVGA frames),
  CPU seconds per second of flight for both estimators, and the per-call costs of the IMU-rate parts.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import math  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any, Literal  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from perception.cli import HEADER, SequenceRun, evaluate, ground_truth_at, load_frames, run_sequence, table_row  # noqa: E402,E501
from perception.obstacle_map import ObstacleMap  # noqa: E402
from perception.obstacles import extract_obstacles  # noqa: E402
from perception.odometry import RgbdOdometry, prepare_frame  # noqa: E402
from perception.pipeline import PerceptionConfig, PerceptionPipeline  # noqa: E402
from perception.synthetic import SyntheticFlight, pose, qvga_intrinsics, render  # noqa: E402
from perception.ukf import Ukf  # noqa: E402
from quadlink.attitude import AttitudeFilter  # noqa: E402
from quadlink.camera import RgbdFrame  # noqa: E402
from quadlink.frames import R_from_euler  # noqa: E402
from quadlink.lie import inv_T  # noqa: E402
from quadlink.vehicle import load_vehicle  # noqa: E402

# the shared data beside the repository (a worktree elsewhere: --data or QUADLINK_SHARED_DATA)
SHARED_DATA = Path(os.environ.get("QUADLINK_SHARED_DATA",
                                  Path(__file__).resolve().parent.parent.parent / "shared" / "data"))
TUM_SEQUENCES = ("tum_fr1_xyz_head", "tum_fr1_rpy_mid", "tum_fr3_teddy_head")
# the shared tum_fr1_xyz_head's stamps are approximate (its README); the project's fixture holds the same images at
# the benchmark's stamps (tests/data/tum/fr1_xyz/README.md), so it stands in for it
RETIMED = {"tum_fr1_xyz_head": Path(__file__).resolve().parent.parent / "tests" / "data" / "tum" / "fr1_xyz"}


def tum_folder(data: Path, seq: str) -> Path:
    return RETIMED.get(seq, data / seq)
METHODS = ("ours", "opencv", "open3d")


def synthetic_sequence(n: int) -> tuple[list[RgbdFrame], np.ndarray]:
    K = qvga_intrinsics()
    frames, poses = [], []
    for k in range(n):
        t = k / 30
        T = pose(R_from_euler(0.1 * math.sin(2 * t), 0.15 * math.sin(3 * t), 0.3 * math.sin(1.5 * t)),
                 [0.3 * math.sin(2 * t), 0.1 * t, 0.2 * math.sin(t)])
        rgb, depth = render(T, K)
        frames.append(RgbdFrame(k, t, rgb, depth, K))
        poses.append(T)
    gt = np.array([inv_T(poses[0]) @ T for T in poses])
    return frames, gt


def run_odometry(method: str, frames: list[RgbdFrame], passes: int, name: str) -> SequenceRun:
    """The method on the frames ``passes`` times: the trajectory of the last pass (all are deterministic) with
    the CPU times of the pass with the lowest median (the machine is shared)."""
    best: SequenceRun | None = None
    for _ in range(passes):
        run = run_sequence(frames, method, name)
        if best is None or np.median(run.cpu_ms) < np.median(best.cpu_ms):
            best = run
    assert best is not None
    return best


def bench_odometry_held_out(data: Path, markdown: Path | None) -> None:
    from perception.cli import leave_one_out_report

    folders = [tum_folder(data, seq) for seq in TUM_SEQUENCES]
    missing = [f for f in folders if not (f / "rgb.txt").is_file()]
    if missing:
        print(f"== odometry held out: skipped ({', '.join(map(str, missing))} not found)")
        return
    print("== RGB-D odometry held out (issue 33): parameters chosen on two sequences, scored on the third; one thread, "
          "CPU ms per frame; RPE over 1 s and frame to frame (RMSE, TUM's pairs by time), ATE after Horn alignment")
    t0 = time.process_time()
    table = leave_one_out_report(folders, progress=lambda msg: print(f"  ({msg})", file=sys.stderr, flush=True))
    print(table)
    print(f"  (held-out evaluation: {time.process_time() - t0:.0f} CPU s)")
    if markdown is not None:
        markdown.write_text(table + "\n", encoding="utf-8")


def bench_odometry(passes: int, n_synth: int, data: Path = SHARED_DATA) -> None:
    print("== RGB-D odometry, 640x480 in, 320x240 inside, one thread: TUM metrics (RPE over 1 s: RMSE over all pairs "
          "1 s apart; ATE after Horn alignment; per-frame RPE), median CPU ms per frame (best of the passes)")
    seqs: list[tuple[str, list[RgbdFrame], Any]] = []
    for seq in TUM_SEQUENCES:
        folder = tum_folder(data, seq)
        if not (folder / "rgb.txt").is_file():
            print(f"  ({folder} not found: skipped)")
            continue
        seqs.append((folder.name, load_frames(folder), folder))
    seqs.append((f"synthetic-{n_synth}", *synthetic_sequence(n_synth)))
    print(f"  {HEADER}")
    ratios = []
    for name, frames, truth in seqs:
        results = {}
        for method in METHODS:
            run = run_odometry(method, frames, passes, name)
            if isinstance(truth, Path):
                gt = ground_truth_at(truth, run.stamps_s)
                assert gt is not None
                m = evaluate(run, *gt)
            else:
                m = evaluate(run, np.ones(len(frames), bool), truth)
            results[method] = (run, m)
            print(f"  {table_row(run, m)}")
        ours_run, ours = results["ours"]
        peers = [results[p] for p in ("opencv", "open3d")]
        faster = min(float(np.median(r.cpu_ms)) for r, _ in peers)
        line = f"  {name}: ours / faster peer time {float(np.median(ours_run.cpu_ms)) / faster:.2f}x (target <= 0.5)"
        for label, key in (("RPE1s trans", "trans_rmse_m"), ("RPE1s rot", "rot_rmse_deg")):
            if ours.rpe_1s.pairs:
                best = min(getattr(m.rpe_1s, key) for _, m in peers)
                line += f"; {label} {getattr(ours.rpe_1s, key) / best:.2f}x the best peer"
        best_ate = min(m.ate.rmse_m for _, m in peers)
        line += f"; ATE {ours.ate.rmse_m / best_ate:.2f}x"
        print(line)
        ratios.append(name)
        if name == TUM_SEQUENCES[1]:   # shared, not retimed
            print(f"  {name}: issue 20 targets RPE1s <= 0.025 m and <= 2.4 deg: ours {ours.rpe_1s.trans_rmse_m:.4f} m, "
                  f"{ours.rpe_1s.rot_rmse_deg:.3f} deg")
    frames = seqs[0][1]
    sp = odometry_split(frames, passes)
    print(f"  ours split on {seqs[0][0]}: prepare_frame {sp['prepare']:.1f} ms + align {sp['align']:.1f} ms per frame "
          f"(from rest, no motion prior, {sp['iterations']:.1f} Gauss-Newton iterations per pair), + "
          f"{sp['reference']:.1f} ms per keyframe (its gradients, points, Jacobians); {sp['keyframes']:.0f} keyframes "
          f"in {len(frames)} frames")


def odometry_split(frames: list[RgbdFrame], passes: int) -> dict[str, float]:
    """Ours only, median CPU ms per frame (best pass): ``prepare_frame``; making a frame a reference (its
    gradients, points and Jacobians: once per keyframe), the first ``align`` against a frame minus a second one
    against the same, now ready, reference; ``align`` against a ready reference (each pair from rest, no motion
    prior); mean Gauss-Newton iterations per pair; keyframes that ``process`` takes on the sequence."""
    odo = RgbdOdometry()
    best = {"prepare": math.inf, "reference": math.inf, "align": math.inf}
    iters: list[int] = []
    for _ in range(passes):
        t_prep, t_ref, t_align, iters = [], [], [], []
        prev = None
        for f in frames:
            assert f.depth_m is not None   # RGB-D sequences
            t0 = time.process_time()
            cur = prepare_frame(f.rgb, f.depth_m, f.intrinsics, odo.config)
            t_prep.append(time.process_time() - t0)
            if prev is not None:
                t0 = time.process_time()
                odo.align(prev, cur)
                t1 = time.process_time()
                iters.append(odo.align(prev, cur).iterations)
                t2 = time.process_time()
                t_ref.append((t1 - t0) - (t2 - t1))
                t_align.append(t2 - t1)
            prev = cur
        for key, t in (("prepare", t_prep), ("reference", t_ref), ("align", t_align)):
            best[key] = min(best[key], float(np.median(t)) * 1e3)
    odo = RgbdOdometry()
    for f in frames:
        assert f.depth_m is not None   # RGB-D sequences
        odo.process(f.stamp_s, f.rgb, f.depth_m, f.intrinsics)
    return {**best, "iterations": float(np.mean(iters)), "keyframes": odo.keyframes}


def bench_obstacle_map(n: int = 200, passes: int = 3) -> None:
    print("== obstacle sectors + local map update per QVGA frame (target <= 2 ms)")
    veh = load_vehicle()
    K = qvga_intrinsics()
    flight = SyntheticFlight(veh.camera.R_qc_matrix, np.asarray(veh.camera.p_qc_m))
    depths = [render(flight.T_w_c(k / 30), K, supersample=1)[1] for k in range(30)]
    best: tuple[float, np.ndarray, np.ndarray] | None = None
    for _ in range(passes):   # best pass: the machine is shared
        m = ObstacleMap()
        rng = np.random.default_rng(0)
        times, parts = [], np.zeros(4)
        for k in range(n):
            t = k / 30
            d = depths[k % len(depths)]
            t0 = time.process_time()
            obs = extract_obstacles(d, K, veh.camera.R_qc_matrix, np.asarray(veh.camera.p_qc_m), 0.02, -0.03)
            t1 = time.process_time()
            m.predict(1 / 30, np.array([0.3, 0.0, 0.0]), np.array([0.3, 0.0, 0.0]), 0.5, 0.5, rng)
            t2 = time.process_time()
            m.measure(t, obs)
            t3 = time.process_time()
            m.sectors(t)
            t4 = time.process_time()
            times.append(t4 - t0)
            parts += (t1 - t0, t2 - t1, t3 - t2, t4 - t3)
        if best is None or np.median(times) < best[0]:
            best = (float(np.median(times)), np.array(times), parts / n)
    assert best is not None
    _, best_times, parts = best
    print(f"  median {np.median(best_times) * 1e3:.2f} ms, p95 {np.percentile(best_times, 95) * 1e3:.2f} ms, "
          f"{len(m)} particles at the end")
    print("  of which (mean ms) sectors from depth {:.2f}, eq. (14) time update {:.2f}, measurement {:.2f}, "
          "72-sector summary {:.2f}".format(*(parts * 1e3)))


def bench_pipeline(seconds: float = 3.0) -> None:
    print("== perception pipeline on a synthetic pan-scanning flight (500 Hz IMU, 30 Hz QVGA)")
    veh = load_vehicle()
    K = qvga_intrinsics()
    R_qc, p_qc = veh.camera.R_qc_matrix, np.asarray(veh.camera.p_qc_m)
    flight = SyntheticFlight(R_qc, p_qc)
    rng = np.random.default_rng(1)
    imu = [(i / 500, flight.gyro(i / 500) + rng.normal(0, 0.01, 3), flight.specific_force(i / 500)
            + rng.normal(0, 0.1, 3)) for i in range(int(seconds * 500))]
    frames = {i: RgbdFrame(i, i / 500, *render(flight.T_w_c(i / 500), K, supersample=1), K)
              for i in range(0, len(imu), 17)}
    for est in ("filters", "ukf"):
        pipe = PerceptionPipeline(PerceptionConfig(estimator=est), K, R_qc, p_qc, np.random.default_rng(2))
        t_imu = t_frame = 0.0
        t_odo = [0.0]
        odometry = pipe._odometry               # instrumented: CPU time of the odometry inside on_frame

        def timed_process(*args: Any, process: Callable[..., Any] = odometry.process,
                          t_odo: list[float] = t_odo) -> Any:
            t0 = time.process_time()
            out = process(*args)
            t_odo[0] += time.process_time() - t0
            return out

        setattr(odometry, "process", timed_process)  # noqa: B010 (mypy: a method, replaced for this run)
        errs = []
        for i, (t, g, a) in enumerate(imu):
            t0 = time.process_time()
            pipe.on_imu(t, g, a)
            t_imu += time.process_time() - t0
            if i in frames:
                t0 = time.process_time()
                out = pipe.on_frame(frames[i])
                t_frame += time.process_time() - t0
                if t > 1.0:
                    errs.append(out.v_h_m_s - flight.v_h(t))
        rmse = np.sqrt(np.mean(np.square(errs), axis=0))
        print(f"  {est:7s}: {(t_imu + t_frame) / seconds:.3f} CPU s per s of flight "
              f"(IMU {t_imu / seconds:.3f}, frames {t_frame / seconds:.3f}; "
              f"{t_frame / len(frames) * 1e3:.1f} ms/frame); "
              f"v_h RMSE x/y/z {rmse[0]:.3f}/{rmse[1]:.3f}/{rmse[2]:.3f} m/s (issue target <= 0.05)")
        print(f"           outside the odometry {(t_frame - t_odo[0]) / len(frames) * 1e3:.2f} ms/frame, "
              f"on_imu {t_imu / len(imu) * 1e6:.1f} us per sample")
    f = AttitudeFilter()
    g, a = np.array([0.1, 0.0, 0.0]), np.array([0.0, 0.0, -9.81])
    n = 5000
    t0 = time.process_time()
    for i in range(n):
        f.update(i * 0.002, g, a)
    print(f"  attitude filter update: {(time.process_time() - t0) / n * 1e6:.1f} us per IMU sample")
    u = Ukf()
    u.initialise(0.0, np.eye(3))
    t0 = time.process_time()
    for _ in range(200):
        u.predict(0.01, g, a)
    t_pred = (time.process_time() - t0) / 200
    t0 = time.process_time()
    for _ in range(200):
        u.on_pose(0.0, np.zeros(3), np.eye(3))
    t_upd = (time.process_time() - t0) / 200
    print(f"  UKF predict (100 Hz): {t_pred * 1e6:.0f} us, pose update: {t_upd * 1e6:.0f} us")


def _sitl_rig(scenario: str, config: PerceptionConfig, seed: int) -> tuple[Any, Any, Any, Any, PerceptionPipeline]:
    """The in-process SITL vehicle (world, firmware, IMU) in ``scenario``, its camera and a pipeline on them:
    (vehicle config, SITL config, SimVehicle, RgbdCamera, PerceptionPipeline)."""
    from sim_sitl.camera_sim import RgbdCamera
    from sim_sitl.config import load_scenario, load_sitl_config
    from sim_sitl.vehicle_sim import SimVehicle

    veh = load_vehicle()
    cfg = load_sitl_config()
    sim = SimVehicle(veh, cfg, load_scenario(scenario), np.random.default_rng(seed))
    cam = RgbdCamera(sim.world, veh.camera, cfg.camera_noise, np.random.default_rng(seed + 1))
    pipe = PerceptionPipeline(config, cam.intrinsics, cam.R_qc, np.asarray(cam.p_qc_m), np.random.default_rng(seed + 2))
    return veh, cfg, sim, cam, pipe


def sitl_flight(seconds: float, estimator: Literal["filters", "ukf"], seed: int = 0) -> None:
    """In-process SITL (pybullet world, firmware, IMU and camera models with noise; no sockets): a pan-scanning
    flight flown on the *true* state (so the estimate is only measured, not in the loop), perception vs truth."""
    from quadlink.frames import Rz, euler_from_R
    from sim_sitl.firmware import AttitudeCommand

    veh, _, sim, cam, pipe = _sitl_rig("paper-arena", PerceptionConfig(estimator=estimator), seed)
    hover = veh.hover_thrust_fraction
    g = 9.81
    errs, t_cpu, n_frames, ok = [], 0.0, 0, 0
    truth, yaws = [], []
    frame_every = round(500 / veh.camera.rate_hz)
    seq = 0
    try:
        while sim.t_s < seconds:
            res = sim.tick()
            s, t = res.state, res.t_s
            pipe.on_imu(t, res.imu.gyro_q_rad_s, res.imu.accel_q_m_s2)
            if res.tick % 5 == 0:   # 100 Hz truth-based controller: altitude 1.2 m, slow figure, pan-scan
                roll, pitch, yaw = euler_from_R(s.R_ned_q)
                z_ref = -1.2
                climb = t > 1.0
                if t < 4.0:
                    v_ref_w = np.zeros(3)
                else:
                    v_ref_w = np.array([0.35 * math.sin(0.25 * (t - 4)), 0.35 * math.sin(0.17 * (t - 4)), 0.0])
                a_w = 1.5 * (v_ref_w - s.v_ned_m_s) + 0.6 * (np.array([-3.0, 0.0, 0.0]) - s.p_ned_m) * (t < 4.0)
                a_h = Rz(yaw).T @ a_w
                pitch_sp = float(np.clip(-a_h[0] / g, -0.3, 0.3))
                roll_sp = float(np.clip(a_h[1] / g, -0.3, 0.3))
                thrust = hover * (1 + 0.25 * (s.p_ned_m[2] - z_ref) + 0.35 * s.v_ned_m_s[2]) if climb else 0.3 * hover
                yaw_rate = 0.6 * math.sin(2 * math.pi * 0.2 * t) if t > 4.0 else 0.0
                sim.on_setpoint(AttitudeCommand(roll_sp, pitch_sp, yaw_rate, float(np.clip(thrust, 0, 1)), True,
                                                (res.tick // 5) & 0xFF))
            if res.tick % frame_every == 0:
                frame = cam.render(s, seq, t)
                seq += 1
                c0 = time.process_time()
                out = pipe.on_frame(frame)
                t_cpu += time.process_time() - c0
                n_frames += 1
                ok += out.odometry_ok
                if t > 6.0:
                    v_h_true = Rz(euler_from_R(s.R_ned_q)[2]).T @ s.v_ned_m_s
                    errs.append(out.v_h_m_s - v_h_true)
                    truth.append(v_h_true)
                    yaws.append(euler_from_R(s.R_ned_q)[2])
    finally:
        sim.close()
    if not errs:
        print(f"  {estimator}: flight too short (errors are taken after 6 s)")
        return
    e = np.array(errs)
    rmse = np.sqrt(np.mean(e**2, axis=0))
    v_rms = np.sqrt(np.mean(np.square(truth), axis=0))
    print(f"  {estimator:7s}: v_h RMSE x/y/z {rmse[0]:.3f}/{rmse[1]:.3f}/{rmse[2]:.3f} m/s (target <= 0.05), "
          f"max |err| {np.abs(e).max():.3f}; true v_h rms {v_rms[0]:.2f}/{v_rms[1]:.2f}/{v_rms[2]:.2f} m/s, "
          f"yaw swept {np.degrees(np.ptp(np.unwrap(yaws))):.0f} deg; odometry ok {ok / max(n_frames, 1):.1%} of "
          f"{n_frames} frames; {t_cpu / max(n_frames, 1) * 1e3:.1f} CPU ms/frame")



def sitl_oval(window: bool, seed: int = 0, **odometry: Any) -> dict[str, Any]:
    """In-process SITL (pybullet world, firmware, IMU and camera models with noise; no sockets) flying paper 003's
    oval as ``quadlink paper003 oval`` does (``configs/scenarios`` ``empty``, pan-scan off, heading 0): take-off
    to 1.2 m, 6 s to P1, the 9 s oval (up to 1 m/s), 2 s hold, flown on the *true* state so that the odometry is
    only measured. The pipeline's body position against the truth, as drift from the first tracked frame above
    0.8 m (the local world's yaw is the first frame's, ~0), and its floor height (``perception.floor``) against the
    true height. ``window``: ``keyframe_refinement``; ``odometry``: other
    :class:`OdometryConfig` fields."""
    from dataclasses import replace

    from harness.trajectory_cli import load_trajectory_file
    from quadlink import CONFIG_DIR
    from quadlink.frames import Rz, euler_from_R
    from quadlink.trajectory.minsnap import minimum_snap
    from sim_sitl.firmware import AttitudeCommand

    pcfg = PerceptionConfig()
    pcfg = replace(pcfg, odometry=replace(pcfg.odometry, keyframe_refinement=window, **odometry))
    veh, _, sim, cam, pipe = _sitl_rig("empty", pcfg, seed)
    _, oval = load_trajectory_file(CONFIG_DIR / "trajectories" / "oval.yaml")
    p0 = sim.world.state.p_ned_m.copy()
    hover_p = p0 + np.array([0.0, 0.0, -1.2 - p0[2]])
    t_up, t_lead = 4.0, 6.0
    lead = minimum_snap(np.array([hover_p, oval.sample(0.0).p_m]), [t_lead])
    t_end = t_up + t_lead + oval.duration_s + 2.0

    def reference(t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if t < t_up:
            z = p0[2] + (hover_p[2] - p0[2]) * min(t / (t_up - 1.0), 1.0)
            return np.array([p0[0], p0[1], z]), np.zeros(3), np.zeros(3)
        r = lead.sample(t - t_up) if t < t_up + t_lead else oval.sample(t - t_up - t_lead)
        return r.p_m, r.v_m_s, r.a_m_s2

    g = 9.81
    frame_every = round(500 / veh.camera.rate_hz)
    rows, seq, n_ok, n_frames = [], 0, 0, 0
    try:
        while sim.t_s < t_end:
            res = sim.tick()
            s, t = res.state, res.t_s
            pipe.on_imu(t, res.imu.gyro_q_rad_s, res.imu.accel_q_m_s2)
            if res.tick % 5 == 0:   # 100 Hz truth-based tracker with the reference's acceleration
                p_r, v_r, a_r = reference(t)
                roll, pitch, yaw = euler_from_R(s.R_ned_q)
                a_w = a_r + 0.45 * v_r + 4.0 * (p_r - s.p_ned_m) + 3.0 * (v_r - s.v_ned_m_s)
                a_h = Rz(yaw).T @ a_w
                thrust = veh.hover_thrust_fraction * (g - a_w[2]) / g / max(math.cos(roll) * math.cos(pitch), 0.5)
                sim.on_setpoint(AttitudeCommand(float(np.clip(a_h[1] / g, -0.3, 0.3)),
                                                float(np.clip(-a_h[0] / g, -0.3, 0.3)), -1.0 * yaw,
                                                float(np.clip(thrust, 0.0, 1.0)), True, (res.tick // 5) & 0xFF))
            if res.tick % frame_every == 0:
                out = pipe.on_frame(cam.render(s, seq, t))
                seq += 1
                n_frames += 1
                n_ok += out.odometry_ok
                floor_m = math.nan if out.floor_height_m is None else out.floor_height_m
                rows.append((t, *out.position_m, *s.p_ned_m, out.odometry_ok, floor_m - (-s.p_ned_m[2])))
    finally:
        sim.close()
    a = np.array(rows, dtype=float)
    start = int(np.argmax((a[:, 6] < -0.8) & (a[:, 7] > 0)))
    d_est = a[start:, 1:4] - a[start, 1:4]
    d_true = a[start:, 4:7] - a[start, 4:7]
    e = d_est - d_true
    t = a[start:, 0]
    in_oval = (t >= t_up + t_lead) & (t <= t_up + t_lead + oval.duration_s)
    e_oval = e[in_oval] - e[in_oval][0]
    e_floor = a[start:, 8][np.isfinite(a[start:, 8])]
    return {"window": window, "frames": n_frames, "ok": n_ok / max(n_frames, 1), "from_s": float(a[start, 0]),
            "end_error_m": e[-1], "max_error_m": np.abs(e).max(axis=0), "oval_drift_m": e_oval[-1],
            "oval_max_m": np.abs(e_oval).max(axis=0), "keyframes": pipe._odometry.keyframes,
            "refined": pipe._odometry.refined_keyframes, "rejected": pipe._odometry.rejected_refinements, "rows": a,
            "floor_rms_m": float(np.sqrt(np.mean(e_floor**2))), "floor_max_m": float(np.abs(e_floor).max())}


def print_sitl_oval(seeds: int) -> None:
    print("== paper 003's oval in the in-process SITL (empty room, pan-scan off), flown on truth: the pipeline's body "
          "position drift against the truth (m, NED), window off / on")
    for seed in range(seeds):
        for window in (False, True):
            r = sitl_oval(window, seed)
            f = lambda v: "/".join(f"{x:+.3f}" for x in v)   # noqa: E731
            print(f"  seed {seed} window {'on ' if window else 'off'}: end {f(r['end_error_m'])}, max |e| "
                  f"{f(r['max_error_m'])} (from {r['from_s']:.1f} s); over the oval drift {f(r['oval_drift_m'])}, "
                  f"max |e| {f(r['oval_max_m'])}; ok {r['ok']:.1%} of {r['frames']}, keyframes {r['keyframes']}, "
                  f"refined {r['refined']}, refused {r['rejected']}; floor height error rms "
                  f"{r['floor_rms_m']:.3f}, max {r['floor_max_m']:.3f}", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--passes", type=int, default=3)
    ap.add_argument("--synthetic-frames", type=int, default=45)
    ap.add_argument("--skip-odometry", action="store_true")
    ap.add_argument("--only-odometry", action="store_true", help="the odometry comparison alone")
    ap.add_argument("--data", type=Path, default=SHARED_DATA, help="folder of the shared TUM sequences")
    ap.add_argument("--markdown", type=Path, default=None, help="also write the held-out odometry table here")
    ap.add_argument("--skip-held-out", action="store_true", help="skip the held-out odometry table (minutes)")
    ap.add_argument("--sitl-seconds", type=float, default=0.0,
                    help="also fly an in-process SITL pan-scan flight this long (issue: 60 s; minutes each)")
    ap.add_argument("--sitl-oval", type=int, default=0, metavar="SEEDS",
                    help="paper 003's oval in the in-process SITL, window off and on, for this many seeds")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    if args.sitl_oval:
        print_sitl_oval(args.sitl_oval)
        return
    print(f"load average at start: {os.getloadavg()[0]:.2f} (shared machine; times are CPU time of this process)")
    if not args.skip_odometry:
        if not args.skip_held_out:
            bench_odometry_held_out(args.data, args.markdown)
        bench_odometry(args.passes, args.synthetic_frames, args.data)
    if args.only_odometry:
        return
    bench_obstacle_map()
    bench_pipeline()
    if args.sitl_seconds > 0:
        print(f"== velocity in H vs SITL truth, {args.sitl_seconds:.0f} s pan-scanning flight with sensor noise "
              "(paper-arena, errors after 6 s)")
        for est in ("filters", "ukf"):
            sitl_flight(args.sitl_seconds, est)


if __name__ == "__main__":
    main()

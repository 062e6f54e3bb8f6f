"""Ground-station figures (issue 7).

1. Force loop at 1 kHz: period statistics and p99 jitter |period - 1 ms| while the operator view runs
   (30 Hz JPEG image stream decoded, compensated, rendered, JPEG-encoded, fetched over HTTP at 15 Hz)
   and the MAVLink loop sends MANUAL_CONTROL at 50 Hz. Target (issue 7): p99 jitter <= 0.5 ms.
2. Pan-scan compensation on a synthetic pan-scanning sequence with the companion's default carrier
   (A = 0.6 rad/s, omega = 1.5 rad/s), a first-order yaw loop (tau = 0.15 s, 20 ms delay), operator yaw
   commands, gyro bias, gyro quantisation and noise, roll/pitch wobble; camera meta at 30 Hz. Figure: RMS
   horizontal shift of the image of the centre-of-oscillation direction from the screen centre, raw vs
   compensated (MK camera: 45 deg right, 30 deg down, portrait). Target (issue 7): residual <= 10 %.

    python benchmarks/bench_teleop.py [--seconds 10]
"""

from __future__ import annotations

import argparse
import logging
import math
import multiprocessing
import os
import tempfile
import time
import urllib.request
from typing import Any

import numpy as np

from quadlink.camera import CameraIntrinsics, CameraStreamServer, RgbdFrame
from quadlink.frames import R_hq, Rz
from quadlink.operator_image import OperatorImageMeta, PanScanMeta
from quadlink.vehicle import load_vehicle
from teleop.config import TeleopConfig
from teleop.force_loop import DeviceSpec
from teleop.station import Station
from teleop.view.compensation import R_vc, project, screen_intrinsics
from teleop.view.panscan import PanScanEstimator


def _fake_image_stream(port_queue: Any, stop: Any) -> None:
    """In a separate process (so it does not share the station's interpreter): the companion's image stream."""
    vehicle = load_vehicle()
    cam = vehicle.camera
    intr = CameraIntrinsics.from_fov(cam.width_px, cam.height_px, cam.hfov_deg, cam.vfov_deg)
    rgb = np.random.default_rng(1).integers(0, 255, (cam.height_px, cam.width_px, 3), dtype=np.uint8)
    server = CameraStreamServer("127.0.0.1", 0)
    port_queue.put(server.port)
    seq = 0
    while not stop.is_set():
        t = seq / 30.0
        meta = OperatorImageMeta(
            stamp_s=t, roll_rad=0.02, pitch_rad=-0.03, yaw_rad=0.0, gyro_yaw_rate_rad_s=0.6 * math.sin(1.5 * t),
            obstacle_points_c_m=tuple((0.1 * i, 0.0, 1.0 + 0.1 * i) for i in range(20)),
            v_cmd_h_m_s=(0.3, 0.0, 0.0), v_est_h_m_s=(0.25, 0.02, 0.0),
            pan_scan=PanScanMeta(True, 0.6 * math.sin(1.5 * t), 0.4 * math.sin(1.5 * t - math.pi / 2),
                                 math.radians(45.0), 0.6, 1.5),
            mode="teleop").to_wire()   # the companion's typed metadata (the station rejects anything else)
        server.publish(RgbdFrame(seq, t, rgb, None, intr, cam.R_qc_matrix, np.zeros(3), meta), rgb_jpeg=True)
        seq += 1
        stop.wait(1 / 30.0)
    server.close()


def _browser(url: str, stop: Any) -> None:
    """In a separate process: a browser polling the page's image at 15 Hz."""
    while not stop.is_set():
        try:
            urllib.request.urlopen(url, timeout=2).read()
        except OSError:
            pass
        stop.wait(1 / 15.0)


def bench_force_loop(seconds: float) -> dict[str, float]:
    cfg = TeleopConfig()
    ctx = multiprocessing.get_context("spawn")
    stop = ctx.Event()
    ports = ctx.Queue()
    publisher = ctx.Process(target=_fake_image_stream, args=(ports, stop), daemon=True)
    publisher.start()
    port = ports.get(timeout=30)
    with tempfile.NamedTemporaryFile("w", suffix=".yaml", delete=False) as f:
        f.write("steps:\n  - push: forward\n    force_n: 1.0\n    duration_s: 100000\n")
    # the force loop in its own process, as quadlink teleop runs it
    station = Station(cfg, DeviceSpec("virtual", f.name), "udpout:127.0.0.1:9", f"tcp://127.0.0.1:{port}",
                      http_port=0)
    station.start()
    assert station.server is not None
    browser = ctx.Process(target=_browser, args=(station.server.url + "frame.jpg", stop), daemon=True)
    browser.start()
    time.sleep(1.5)
    n0 = station.force_periods_s().size
    frames0 = station.view_frames
    cpu0, wall0 = time.process_time(), time.perf_counter()
    time.sleep(seconds)
    cpu_pct = 100.0 * (time.process_time() - cpu0) / (time.perf_counter() - wall0)
    periods = station.force_periods_s()[n0:]
    frames = station.view_frames - frames0
    stop.set()
    station.close()
    publisher.join(timeout=5)
    browser.join(timeout=5)
    os.unlink(f.name)
    jitter = np.abs(periods - 1e-3)
    return {"ticks": float(periods.size), "rate_hz": periods.size / max(periods.sum(), 1e-9),
            "p50_ms": float(np.percentile(periods, 50) * 1e3), "p99_ms": float(np.percentile(periods, 99) * 1e3),
            "max_ms": float(periods.max() * 1e3), "jitter_p99_ms": float(np.percentile(jitter, 99) * 1e3),
            "view_fps": frames / seconds, "cpu_pct": cpu_pct}


def synthetic_pan_scan(seconds: float, rng: np.random.Generator, operator_yaw_rad_s: float) -> dict[str, np.ndarray]:
    """Yaw of a first-order yaw loop driven by operator commands + the pan-scan carrier (eq. 4)."""
    dt_sim, fs_cam = 1e-3, 30.0
    A, omega, tau, delay = 0.6, 1.5, 0.15, 0.02
    t = np.arange(0.0, seconds, dt_sim)
    # operator turns: 0.25 rad/s right for ~4.5 s every 23 s (and as much left), ~40 % of the time turning
    phase = np.sin(2 * np.pi * t / 23.0)
    operator = operator_yaw_rad_s * (np.where(phase > 0.6, 1.0, 0.0) - np.where(phase < -0.6, 1.0, 0.0))
    pan = A * np.sin(omega * t)
    n_delay = int(round(delay / dt_sim))
    rate_pan = np.zeros_like(t)     # the response to the two inputs, kept apart (linear superposition)
    rate_op = np.zeros_like(t)
    for k in range(1, t.size):
        j = max(k - n_delay, 0)
        rate_pan[k] = rate_pan[k - 1] + dt_sim / tau * (pan[j] - rate_pan[k - 1])
        rate_op[k] = rate_op[k - 1] + dt_sim / tau * (operator[j] - rate_op[k - 1])
    psi_pan = np.cumsum(rate_pan) * dt_sim
    # centre of oscillation: the pan-scan yaw has no mean in steady state; remove the start transient's offset
    steady = t > 10.0
    psi_s_true = psi_pan - psi_pan[steady].mean()
    idx = np.arange(0, t.size, int(round(1 / (fs_cam * dt_sim))))
    gyro_lsb = load_vehicle().imu.gyro_lsb_rad_s
    gyro = rate_pan[idx] + rate_op[idx] + 0.03 + rng.normal(0.0, 0.02, idx.size)
    gyro = np.round(gyro / gyro_lsb) * gyro_lsb          # 10-bit ADC quantisation
    roll = 0.05 * np.sin(2 * np.pi * 0.7 * t[idx] + 0.5)
    pitch = 0.04 * np.sin(2 * np.pi * 0.45 * t[idx])
    latency = 2   # the operator command reaches the view ~2 frames late (TELEOP_FEEDBACK at 50 Hz + network)
    op_cmd = np.concatenate([np.zeros(latency), operator[idx][:-latency]])
    return {"t": t[idx], "gyro": gyro, "psi_s": psi_s_true[idx], "roll": roll, "pitch": pitch, "op_cmd": op_cmd}


def bench_compensation(operator_yaw_rad_s: float, use_operator_cmd: bool, seconds: float = 120.0) -> dict[str, float]:
    cfg = TeleopConfig()
    vehicle = load_vehicle()
    cam = vehicle.camera
    intr = CameraIntrinsics.from_fov(cam.width_px, cam.height_px, cam.hfov_deg, cam.vfov_deg)
    screen = screen_intrinsics(intr, cfg.view.canvas_width_px, cfg.view.canvas_height_px)
    R_qc = cam.R_qc_matrix
    seq = synthetic_pan_scan(seconds, np.random.default_rng(7), operator_yaw_rad_s)
    v = cfg.view
    est = PanScanEstimator(v.initial_frequency_hz, v.min_frequency_hz, v.max_frequency_hz, v.bandpass_q,
                           v.bias_periods, operator_yaw_time_constant_s=v.operator_yaw_time_constant_s)
    d_h = R_qc[:, 2] / np.linalg.norm(R_qc[:, 2])   # direction of the centre of oscillation (level body)
    raw, comp, psi_err = [], [], []
    t0 = time.perf_counter()
    for k, t in enumerate(seq["t"]):
        e = est.update(float(seq["gyro"][k]), float(t), True, float(seq["op_cmd"][k]) if use_operator_cmd else 0.0)
        if t < 20.0:
            continue
        roll, pitch, psi = float(seq["roll"][k]), float(seq["pitch"][k]), float(seq["psi_s"][k])
        d_c = (Rz(psi) @ R_hq(roll, pitch) @ R_qc).T @ d_h     # the direction, in the real camera frame
        u_raw = project(d_c[None, :], R_vc(R_qc, 0.0, 0.0, 0.0), screen)[0, 0]     # image shown as is (upright)
        u_comp = project(d_c[None, :], R_vc(R_qc, roll, pitch, e.yaw_rad), screen)[0, 0]
        raw.append(u_raw - screen.cx)
        comp.append(u_comp - screen.cx)
        psi_err.append(e.yaw_rad - psi)
    cost_us = (time.perf_counter() - t0) / len(seq["t"]) * 1e6
    raw_rms = float(np.sqrt(np.mean(np.square(raw))))
    comp_rms = float(np.sqrt(np.mean(np.square(comp))))
    return {"raw_rms_px": raw_rms, "compensated_rms_px": comp_rms, "residual_pct": 100.0 * comp_rms / raw_rms,
            "psi_err_rms_deg": math.degrees(float(np.sqrt(np.mean(np.square(psi_err))))),
            "psi_s_rms_deg": math.degrees(float(np.sqrt(np.mean(np.square(seq["psi_s"][seq["t"] >= 20.0]))))),
            "frequency_hz": est.last.frequency_hz, "true_frequency_hz": 1.5 / (2 * math.pi),
            "cost_us_per_frame": cost_us}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=10.0, help="force-loop measurement time")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    print("== pan-scan compensation (synthetic, MK camera, 30 Hz meta, 100 s after 20 s warm-up) ==")
    print("RMS horizontal shift of the centre-of-oscillation direction from the screen centre; target <= 10 %")
    print(f"{'scenario':58s} {'f est/true Hz':>15s} {'psi_s rms':>9s} {'raw px':>7s} {'comp px':>7s} {'residual':>8s}")
    for label, op, use in (("no operator yaw (pan-scan only; paper's scheme)", 0.0, False),
                           ("operator turns 0.25 rad/s, gyro only (paper's scheme)", 0.25, False),
                           ("operator turns 0.25 rad/s, operator command removed", 0.25, True)):
        c = bench_compensation(op, use)
        print(f"{label:58s} {c['frequency_hz']:6.4f}/{c['true_frequency_hz']:6.4f}  {c['psi_s_rms_deg']:6.2f} deg "
              f"{c['raw_rms_px']:7.2f} {c['compensated_rms_px']:7.2f} {c['residual_pct']:7.1f} %"
              f"  {'met' if c['residual_pct'] <= 10 else 'NOT met'}")
    print(f"estimator + projection cost: {c['cost_us_per_frame']:.0f} us per frame")
    print(f"\n== force loop, 1 kHz, with the operator view running ({args.seconds:.0f} s) ==")
    f = bench_force_loop(args.seconds)
    print(f"ticks {f['ticks']:.0f}  rate {f['rate_hz']:.1f} Hz  view {f['view_fps']:.1f} frames/s  "
          f"ground-station CPU {f['cpu_pct']:.0f} % of one core")
    print(f"period p50 {f['p50_ms']:.3f} ms  p99 {f['p99_ms']:.3f} ms  max {f['max_ms']:.3f} ms")
    print(f"jitter p99 |period - 1 ms| = {f['jitter_p99_ms']:.3f} ms   (target <= 0.5 ms: "
          f"{'met' if f['jitter_p99_ms'] <= 0.5 else 'NOT met'})")


if __name__ == "__main__":
    main()

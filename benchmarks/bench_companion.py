"""Companion daemon benchmark: frame-to-setpoint latency and whole-daemon CPU per second of flight.

Runs ``quadlink companion`` as a subprocess with the real perception pipeline, fed in real time at 30 Hz
with 320x240 RGB-D frames over the camera stream (lock-step acks) and 500 Hz HIGHRES_IMU from a fake
autopilot over UDP. Frames are rendered from perception's synthetic textured room along a flight with
the pan-scan yaw swing (or replayed from a TUM folder with ``--tum``).

* latency: ``publish(frame)`` -> the SET_POSITION_TARGET_LOCAL_NED stamped with that frame received by the
  autopilot side (both clocks in this process). Reference targets: p50 <= 15 ms, p99 <= 30 ms.
* CPU: user+system seconds of the daemon process over the measured span / seconds of flight (real-time
  pacing: flight time = wall time). Reference target: <= 0.3 core-s/s.
* link decode: CPU µs per HIGHRES_IMU received, ``mavutil`` ``recv_msg`` vs the daemon's codec reader.

    python benchmarks/bench_companion.py [--seconds 20] [--tum /work/shared/data/tum_fr1_xyz_head]
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import psutil

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from perception.synthetic import pose, qvga_intrinsics, render  # noqa: E402
from quadlink.camera import CameraStreamServer, RgbdFrame  # noqa: E402
from quadlink.frames import Rz  # noqa: E402
from quadlink.mavlink import mavlink  # noqa: E402
from quadlink.mavlink.connection import open_mavlink  # noqa: E402
from quadlink.vehicle import CameraConfig  # noqa: E402

FPS = 30.0
IMU_HZ = 500
TARGET_P50_S, TARGET_P99_S, TARGET_CPU = 0.015, 0.030, 0.3
PAN_A_RAD_S, PAN_W_RAD_S = 0.6, 1.5


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def synthetic_frames(n: int) -> tuple[list[RgbdFrame], np.ndarray]:
    """Frames along a slow forward flight with the pan-scan yaw swing; returns frames and yaw rates."""
    cam = CameraConfig()
    R_qc, p_qc = cam.R_qc_matrix, cam.p_qc
    K = qvga_intrinsics()
    frames, rates = [], []
    for k in range(n):
        t = k / FPS
        yaw = -(PAN_A_RAD_S / PAN_W_RAD_S) * math.cos(PAN_W_RAD_S * t)
        R_wq = Rz(yaw)
        p_wq = np.array([-0.6 + 0.2 * t, 0.0, 0.3])
        rgb, depth = render(pose(R_wq @ R_qc, p_wq + R_wq @ p_qc), K)
        frames.append(RgbdFrame(k + 1, t, rgb, depth, K, R_qc, p_qc))
        rates.append(PAN_A_RAD_S * math.sin(PAN_W_RAD_S * t))
    return frames, np.asarray(rates)


def tum_frames(folder: str, n: int) -> tuple[list[RgbdFrame], np.ndarray]:
    from perception.sources import TumFolderSource

    src = TumFolderSource(folder, max_frames=n, resize_to=(320, 240))
    cam = CameraConfig()
    out = []
    for f in src.frames():
        out.append(dataclasses.replace(f, R_qc=cam.R_qc_matrix, p_qc_m=cam.p_qc))
    return out, np.zeros(len(out))


def run(seconds: float, tum: str | None, warmup_s: float = 3.0, profile: str | None = None) -> dict[str, float]:
    n_unique = int(min(seconds + warmup_s, 4.0) * FPS)
    t0 = time.perf_counter()
    frames, rates = tum_frames(tum, n_unique) if tum else synthetic_frames(n_unique)
    print(f"prepared {len(frames)} {'TUM' if tum else 'synthetic'} frames in {time.perf_counter() - t0:.1f} s")
    ap_port, gcs_port = free_udp_port(), free_udp_port()
    server = CameraStreamServer("127.0.0.1", 0)
    prof = ["-m", "cProfile", "-o", profile] if profile else []
    argv = [sys.executable, *prof, "-m", "quadlink.cli", "-q", "companion", "--autopilot", f"udpin:127.0.0.1:{ap_port}",
            "--gcs", f"udpin:127.0.0.1:{gcs_port}", "--camera", f"tcp://127.0.0.1:{server.port}",
            "--image-port", "0"]
    proc = subprocess.Popen(argv, stdin=subprocess.DEVNULL, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    ap = open_mavlink(f"udpout:127.0.0.1:{ap_port}", 1, 1)
    latencies: list[float] = []
    try:
        if not server.wait_for_client(20.0):
            raise RuntimeError("companion did not connect to the camera stream")
        ps = psutil.Process(proc.pid)
        period = 1.0 / FPS
        n_total = int((seconds + warmup_s) * FPS)
        start = time.perf_counter()
        cpu0 = None
        t_measure0 = 0.0
        for k in range(n_total):
            n = len(frames)  # play the prepared frames forward and back (no jump for the odometry)
            idx = k % max(2 * n - 2, 1)
            backward = idx >= n
            if backward:
                idx = 2 * n - 2 - idx
            base = frames[idx]
            stamp = k * period
            if k % int(FPS) == 0:
                ap.mav.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, 0, 0,
                                      mavlink.MAV_STATE_STANDBY)
            r = -float(rates[idx]) if backward else float(rates[idx])
            for i in range(int(IMU_HZ / FPS)):
                t_us = int(max(0.0, stamp - period + (i + 1) / IMU_HZ) * 1e6)
                ap.mav.highres_imu_send(t_us, 0.0, 0.0, -9.81, 0.0, 0.0, r, 0, 0, 0, 0, 0, 0, 20.0, 0x3F)
            if k == int(warmup_s * FPS):
                cpu_t = ps.cpu_times()
                cpu0 = cpu_t.user + cpu_t.system
                t_measure0 = time.perf_counter()
            frame = dataclasses.replace(base, seq=k + 1, stamp_s=stamp)
            t_pub = time.perf_counter()
            server.publish(frame)
            want_ms = int(stamp * 1e3)
            got = None
            while got is None and time.perf_counter() - t_pub < 0.5:
                m = ap.recv_msg()
                if m is None:
                    time.sleep(0.0002)
                    continue
                if m.get_type() == "SET_POSITION_TARGET_LOCAL_NED" and m.time_boot_ms == want_ms:
                    got = time.perf_counter()
            if got is not None and cpu0 is not None:
                latencies.append(got - t_pub)
            server.wait_acks(k + 1, 2.0)
            sleep = start + (k + 1) * period - time.perf_counter()
            if sleep > 0:
                time.sleep(sleep)
        cpu_t = ps.cpu_times()
        cpu = cpu_t.user + cpu_t.system - (cpu0 or 0.0)
        wall_s = time.perf_counter() - t_measure0
        flight_s = (n_total - int(warmup_s * FPS)) / FPS  # simulated flight time of the measured frames
    finally:
        proc.send_signal(2)  # SIGINT: clean shutdown (and the profile is written)
        try:
            proc.wait(10.0)
        except subprocess.TimeoutExpired:
            proc.kill()
        server.close()
        ap.close()
    lat = np.sort(np.asarray(latencies))
    expected = int(seconds * FPS)
    return {"frames": float(lat.size), "expected": float(expected), "p50_s": float(np.percentile(lat, 50)),
            "p99_s": float(np.percentile(lat, 99)), "max_s": float(lat[-1]), "cpu_core_s_per_s": cpu / flight_s,
            "flight_s": flight_s, "wall_s": wall_s}


def perception_alone(frames: list[RgbdFrame], rates: np.ndarray) -> dict[str, float]:
    """The perception pipeline in this process on the same frames: its share of latency and CPU."""
    from perception.pipeline import PerceptionConfig, PerceptionPipeline

    f0 = frames[0]
    pipe = PerceptionPipeline(PerceptionConfig(), f0.intrinsics, f0.R_qc, f0.p_qc_m, np.random.default_rng(0))
    frame_s, cpu0 = [], time.process_time()
    for k, f in enumerate(frames):
        for i in range(int(IMU_HZ / FPS)):
            pipe.on_imu(f.stamp_s - 1.0 / FPS + (i + 1) / IMU_HZ + 1e-6, np.array([0.0, 0.0, rates[k]]),
                        np.array([0.0, 0.0, -9.81]))
        t = time.perf_counter()
        pipe.on_frame(f)
        frame_s.append(time.perf_counter() - t)
    cpu = time.process_time() - cpu0
    return {"p50_s": float(np.median(frame_s)), "cpu_core_s_per_s": cpu / (len(frames) / FPS)}


def link_decode_cost(messages: int = 2000, reps: int = 5) -> dict[str, float]:
    """CPU µs per HIGHRES_IMU received on a UDP link: mavutil's ``recv_msg`` vs the daemon's
    :class:`companion.link_reader.CodecReader` (the dialect's codec on raw datagrams); median of ``reps``."""
    from companion.link_reader import CodecReader

    out: dict[str, list[float]] = {"mavutil": [], "codec": []}
    for _ in range(reps):
        for kind in out:
            port = free_udp_port()
            rx = open_mavlink(f"udpin:127.0.0.1:{port}", 1, 191)
            tx = open_mavlink(f"udpout:127.0.0.1:{port}", 1, 1)
            reader = CodecReader(rx) if kind == "codec" else rx
            n, cpu = 0, 0.0
            for _burst in range(messages // 200):
                for i in range(200):   # a burst fits the socket buffer; then drained
                    tx.mav.highres_imu_send(i * 2000, 0.0, 0.0, -9.81, 0.0, 0.0, 0.1, 0, 0, 0, 0, 0, 0, 20.0, 0x3F)
                time.sleep(0.01)
                t0 = time.process_time()
                while (m := reader.recv_msg()) is not None:
                    n += m.get_type() == "HIGHRES_IMU"
                cpu += time.process_time() - t0
            out[kind].append(cpu / max(n, 1) * 1e6)
            rx.close()
            tx.close()
    return {k: float(np.median(v)) for k, v in out.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=20.0, help="measured flight time (after a 3 s warm-up)")
    ap.add_argument("--tum", default=None, help="replay this TUM RGB-D folder instead of synthetic frames")
    ap.add_argument("--profile", default=None, help="run the daemon under cProfile, write the stats here")
    args = ap.parse_args()
    r = run(args.seconds, args.tum, profile=args.profile)
    print(f"companion @ {FPS:.0f} Hz 320x240 + {IMU_HZ} Hz IMU, {r['flight_s']:.1f} s of flight measured "
          f"({r['wall_s']:.1f} s wall; > flight time means this machine could not keep real time), "
          f"{int(r['frames'])}/{int(r['expected'])} setpoints matched")
    print(f"  frame->setpoint latency p50 {r['p50_s'] * 1e3:6.2f} ms  (target {TARGET_P50_S * 1e3:.0f} ms, "
          f"ratio {r['p50_s'] / TARGET_P50_S:.2f})")
    print(f"  frame->setpoint latency p99 {r['p99_s'] * 1e3:6.2f} ms  (target {TARGET_P99_S * 1e3:.0f} ms, "
          f"ratio {r['p99_s'] / TARGET_P99_S:.2f});  max {r['max_s'] * 1e3:.1f} ms")
    print(f"  daemon CPU {r['cpu_core_s_per_s']:.3f} core-s per s of flight  (target {TARGET_CPU}, "
          f"ratio {r['cpu_core_s_per_s'] / TARGET_CPU:.2f})")
    frames, rates = tum_frames(args.tum, 60) if args.tum else synthetic_frames(60)
    p = perception_alone(frames, rates)
    print(f"  of which perception alone (same frames, in-process): on_frame p50 {p['p50_s'] * 1e3:.2f} ms, "
          f"{p['cpu_core_s_per_s']:.3f} core-s/s  -> companion's own share: latency "
          f"{(r['p50_s'] - p['p50_s']) * 1e3:.2f} ms, CPU {r['cpu_core_s_per_s'] - p['cpu_core_s_per_s']:.3f} core-s/s")
    d = link_decode_cost()
    print(f"  autopilot link, CPU per HIGHRES_IMU received: mavutil recv_msg {d['mavutil']:.1f} us, codec reader "
          f"{d['codec']:.1f} us (x{IMU_HZ} Hz = {d['mavutil'] * IMU_HZ * 1e-6:.3f} vs "
          f"{d['codec'] * IMU_HZ * 1e-6:.3f} core-s/s)")


if __name__ == "__main__":
    main()

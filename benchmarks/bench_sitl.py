"""SITL speed: real-time factor with camera + physics + IMU stream on one core, cost per frame, IMU link.

Issue 3 targets: real-time factor >= 1.5 with the camera at 30 Hz 320x240, physics >= 500 Hz and the IMU
stream on, on one core; IMU 500 Hz +- 1 % on port 2 with zero frames lost, bytes/s within the
115200-baud budget (11,520 B/s). Run: ``python benchmarks/bench_sitl.py [--sim-s 20] [--soak-s 120]
[--renderers raster,pybullet] [--repeat 3]``.
The SITL runs unpaced (as fast as it can) in a child process pinned to one core, with a camera client and an
IMU client attached from this process (as the companion and the bridge would be, in their own processes).
Each camera figure is given for both renderers (``camera.renderer`` in configs/sitl.yaml): the median over
``--repeat`` runs of the wall-clock real-time factor, the CPU real-time factor (sim time / the SITL process's
CPU time: what one dedicated core would give, robust to other load) and CPU ms per frame (render + noise).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import os
import socket
import subprocess
import sys
import threading
import time

import numpy as np

from quadlink.camera import CameraStreamClient
from quadlink.frames import GRAVITY_M_S2
from quadlink.mk.messages import AttitudeSetpoint, ImuSample, decode_message, encode_message
from quadlink.mk.protocol import FrameDecoder
from quadlink.vehicle import load_vehicle
from sim_sitl.config import load_sitl_config
from sim_sitl.runner import Sitl, SitlOptions

BAUD_BUDGET_B_S = 115200 / 10


class ImuCounter(threading.Thread):
    def __init__(self, address: tuple[str, int]) -> None:
        super().__init__(daemon=True)
        self.sock = socket.create_connection(address, timeout=5)
        self.sock.settimeout(0.5)
        self.frames = 0
        self.bytes = 0
        self.gaps = 0
        self.stop = threading.Event()

    def run(self) -> None:
        dec = FrameDecoder()
        last = None
        while not self.stop.is_set():
            try:
                data = self.sock.recv(65536)
            except TimeoutError:
                continue
            except OSError:
                return
            if not data:
                return
            self.bytes += len(data)
            for f in dec.feed(data):
                msg = decode_message(f)
                if isinstance(msg, ImuSample):
                    if last is not None and (msg.sample_counter - last) % 4096 != 1:
                        self.gaps += 1
                    last = msg.sample_counter
                    self.frames += 1


class CameraConsumer(threading.Thread):
    def __init__(self, port: int) -> None:
        super().__init__(daemon=True)
        self.client = CameraStreamClient(f"tcp://127.0.0.1:{port}")
        self.frames = 0
        self.stop = threading.Event()

    def run(self) -> None:
        while not self.stop.is_set():
            f = self.client.read(timeout_s=0.5)
            if f is not None:
                self.frames += 1
                self.client.ack(f.seq)


def child(sim_s: float, camera: bool, res: tuple[int, int], scenario: str, pin: bool, flying: bool,
          renderer: str) -> None:
    """The SITL under test, in its own process (pinned to one core): ports out, 'go' in, stats out."""
    if pin and hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
    cfg = load_sitl_config()
    cfg = dataclasses.replace(cfg, camera=dataclasses.replace(cfg.camera, renderer=renderer))
    opts = SitlOptions(config=cfg, scenario=scenario, port1=0, port2=0, camera_port=0, camera=camera,
                       camera_res=res, truth_url="udpout:127.0.0.1:9", speed=0.0, duration_s=sim_s,
                       progress_every_s=1e9)
    sitl = Sitl(opts)
    if flying:  # hover 1.2 m above the start, rotors spun up; the parent sends hover setpoints with a yaw rate
        world = sitl.sim.world
        world.reset_pose(world.start_p_ned_m + np.array([0.0, 0.0, -1.2]), world.state.R_ned_q)
        world.motor_thrust_n[:] = sitl.vehicle.mass_kg * GRAVITY_M_S2 / 4.0
    print(json.dumps({"port1": sitl.port1.address[1], "port2": sitl.port2.address[1],
                      "camera": sitl.camera_server.port if sitl.camera_server else None}), flush=True)
    sys.stdin.readline()
    if camera:
        deadline = time.monotonic() + 5
        while sitl.camera_server.client_count == 0 and time.monotonic() < deadline:
            time.sleep(0.01)
    t0 = time.perf_counter()
    cpu0 = time.process_time()
    sitl.run()
    wall = time.perf_counter() - t0
    s = sitl.stats
    print(json.dumps({"sim_s": sitl.sim.t_s, "wall_s": wall, "rtf": sitl.sim.t_s / wall,
                      "cpu_s": time.process_time() - cpu0, "frames": s.camera_frames,
                      "ms_per_frame": 1000 * s.camera_render_s / max(1, s.camera_frames),
                      "cpu_ms_per_frame": 1000 * s.camera_render_cpu_s / max(1, s.camera_frames),
                      "imu_dropped": s.imu_frames_dropped, "p1_dropped": sitl.line1.stats.frames_dropped}),
          flush=True)
    sitl.stop()


def render_only(scenario: str, res: tuple[int, int], renderer: str, n: int = 36) -> tuple[float, float]:
    """In-process CPU ms per frame (medians over a turn at 1.2 m): noise-free render, and render + noise model."""
    from quadlink.frames import Rz
    from sim_sitl.camera_sim import RgbdCamera
    from sim_sitl.config import load_scenario
    from sim_sitl.world import World

    cfg = load_sitl_config()
    vehicle = load_vehicle()
    world = World(vehicle, cfg, load_scenario(scenario), np.random.default_rng(0))
    try:
        cam = RgbdCamera(world, vehicle.camera, cfg.camera_noise, np.random.default_rng(1), res[0], res[1], renderer)
        raw, full = [], []
        for i in range(n):
            world.reset_pose(world.start_p_ned_m + np.array([0.0, 0.0, -1.2]), Rz(2 * np.pi * i / n))
            t0 = time.process_time()
            cam.render_raw(world.state)
            t1 = time.process_time()
            cam.render(world.state, i, 0.0)
            raw.append(t1 - t0)
            full.append(time.process_time() - t1)
        return 1000 * float(np.median(raw)), 1000 * float(np.median(full))
    finally:
        world.close()


def hover_setpoints(port: int, hover: float, stop: threading.Event) -> None:
    """100 Hz (wall) hover setpoints turning at 0.5 rad/s, so the camera sweeps the room."""
    sock = socket.create_connection(("127.0.0.1", port), timeout=5)
    seq = 0
    while not stop.is_set():
        try:
            sock.sendall(encode_message(AttitudeSetpoint(0.0, 0.0, 0.5, hover, True, seq % 256)))
        except OSError:
            break
        seq += 1
        time.sleep(0.01)
    sock.close()


def run(sim_s: float, camera: bool, res: tuple[int, int], scenario: str, pin: bool,
        flying: bool = True, renderer: str = "raster") -> dict[str, float]:
    cmd = [sys.executable, __file__, "--child", "--sim-s", str(sim_s), "--res", f"{res[0]}x{res[1]}",
           "--scenario", scenario, "--renderer", renderer] + ([] if camera else ["--no-camera"]) + (
           [] if pin else ["--all-cores"]) + (["--flying"] if flying else [])
    proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdin is not None and proc.stdout is not None
        ports = json.loads(proc.stdout.readline())
        imu = ImuCounter(("127.0.0.1", ports["port2"]))
        imu.start()
        cam = CameraConsumer(ports["camera"]) if camera else None
        if cam:
            cam.start()
        stop_sp = threading.Event()
        sp = threading.Thread(target=hover_setpoints, args=(ports["port1"], load_vehicle().hover_thrust_fraction,
                                                            stop_sp), daemon=True)
        if flying:
            sp.start()
        proc.stdin.write("go\n")
        proc.stdin.flush()
        result = json.loads(proc.stdout.readline())
        stop_sp.set()
        time.sleep(0.3)
        imu.stop.set()
        if cam:
            cam.stop.set()
        result.update(imu_hz=imu.frames / result["sim_s"], imu_gaps=imu.gaps, port2_b_s=imu.bytes / result["sim_s"],
                      rtf_cpu=result["sim_s"] / result["cpu_s"])
        return result
    finally:
        proc.wait(timeout=30)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sim-s", type=float, default=20.0, help="simulated seconds with the camera")
    ap.add_argument("--soak-s", type=float, default=120.0, help="simulated seconds of IMU soak (no camera); 600 = "
                    "the issue's 10 minutes")
    ap.add_argument("--scenario", default="paper-arena")
    ap.add_argument("--all-cores", action="store_true", help="do not pin the SITL to one core")
    ap.add_argument("--renderers", default="raster,pybullet", help="camera renderers to measure, comma-separated")
    ap.add_argument("--repeat", type=int, default=3, help="runs per camera figure (median reported)")
    ap.add_argument("--renderer", default="raster", help=argparse.SUPPRESS)
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--res", default="320x240", help=argparse.SUPPRESS)
    ap.add_argument("--no-camera", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--flying", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    if args.child:
        w, h = (int(x) for x in args.res.split("x"))
        child(args.sim_s, not args.no_camera, (w, h), args.scenario, not args.all_cores, args.flying, args.renderer)
        return
    pin = not args.all_cores
    print(f"SITL process {'pinned to one core' if pin else 'on all cores'}; clients in this process; "
          f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores; medians of {args.repeat} runs")

    def median_run(sim_s: float, res: tuple[int, int], flying: bool, renderer: str) -> dict[str, float]:
        runs = [run(sim_s, True, res, args.scenario, pin, flying, renderer) for _ in range(args.repeat)]
        return {key: float(np.median([r[key] for r in runs])) for key in ("rtf", "rtf_cpu", "ms_per_frame",
                                                                           "cpu_ms_per_frame", "frames", "sim_s")}

    for renderer in args.renderers.split(","):
        for res in ((320, 240), (640, 480)):
            raw_ms, full_ms = render_only(args.scenario, res, renderer)
            print(f"[{renderer}] {res[0]}x{res[1]} in-process, hovering 1.2 m, a full turn in 10 deg steps: "
                  f"{raw_ms:.1f} ms CPU per noise-free render, {full_ms:.1f} ms with the noise model (medians)")
        for res in ((320, 240), (640, 480)):
            r = median_run(args.sim_s if res == (320, 240) else args.sim_s / 4, res, True, renderer)
            print(f"[{renderer}] camera 30 Hz {res[0]}x{res[1]} + physics 500 Hz + IMU stream ({args.scenario}, "
                  f"hovering 1.2 m, turning): real-time factor {r['rtf']:.2f} wall, {r['rtf_cpu']:.2f} CPU "
                  f"(target >= 1.5: {r['rtf'] / 1.5:.2f}x of target), {r['cpu_ms_per_frame']:.1f} ms CPU "
                  f"({r['ms_per_frame']:.1f} ms wall) per frame (render + noise model), {r['frames']:.0f} frames in "
                  f"{r['sim_s']:.1f} s sim")
        r = median_run(args.sim_s, (320, 240), False, renderer)
        print(f"[{renderer}] same, vehicle on the ground (camera sees the floor only): real-time factor "
              f"{r['rtf']:.2f} wall, {r['rtf_cpu']:.2f} CPU, {r['cpu_ms_per_frame']:.1f} ms CPU per frame")
    r = run(args.sim_s, False, (320, 240), args.scenario, pin)
    print(f"physics 500 Hz + IMU stream, no camera: real-time factor {r['rtf']:.2f} wall, {r['rtf_cpu']:.2f} CPU")
    r = run(args.soak_s, False, (320, 240), args.scenario, pin, flying=False)
    print(f"IMU on port 2 over {r['sim_s']:.0f} s sim: {r['imu_hz']:.2f} Hz (target 500 +- 1 %: "
          f"{abs(r['imu_hz'] - 500) / 5:.2f} of tolerance), lost {r['imu_gaps']} (counter gaps) + "
          f"{r['imu_dropped']} (TX drops), {r['port2_b_s']:.0f} B/s = "
          f"{100 * r['port2_b_s'] / BAUD_BUDGET_B_S:.1f} % of "
          f"the 115200-baud budget ({BAUD_BUDGET_B_S:.0f} B/s)")


if __name__ == "__main__":
    main()

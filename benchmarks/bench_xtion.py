"""The camera's cost per frame with the basic and the Xtion noise models (sim_sitl/xtion.py), in process.

CPU ms per frame (medians over a turn at 1.2 m, ``--n`` poses) of ``RgbdCamera.render`` with the raster renderer:
the basic model, the Xtion model at rest (no blur), and the Xtion model yawing (blur: the samples grow with the
smear). Run: ``python benchmarks/bench_xtion.py [--scenario paper-arena] [--res 320x240] [--n 72]``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import time

import numpy as np

from quadlink.frames import Rz
from quadlink.vehicle import load_vehicle
from sim_sitl.camera_sim import RgbdCamera
from sim_sitl.config import load_scenario, load_sitl_config
from sim_sitl.world import World


def measure(scenario: str, res: tuple[int, int], n: int) -> dict[str, float]:
    cfg = load_sitl_config()
    vehicle = load_vehicle()
    world = World(vehicle, cfg, load_scenario(scenario), np.random.default_rng(0))
    cases = {"basic": ("basic", 0.0), "xtion_rest": ("xtion", 0.0), "xtion_yaw_1rad_s": ("xtion", 1.0),
             "xtion_yaw_3rad_s": ("xtion", 3.0)}
    out: dict[str, float] = {}
    try:
        cams = {name: RgbdCamera(world, vehicle.camera, dataclasses.replace(cfg.camera_noise, model=model),
                                 np.random.default_rng(1), res[0], res[1]) for name, (model, _) in cases.items()}
        times: dict[str, list[float]] = {name: [] for name in cases}
        raw: list[float] = []
        for i in range(n):
            world.reset_pose(world.start_p_ned_m + np.array([0.0, 0.0, -1.2]), Rz(2 * math.pi * i / n))
            t0 = time.process_time()
            cams["basic"].render_raw(world.state)
            raw.append(time.process_time() - t0)
            for name, (_, rate) in cases.items():
                state = dataclasses.replace(world.state, omega_q_rad_s=np.array([0.0, 0.0, rate]))
                t0 = time.process_time()
                cams[name].render(state, i, 0.0)
                times[name].append(time.process_time() - t0)
        out["render_raw"] = 1000 * float(np.median(raw))
        out.update({name: 1000 * float(np.median(t)) for name, t in times.items()})
    finally:
        world.close()
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="paper-arena")
    ap.add_argument("--res", default="320x240")
    ap.add_argument("--n", type=int, default=72)
    args = ap.parse_args()
    w, h = (int(v) for v in args.res.split("x"))
    result = measure(args.scenario, (w, h), args.n)
    print(json.dumps({"scenario": args.scenario, "res": args.res, "cpu_ms_per_frame": result}, indent=1))


if __name__ == "__main__":
    main()

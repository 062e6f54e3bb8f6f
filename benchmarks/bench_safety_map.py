"""Per-frame CPU of the safety layer's map work added in issue 14, against the companion's frame budget.

Measured on a full obstacle map (``max_particles``, 20,000 particles within 5 m, a tenth of them on a 0.75 m
desk top under and around the vehicle), the vehicle moving at 0.3 m/s and yawing with the pan-scan:

* the obstacle map's time update (eq. 14) with the near-field keep (particles within 1.5 m live 20 s, not 8 s)
  and without it (``near_field_max_age_s`` = ``max_age_s``): the keep's cost is the difference;
* ``BelowMemory.observe`` (the tops under the vehicle kept in the odometry's world), ``BelowMemory.points_h`` and
  ``object_below`` (the landing check, asked on a ground station's LAND and at a failsafe landing).

Reference: the companion's budget of 0.3 core-s per second of flight at 30 frames/s, 10 ms per frame
(benchmarks/bench_companion.py measures the whole daemon against it).

    python benchmarks/bench_safety_map.py [--frames 300]
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from companion.landing_spot import BelowMemory, LandingSpotParams, object_below  # noqa: E402
from perception.obstacle_map import ObstacleMap, ObstacleMapConfig  # noqa: E402

FRAME_BUDGET_S = 0.3 / 30.0
HEIGHT_M = 1.1


def full_map(cfg: ObstacleMapConfig, rng: np.random.Generator) -> ObstacleMap:
    n = cfg.max_particles
    m = ObstacleMap(cfg)
    r = cfg.radius_m * np.sqrt(rng.uniform(0.0, 1.0, n))
    az = rng.uniform(-math.pi, math.pi, n)
    z = rng.uniform(-1.0, HEIGHT_M, n)                      # H, z down: from 1 m above to the floor
    desk = slice(0, n // 10)                                 # a desk top 0.75 m high under the vehicle
    r[desk] = rng.uniform(0.0, 1.2, n // 10)
    z[desk] = HEIGHT_M - 0.75
    m.points_h_m = np.column_stack([r * np.cos(az), r * np.sin(az), z])
    m.ages_s = rng.uniform(0.0, cfg.max_age_s, n)            # a spread of ages: some age out every frame
    return m


def time_predict(cfg: ObstacleMapConfig, frames: int, seed: int) -> float:
    rng = np.random.default_rng(seed)
    dt, v = 1.0 / 30.0, np.array([0.3, 0.0, 0.0])
    total = 0.0
    for k in range(frames):
        if k % 30 == 0:                                      # refilled: the map stays full, as in flight
            m = full_map(cfg, rng)
        yaw_rate = 0.6 * math.sin(1.5 * k * dt)
        t0 = time.perf_counter()
        m.predict(dt, v, v, yaw_rate, yaw_rate, rng)
        total += time.perf_counter() - t0
    return total / frames


def time_below_memory(frames: int, seed: int) -> tuple[float, float, int]:
    rng = np.random.default_rng(seed)
    params = LandingSpotParams()
    memory = BelowMemory(params)
    m = full_map(ObstacleMapConfig(), rng)
    points = m.points_h_m
    observe = check = 0.0
    for k in range(frames):
        pos = np.array([0.01 * k, 0.0, -HEIGHT_M])
        yaw = 0.4 * math.sin(0.05 * k)
        t0 = time.perf_counter()
        memory.observe(points, HEIGHT_M, 0.15, pos, yaw)
        t1 = time.perf_counter()
        below = memory.points_h(pos, yaw, HEIGHT_M)
        object_below(np.vstack([points, below]), HEIGHT_M, params, 0.15)
        t2 = time.perf_counter()
        observe += t1 - t0
        check += t2 - t1
    return observe / frames, check / frames, len(memory)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    cfg = ObstacleMapConfig()
    with_keep = time_predict(cfg, args.frames, args.seed)
    without = time_predict(replace(cfg, near_field_max_age_s=cfg.max_age_s), args.frames, args.seed)
    observe, check, cells = time_below_memory(args.frames, args.seed)
    print(f"map of {cfg.max_particles} particles, {args.frames} frames; budget {FRAME_BUDGET_S * 1e3:.1f} ms/frame")
    print(f"  map time update with near-field keep   {with_keep * 1e6:8.0f} us/frame")
    print(f"  map time update without it             {without * 1e6:8.0f} us/frame")
    keep = with_keep - without
    print(f"  near-field keep                        {keep * 1e6:8.0f} us/frame  "
          f"({keep / FRAME_BUDGET_S:6.1%} of budget)")
    print(f"  BelowMemory.observe (every frame)      {observe * 1e6:8.0f} us/frame  "
          f"({observe / FRAME_BUDGET_S:6.1%} of budget; {cells} cells kept)")
    print(f"  landing check (on LAND / failsafe)     {check * 1e6:8.0f} us/call")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

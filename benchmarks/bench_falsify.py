"""Falsification (issue 31): evaluations per hour at ``--parallel 1`` and ``2``, and the search against random
sampling on the same budget.

Run: ``python benchmarks/bench_falsify.py [--budget 12] [--startup 4] [--duration 24] [--parallels 1,2]
[--throughput-budget 2] [--seeds 1] [--out DIR]``.

* **Throughput:** for each parallelism a random-sampler search of ``--throughput-budget`` flights (the same seed,
  so the same flights) through the campaign runner's local Ray; evaluations (judged flights) per hour of wall.
* **Search vs random:** for each seed, a study of ``--budget`` flights with ``--sampler random`` and one with TPE
  (``--startup`` random flights first), both at the largest parallelism; the lowest clearance each found, the
  flight where each first got within 0.05 m of its own best, and how many flights went below 0.45 m and 0.40 m.
  With one seed and a small budget the comparison is one sample, not a statistic: the script says so.

The flights are lock-step and deterministic, so the CPU load of other jobs changes the wall time, not the
clearances; note the load average printed first.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time
from pathlib import Path
from typing import Any

from harness.falsify.report import summary
from harness.falsify.search import SearchOptions, run_search


def _search(out: Path, budget: int, seed: int, parallel: int, sampler: str, startup: int, duration_s: float,
            port_offset: int) -> tuple[dict[str, Any], float]:
    import optuna

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    t0 = time.monotonic()
    study = run_search(SearchOptions(budget, seed, out, parallel, None, sampler, startup, duration_s, port_offset),
                       echo=lambda s: None)
    return summary(study, out), time.monotonic() - t0


def _first_within(conv: list[float], best: float, tol_m: float = 0.05) -> int | None:
    for i, v in enumerate(conv, 1):
        if v <= best + tol_m:
            return i
    return None


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--budget", type=int, default=12)
    ap.add_argument("--startup", type=int, default=4)
    ap.add_argument("--duration", type=float, default=24.0)
    ap.add_argument("--parallels", default="1,2")
    ap.add_argument("--throughput-budget", type=int, default=2)
    ap.add_argument("--seeds", default="1")
    ap.add_argument("--skip-throughput", action="store_true")
    ap.add_argument("--skip-compare", action="store_true")
    ap.add_argument("--port-offset", type=int, default=4400)
    ap.add_argument("--out", type=Path, default=Path("/tmp/quadlink-bench-falsify"))
    args = ap.parse_args()
    print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores; flights of {args.duration:g} s")
    figures: dict[str, Any] = {"duration_s": args.duration}
    parallels = [int(p) for p in args.parallels.split(",")]
    if not args.skip_throughput:
        for parallel in parallels:
            out = args.out / f"throughput-p{parallel}"
            s, wall_s = _search(out, args.throughput_budget, 31, parallel, "random", 0, args.duration,
                                args.port_offset)
            rate = s["flights"] / wall_s * 3600
            figures[f"parallel_{parallel}"] = {"flights": s["flights"], "wall_s": wall_s, "evaluations_per_hour": rate,
                                               "mean_flight_wall_s": s["mean_flight_wall_s"]}
            print(f"--parallel {parallel}: {rate:.0f} evaluations/h ({s['flights']} flights in {wall_s:.0f} s wall; "
                  f"{s['mean_flight_wall_s']:.0f} s wall per flight)")
    if not args.skip_compare:
        compare: dict[str, Any] = {}
        for seed in (int(x) for x in args.seeds.split(",")):
            for sampler in ("random", "tpe"):
                out = args.out / f"compare-{sampler}-s{seed}"
                s, wall_s = _search(out, args.budget, seed, max(parallels), sampler, args.startup, args.duration,
                                    args.port_offset)
                conv = [v if v is not None else math.inf for v in s["convergence_m"]]
                best = s["best_clearance_m"]
                compare[f"{sampler}_s{seed}"] = {
                    "best_clearance_m": best, "median_clearance_m": s["median_clearance_m"],
                    "below_0.45": s["below_safe_distance"], "below_0.40": s["below_envelope"],
                    "failed": s["failed"], "first_within_5cm_of_best": _first_within(conv, best) if best else None,
                    "convergence_m": s["convergence_m"], "wall_s": wall_s,
                    "best_trial": s["lowest"][0]["trial"] if s["lowest"] else None,
                    "best_params": s["lowest"][0]["params"] if s["lowest"] else None}
                print(f"seed {seed} {sampler:6s}: best {best:.3f} m, median {s['median_clearance_m']:.3f} m, "
                      f"below 0.45 m {s['below_safe_distance']}, below 0.40 m {s['below_envelope']}, "
                      f"failed {s['failed']} ({args.budget} flights, {wall_s:.0f} s)")
            r, t = compare[f"random_s{seed}"], compare[f"tpe_s{seed}"]
            lower = t["best_clearance_m"] < r["best_clearance_m"]
            verdict = f"TPE {'found' if lower else 'did NOT find'} a lower clearance than random sampling"
            print(f"seed {seed}: {verdict} ({t['best_clearance_m']:.3f} m vs {r['best_clearance_m']:.3f} m on "
                  f"{args.budget} flights each, {args.startup} of TPE's random); one seed at this budget is one "
                  f"sample, not a statistic")
        figures["compare"] = compare
    (args.out / "bench_falsify.json").parent.mkdir(parents=True, exist_ok=True)
    (args.out / "bench_falsify.json").write_text(json.dumps(figures, indent=2, default=float) + "\n")
    print(json.dumps(figures, indent=2, default=float))
    print(f"load average after {os.getloadavg()[0]:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

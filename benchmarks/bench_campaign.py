"""Campaign throughput (issue 15): flights per hour at ``--parallel 1`` and ``2``, and what one flight costs.

Run: ``python benchmarks/bench_campaign.py [--flights 2] [--duration 60] [--parallels 1,2] [--out DIR]``.

For each parallelism it flies a campaign of ``--flights`` lock-step flights through the embedded local Ray
(the same seed each time, so the same flights) and prints flights per hour, wall seconds per flight and
the real-time factor. For one flight it prints the CPU core-seconds per simulated second, per part
(``cpu_core_s_per_sim_s`` of the demo's report: the processes' user + system time over the flight's
simulated duration) and in total. Target (issue 15): a 60 s flight in <= 60 s of wall time.

The figures depend on the load: on a shared machine (other jobs on the same cores) the lock-step flights
slow down, so also note the load average printed first. The flights are the campaign's default, the
deterministic lock-step (quadlink/lockstep.py): every part runs on simulated time, so the CPU figures are
robust to load (in the plain lock-step the ground station's 1 kHz force loop ran on the wall clock, and its
CPU per simulated second grew as the simulation slowed down).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from pathlib import Path

from harness.campaign.runner import CampaignOptions, run_campaign


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--flights", type=int, default=2)
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--parallels", default="1,2")
    ap.add_argument("--seed", type=int, default=15)
    ap.add_argument("--port-offset", type=int, default=3600)
    ap.add_argument("--out", type=Path, default=Path("/tmp/quadlink-bench-campaign"))
    args = ap.parse_args()
    print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")
    figures: dict[str, object] = {}
    for parallel in (int(p) for p in args.parallels.split(",")):
        out = args.out / f"parallel-{parallel}"
        options = CampaignOptions(args.flights, args.seed, out, args.duration, parallel, port_offset=args.port_offset)
        t0 = time.monotonic()
        results = run_campaign(options, echo=lambda s: None)
        wall_s = time.monotonic() - t0
        ok = [r for r in results if r.status == "ok"]
        sim_s = [float(r.report.get("sim_duration_s", 0.0)) for r in ok]
        cpu = [r.report.get("cpu_core_s_per_sim_s", {}) for r in ok]
        per_part = {k: statistics.mean(c[k] for c in cpu) for k in (cpu[0] if cpu else {})}
        fig = {"flights": len(results), "ok": len(ok), "wall_s": wall_s,
               "flights_per_hour": len(results) / wall_s * 3600,
               "wall_s_per_flight": [r.wall_s for r in results],
               "real_time_factor": [s / r.wall_s for s, r in zip(sim_s, ok)],
               "core_s_per_sim_s": per_part, "core_s_per_sim_s_total": sum(per_part.values())}
        figures[f"parallel_{parallel}"] = fig
        print(f"--parallel {parallel}: {fig['flights_per_hour']:.1f} flights/h ({len(ok)}/{len(results)} ok, "
              f"{wall_s:.0f} s wall for {sum(sim_s):.0f} s simulated); per flight wall "
              + ", ".join(f"{w:.0f} s" for w in fig["wall_s_per_flight"])  # type: ignore[union-attr]
              + "; real-time factor " + ", ".join(f"{x:.2f}" for x in fig["real_time_factor"]))  # type: ignore[union-attr]
        print("  core-s per sim-s: " + ", ".join(f"{k} {v:.2f}" for k, v in per_part.items())
              + f"; total {fig['core_s_per_sim_s_total']:.2f}")
    print(json.dumps(figures, indent=2, default=float))
    print(f"load average after {os.getloadavg()[0]:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Clearance and latency against the companion board's CPU share (issue 30).

Run: ``python benchmarks/bench_starved.py [--flights 2] [--shares full,1.0,0.5,0.35,0.25] [--no-busy] [--seed 30]``.

The same campaign flights (seed, indices: the same arenas, operators, vehicles and sensors) are flown in real time
once per CPU share: ``full`` without a cgroup or a neighbour (the reference), each number with the bridge and the
companion held to that many cores (CFS bandwidth control, 20 ms period: :class:`harness.cpu_share.CpuShare`) and
a busy process spinning beside the stack (not with ``--no-busy``). Printed per share: the flights' minimum true
clearance (the campaign's judge; target >= 0.40 m), the companion's own data age (camera stamp to setpoint, from its
DATA_AGE reports: median of the flights' p50, and the largest), the time the kernel held the share back, and the
wall time.
The reference is the ``full`` row: what the same flights do with the CPU ample.

Needs root (or a delegated cgroup) for the shares; flies one flight at a time (a starved flight in real time next
to another would measure the other). A real-time flight is not deterministic: two runs of one share differ, so
read the rows as samples (``--flights`` more for a distribution), not as a curve fitted to the share.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import time
from pathlib import Path

from harness.campaign.draws import StarvationRange
from harness.campaign.runner import CampaignOptions, FlightResult, run_campaign
from harness.cpu_share import CpuShare, CpuShareUnavailable
from harness.machine_speed import REFERENCE_DATE, REFERENCE_WORK_CPU_S, starved_cores, work_cpu_s
from quadlink.safety import CLEARANCE_BOUND_M


def _figures(results: list[FlightResult], wall_s: float) -> dict[str, object]:
    d = [float(r.envelope.get("min_nonfloor_m", math.nan)) for r in results]
    ages = [r.report.get("data_age_ms", {}) for r in results]
    p50 = [a["p50"] for a in ages if "p50" in a]
    mx = [a["max"] for a in ages if "max" in a]
    throttled = [r.report.get("cpu_share", {}).get("throttled_s", math.nan) for r in results]
    return {"flights": len(results), "ok": sum(r.status == "ok" for r in results),
            "min_clearance_m": d, "below_target": sum(x < CLEARANCE_BOUND_M for x in d if math.isfinite(x)),
            "data_age_p50_ms_median": statistics.median(p50) if p50 else math.nan,
            "data_age_max_ms": max(mx) if mx else math.nan, "throttled_s": throttled, "wall_s": wall_s}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--flights", type=int, default=2)
    ap.add_argument("--duration", type=float, default=40.0, help="Simulated seconds per flight's session.")
    ap.add_argument("--shares", default="full,1.0,0.5,0.35,0.25", help="'full' (no share) and cores, comma-separated.")
    ap.add_argument("--no-busy", action="store_true", help="No busy process beside a starved stack.")
    ap.add_argument("--seed", type=int, default=30)
    ap.add_argument("--port-offset", type=int, default=3800)
    ap.add_argument("--out", type=Path, default=Path("/tmp/quadlink-bench-starved"))
    args = ap.parse_args()
    shares = [s.strip() for s in args.shares.split(",") if s.strip()]
    if any(s != "full" for s in shares):
        try:
            with CpuShare(1.0):
                pass
        except CpuShareUnavailable as exc:
            print(f"no CPU share can be set here ({exc}); run as root, or with --shares full")
            return 2
    busy = "no" if args.no_busy else "a"
    print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores; {args.flights} flights per share, "
          f"seed {args.seed}, {args.duration:.0f} s sessions, real time, {busy} busy neighbour when starved")
    work_s = work_cpu_s()
    print(f"machine speed: the fixed work took {work_s:.3f} CPU-s ({REFERENCE_WORK_CPU_S:.3f} s on the reference, "
          f"{REFERENCE_DATE}): 1 core here is {REFERENCE_WORK_CPU_S / work_s:.2f} core there; the starved flights' "
          f"validated 0.35 core is {starved_cores(work_s):.2f} core "
          "here (harness/machine_speed.py)")
    figures: dict[str, dict[str, object]] = {}
    for share in shares:
        starve = None if share == "full" else StarvationRange(float(share), float(share), 0.0 if args.no_busy else 1.0)
        out = args.out / f"share-{share}"
        options = CampaignOptions(args.flights, args.seed, out, args.duration, 1, port_offset=args.port_offset,
                                  deterministic=False, realtime=True, starve=starve)
        t0 = time.monotonic()
        results = run_campaign(options, echo=lambda s: None)
        fig = figures[share] = _figures(results, time.monotonic() - t0)
        d = ", ".join(f"{x:.3f}" for x in fig["min_clearance_m"])  # type: ignore[attr-defined]
        print(f"share {share:>5}: min clearance {d} m ({fig['below_target']} below {CLEARANCE_BOUND_M} m); data age "
              f"p50 {fig['data_age_p50_ms_median']:.0f} ms, max {fig['data_age_max_ms']:.0f} ms; throttled "
              + ", ".join(f"{t:.1f}" for t in fig["throttled_s"]) + " s"  # type: ignore[attr-defined]
              + f"; {fig['ok']}/{fig['flights']} ok in {fig['wall_s']:.0f} s")
    print(json.dumps(figures, indent=2, default=float))
    print(f"load average after {os.getloadavg()[0]:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

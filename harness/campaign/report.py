"""The campaign report (issue 15): ``campaign.json``, ``campaign.png`` and a printed summary (pure but for
the files it writes).

Per flight: its seeds, its arena and operator kind, the demo's metrics (``report.json``) and the safety
envelope (:mod:`harness.campaign.safety`: the minimum true distance to walls, obstacles and the ceiling).
Over the campaign: the CDF of that minimum with the 0.40 m target and the 0.45 m safe distance marked,
histograms of the velocity-estimate and tracking RMSE (worst axis per flight), the share of flights with
setpoint gaps over 100 ms, the five worst flights with the command that replays each.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from harness.campaign import manoeuvres
from harness.campaign.runner import CampaignOptions, FlightResult
from harness.demo.report import TARGETS
from quadlink.safety import CLEARANCE_BOUND_M, SAFE_DISTANCE_M

TARGET_M = CLEARANCE_BOUND_M
WORST_N = 5
TOUCHDOWN_BOUND_M_S = TARGETS["touchdown_m_s"]   # a landing's impact speed above this is listed (the demo's target)
TAKEOFF_S = 5.0   # a take-off to 1 m takes 2-3 s: a flight airborne for less came down in its take-off (the bridge
                  # lands a take-off without odometry); its session was not flown


def _worst_axis(d: dict[str, float] | None) -> float:
    vals = [v for v in (d or {}).values() if isinstance(v, (int, float)) and math.isfinite(v)]
    return max(vals) if vals else math.nan


def flight_row(r: FlightResult) -> dict[str, Any]:
    rep, env, draws = r.report, r.envelope, r.draws
    return {
        "index": r.index, "status": r.status, "attempts": r.attempts, "retried": r.attempts > 1,
        "folder": r.folder, "failure": r.failure, "wall_s": r.wall_s, "port_offset": r.port_offset,
        "seed": {"campaign": draws.get("campaign_seed"), "spawn_key": draws.get("seed_sequence", {}).get("spawn_key"),
                 "sitl": draws.get("sitl_seed")},
        "layout": draws.get("arena", {}).get("layout"), "operator": draws.get("operator", {}).get("kind"),
        "min_nonfloor_distance_m": env.get("min_nonfloor_m", math.nan),
        "min_obstacle_distance_m": env.get("min_obstacle_m", math.nan),
        "min_ceiling_distance_m": env.get("min_ceiling_m", math.nan),
        "closest_surface": env.get("surface"), "t_closest_s": env.get("t_min_s", math.nan),
        "velocity_rmse_m_s": _worst_axis(rep.get("velocity_rmse_m_s")),
        "tracking_rmse_m_s": _worst_axis(rep.get("tracking_rmse_m_s")),
        "setpoint_gaps_over_100ms": rep.get("setpoint_gaps_over_100ms"),
        "max_setpoint_gap_s": rep.get("max_setpoint_gap_s", math.nan),
        "fraction_estimate_le_truth": rep.get("fraction_estimate_le_truth", math.nan),
        "sim_duration_s": rep.get("sim_duration_s", math.nan),
        "flying_time_s": rep.get("flying_time_s", math.nan),
        "max_height_m": env.get("max_height_m", math.nan),
        "touchdown_m_s": env.get("touchdown_m_s", math.nan),
        "cpu_share_cores": draws.get("starvation", {}).get("cpu_cores", math.nan),
        "busy_neighbours": draws.get("starvation", {}).get("busy_neighbours"),
        "data_age_p50_ms": rep.get("data_age_ms", {}).get("p50", math.nan),
        "data_age_max_ms": rep.get("data_age_ms", {}).get("max", math.nan),
        "odometry_jumps_refused": rep.get("odometry_counts", {}).get("jumps_refused"),
        "odometry_restarts": rep.get("odometry_counts", {}).get("restarts"),
        "odometry_bridged_airborne": rep.get("odometry_counts_airborne", {}).get("bridged"),
        "replay": f"quadlink demo --replay {r.folder}",
    }


CPU_SHARE_BINS = (0.0, 0.45, 0.6, 0.8, 64.0)  # cores: the rows of the clearance-and-latency-vs-CPU-share table


def by_cpu_share(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Issue 30: clearance and the companion's data age by the flights' CPU share (starved flights only)."""
    out = []
    for lo, hi in zip(CPU_SHARE_BINS[:-1], CPU_SHARE_BINS[1:]):
        sel = [r for r in rows if lo <= r.get("cpu_share_cores", math.nan) < hi]
        if not sel:
            continue
        d, age50, agemax = (_finite(sel, k) for k in ("min_nonfloor_distance_m", "data_age_p50_ms", "data_age_max_ms"))
        out.append({"cores_from": lo, "cores_to": hi, "flights": len(sel),
                    "with_busy_neighbour": sum(bool(r.get("busy_neighbours")) for r in sel),
                    "min_nonfloor_distance_m": float(d.min()) if d.size else math.nan,
                    "median_nonfloor_distance_m": float(np.median(d)) if d.size else math.nan,
                    "below_target": int(np.sum(d < TARGET_M)),
                    "data_age_p50_ms_median": float(np.median(age50)) if age50.size else math.nan,
                    "data_age_max_ms": float(agemax.max()) if agemax.size else math.nan})
    return out


def by_cpu_share_text(table: list[dict[str, Any]]) -> str:
    lines = [f"{'CPU share (cores)':<18} {'flights':>7} {'busy':>4} {'min d':>6} {'median d':>8} {'<0.40':>5} "
             f"{'age p50':>8} {'age max':>8}"]
    for b in table:
        span = f"{b['cores_from']:.2f}-{b['cores_to']:.2f}" if b["cores_to"] < 64 else f">= {b['cores_from']:.2f}"
        lines.append(f"{span:<18} {b['flights']:>7} {b['with_busy_neighbour']:>4} {b['min_nonfloor_distance_m']:6.3f} "
                     f"{b['median_nonfloor_distance_m']:8.3f} {b['below_target']:>5} "
                     f"{b['data_age_p50_ms_median']:6.0f}ms {b['data_age_max_ms']:6.0f}ms")
    return "\n".join(lines)


def _finite(rows: list[dict[str, Any]], key: str) -> np.ndarray:
    return np.asarray([row[key] for row in rows if isinstance(row.get(key), (int, float))
                       and math.isfinite(row[key])], dtype=float)


def _option_json(value: Any) -> Any:
    """A campaign option as JSON: a path as its string, a dataclass (the starvation range) as its fields."""
    if isinstance(value, Path):
        return str(value)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return dataclasses.asdict(value)
    return value


def summarize(results: list[FlightResult], options: CampaignOptions, wall_s: float) -> dict[str, Any]:
    rows = [flight_row(r) for r in results]
    flown = [row for row in rows if math.isfinite(row["min_nonfloor_distance_m"])]
    d = _finite(flown, "min_nonfloor_distance_m")
    gaps = [row for row in flown if row["setpoint_gaps_over_100ms"] is not None]
    sim_s = float(np.sum(_finite(flown, "sim_duration_s")))
    worst = sorted(flown, key=lambda row: row["min_nonfloor_distance_m"])[:WORST_N]
    by_manoeuvre = manoeuvres.table([m for r in results for m in manoeuvres.flight_manoeuvres(Path(r.folder), r.index)])
    return {
        "options": {k: _option_json(v) for k, v in vars(options).items()},
        "flights": rows,
        "summary": {
            "flights": len(rows), "ok": sum(r["status"] == "ok" for r in rows),
            "failed": [r["index"] for r in rows if r["status"] not in ("ok",)],
            "retried": [r["index"] for r in rows if r["retried"]],
            # a flight that never left the ground says nothing about the envelope: listed, not hidden
            "did_not_take_off": [r["index"] for r in rows if not (r.get("max_height_m", 0.0) > 0.5)],
            "landed_in_takeoff": [r["index"] for r in rows if r.get("max_height_m", 0.0) > 0.5
                                  and r.get("flying_time_s", math.inf) < TAKEOFF_S],
            "min_nonfloor_distance_m": float(d.min()) if d.size else math.nan,
            "share_below_target": float(np.mean(d < TARGET_M)) if d.size else math.nan,
            "share_below_safe_distance": float(np.mean(d < SAFE_DISTANCE_M)) if d.size else math.nan,
            "velocity_rmse_m_s_median": float(np.median(_finite(flown, "velocity_rmse_m_s")))
            if _finite(flown, "velocity_rmse_m_s").size else math.nan,
            "tracking_rmse_m_s_median": float(np.median(_finite(flown, "tracking_rmse_m_s")))
            if _finite(flown, "tracking_rmse_m_s").size else math.nan,
            # the landing's impact speed (truth), against PX4's MPC_LAND_SPEED-like bound the failsafe tests use
            "touchdown_m_s_median": float(np.median(_finite(flown, "touchdown_m_s")))
            if _finite(flown, "touchdown_m_s").size else math.nan,
            "touchdown_m_s_max": float(np.max(_finite(flown, "touchdown_m_s")))
            if _finite(flown, "touchdown_m_s").size else math.nan,
            "touchdowns_over_bound": [r["index"] for r in flown if r.get("touchdown_m_s", 0.0) > TOUCHDOWN_BOUND_M_S],
            "share_with_setpoint_gaps": float(np.mean([(r["setpoint_gaps_over_100ms"] or 0) > 0 for r in gaps]))
            if gaps else math.nan,
            "wall_time_s": wall_s, "simulated_s": sim_s,
            "flights_per_hour": len(rows) / wall_s * 3600 if wall_s > 0 else math.nan,
            "worst": [{"index": w["index"], "min_nonfloor_distance_m": w["min_nonfloor_distance_m"],
                       "surface": w["closest_surface"], "layout": w["layout"], "operator": w["operator"],
                       "replay": w["replay"]} for w in worst],
            # issue 29: by manoeuvre x direction of motion relative to the camera (an unseen flank is a row)
            "by_manoeuvre_and_direction": by_manoeuvre,
            # issue 30: a starved campaign's clearance and latency by CPU share (empty when nothing was starved)
            "by_cpu_share": by_cpu_share(rows),
        },
    }


def make_plot(campaign: dict[str, Any], path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = campaign["flights"]
    d = np.sort(_finite(rows, "min_nonfloor_distance_m"))
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    ax = axes[0]
    if d.size:
        ax.step(d, np.arange(1, d.size + 1) / d.size, where="post", color="tab:blue")
    ax.axvline(TARGET_M, color="r", ls="--", label=f"target {TARGET_M:.2f} m")
    ax.axvline(SAFE_DISTANCE_M, color="k", ls=":", label=f"safe distance {SAFE_DISTANCE_M:.2f} m")
    ax.set_xlabel("min true distance to walls, obstacles, ceiling [m]")
    ax.set_ylabel("share of flights")
    ax.set_title(f"Safety envelope ({d.size} flights)")
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right")
    for ax, key, title in ((axes[1], "velocity_rmse_m_s", "velocity-estimate RMSE (worst axis)"),
                           (axes[2], "tracking_rmse_m_s", "tracking RMSE (worst axis)")):
        v = _finite(rows, key)
        if v.size:
            ax.hist(v, bins=max(5, min(30, v.size)), color="tab:green")
        ax.set_xlabel(f"{key} [m/s]")
        ax.set_ylabel("flights")
        ax.set_title(title)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def write_campaign(results: list[FlightResult], options: CampaignOptions, wall_s: float) -> dict[str, Any]:
    campaign = summarize(results, options, wall_s)
    campaign["plot"] = str(make_plot(campaign, options.out_dir / "campaign.png"))
    (options.out_dir / "campaign.json").write_text(json.dumps(campaign, indent=2, default=float) + "\n")
    return campaign


def summary_text(campaign: dict[str, Any]) -> str:
    s = campaign["summary"]
    lines = [f"{'flight':>6} {'status':<9} {'layout':<18} {'operator':<8} {'min d':>6} {'surface':<8} "
             f"{'v RMSE':>7} {'track':>7} {'land':>5} {'gaps':>4} {'flying':>6} {'sitl seed':>10}"]
    for r in campaign["flights"]:
        lines.append(f"{r['index']:>6} {r['status'] + ('*' if r['retried'] else ''):<9} {str(r['layout']):<18} "
                     f"{str(r['operator']):<8} {r['min_nonfloor_distance_m']:6.2f} {str(r['closest_surface']):<8} "
                     f"{r['velocity_rmse_m_s']:7.3f} {r['tracking_rmse_m_s']:7.3f} "
                     f"{r.get('touchdown_m_s', math.nan):5.2f} {str(r['setpoint_gaps_over_100ms']):>4} "
                     f"{r['flying_time_s']:5.1f}s {str(r['seed']['sitl']):>10}")
    lines += [
        "",
        f"flights {s['flights']} (ok {s['ok']}; failed {s['failed'] or 'none'}; retried (*) {s['retried'] or 'none'}; "
        f"did not take off {s['did_not_take_off'] or 'none'}; landed in the take-off, under {TAKEOFF_S:.0f} s "
        f"airborne {s.get('landed_in_takeoff') or 'none'})",
        f"min true distance to walls/obstacles/ceiling: {s['min_nonfloor_distance_m']:.3f} m; "
        f"below {TARGET_M} m in {100 * s['share_below_target']:.0f} % of flights, below {SAFE_DISTANCE_M} m in "
        f"{100 * s['share_below_safe_distance']:.0f} %",
        f"velocity-estimate RMSE median {s['velocity_rmse_m_s_median']:.3f} m/s; tracking RMSE median "
        f"{s['tracking_rmse_m_s_median']:.3f} m/s; flights with setpoint gaps > 100 ms: "
        f"{100 * s['share_with_setpoint_gaps']:.0f} %",
        f"touchdown speed (truth) median {s.get('touchdown_m_s_median', math.nan):.2f} m/s, fastest "
        f"{s.get('touchdown_m_s_max', math.nan):.2f} m/s; over {TOUCHDOWN_BOUND_M_S} m/s: "
        f"{s.get('touchdowns_over_bound') or 'none'}",
        f"throughput: {s['flights_per_hour']:.1f} flights/h ({s['simulated_s']:.0f} s simulated in "
        f"{s['wall_time_s']:.0f} s wall)",
        "worst flights:",
    ]
    for w in s["worst"]:
        lines.append(f"  flight {w['index']:>4}: {w['min_nonfloor_distance_m']:.3f} m ({w['surface']}, {w['layout']}, "
                     f"{w['operator']})  {w['replay']}")
    if s.get("by_cpu_share"):
        lines += ["", "clearance and the companion's data age by its CPU share (a starved campaign):",
                  by_cpu_share_text(s["by_cpu_share"])]
    if s.get("by_manoeuvre_and_direction"):
        lines += ["", "clearance by manoeuvre x direction of motion relative to the camera:",
                  manoeuvres.table_text(s["by_manoeuvre_and_direction"])]
    return "\n".join(lines)

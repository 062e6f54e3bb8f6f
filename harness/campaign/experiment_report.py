"""The report of a paper 003 experiment campaign (issue 19): per flight and as worst / median, paper 003's figures
beside the paper's Tables 3-5 and issue 19's targets, PASS/FAIL, and the command that re-flies each flight.

Pure but for :func:`write_experiment_campaign` (``campaign.json``). The oval's figures are ``paper003.json``'s
tables (RMSE per axis x / y / z, :func:`harness.demo.paper003.tables`); the hover's are the three pushes' peak
displacement and time back within 5 cm (truth, :func:`harness.demo.paper003.push_recoveries`). A flight passes
when every criterion of its ``pass`` holds; a flight with no figures (it failed before the experiment ended)
counts as failed.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from harness.campaign.experiment_flight import replay_command, verdict
from harness.campaign.experiments import experiment
from harness.campaign.runner import CampaignOptions, FlightResult
from harness.demo.paper003 import (
    HOVER_BACK_WITHIN_S,
    HOVER_PEAK_RANGE_M,
    ISSUE19_TARGETS,
    PAPER_TABLE3_VELOCITY_M_S,
    PAPER_TABLE4_POSITION_M,
    PAPER_TABLE5_VELOCITY_M_S,
)

#: the figures of each experiment: key, title, unit, paper 003's value per axis, issue 19's bound (upper, or range);
#: issue 19 also asks each of the oval's figures to beat paper 003's (counted per axis, not part of PASS)
OVAL_FIGURES: tuple[tuple[str, str, str, tuple[float, ...] | None, Any], ...] = (
    ("table4_position_m", "T4 pos est-des", "m", PAPER_TABLE4_POSITION_M, ISSUE19_TARGETS["table4_position_m"]),
    ("table5_velocity_m_s", "T5 vel est-des", "m/s", PAPER_TABLE5_VELOCITY_M_S,
     ISSUE19_TARGETS["table5_velocity_m_s"]),
    ("table3_velocity_m_s", "T3 vel est-true", "m/s", PAPER_TABLE3_VELOCITY_M_S,
     ISSUE19_TARGETS["table3_velocity_m_s"]),
    ("true_position_vs_desired_m", "pos true-des", "m", None, None),
)
HOVER_FIGURES: tuple[tuple[str, str, str, tuple[float, ...] | None, Any], ...] = (
    ("peak_displacement_m", "push peak z/y/x", "m", (0.7, 0.7, 0.7), HOVER_PEAK_RANGE_M),
    ("back_after_s", "back in 5 cm z/y/x", "s", (3.0, 3.0, 3.0), HOVER_BACK_WITHIN_S),
)


def figures_of(report: dict[str, Any]) -> dict[str, list[float]]:
    """The experiment's figures from its ``paper003.json`` (three values each; empty if it has none)."""
    if report.get("experiment") == "oval":
        t = report.get("tables") or {}
        return {key: [float(v) for v in t[key]] for key, *_ in OVAL_FIGURES if key in t}
    rec = report.get("recoveries_truth") or []
    if len(rec) != 3:
        return {}
    return {key: [float(r[key]) for r in rec] for key, *_ in HOVER_FIGURES}


def experiment_row(r: FlightResult) -> dict[str, Any]:
    draws = r.draws
    exp = experiment(draws.get("experiment", ""))
    ok = verdict(r.report) if r.status == "ok" else None
    return {
        "index": r.index, "status": r.status, "attempts": r.attempts, "retried": r.attempts > 1,
        "folder": r.folder, "failure": r.failure, "wall_s": r.wall_s, "port_offset": r.port_offset,
        "seed": {"campaign": draws.get("campaign_seed"), "spawn_key": draws.get("seed_sequence", {}).get("spawn_key"),
                 "sitl": draws.get("sitl_seed")},
        "start_position_m": draws.get("arena", {}).get("start", {}).get("position_m"),
        "start_yaw_deg": draws.get("arena", {}).get("start", {}).get("yaw_deg"),
        "path_clearance_m": draws.get("arena", {}).get("path_clearance_m"),
        "mass_kg": draws.get("vehicle", {}).get("mass_kg"),
        "figures": figures_of(r.report), "pass": r.report.get("pass") or (r.report.get("tables") or {}).get("pass"),
        "verdict": {True: "PASS", False: "FAIL", None: "FAIL (no figures)"}[ok],
        "replay": replay_command(exp.paper003, r.folder),
    }


def _figure_spec(name: str) -> tuple[tuple[str, str, str, tuple[float, ...] | None, Any], ...]:
    return OVAL_FIGURES if experiment(name).paper003 == "oval" else HOVER_FIGURES


def summarize_experiment(results: list[FlightResult], options: CampaignOptions, wall_s: float) -> dict[str, Any]:
    rows = [experiment_row(r) for r in results]
    stats: dict[str, Any] = {}
    oval = experiment(options.experiment).paper003 == "oval"
    for key, _, _, paper, _ in _figure_spec(options.experiment):
        values = np.array([row["figures"][key] for row in rows if key in row["figures"]], dtype=float).reshape(-1, 3)
        finite = np.where(np.isfinite(values), values, np.inf)  # a push never back counts as worst
        stats[key] = {"min": finite.min(axis=0).tolist() if values.size else [math.nan] * 3,
                      "median": np.median(finite, axis=0).tolist() if values.size else [math.nan] * 3,
                      "worst": finite.max(axis=0).tolist() if values.size else [math.nan] * 3,
                      "flights": int(values.shape[0])}
        if oval and paper is not None:
            stats[key]["beats_paper"] = np.sum(finite < np.asarray(paper)[None, :], axis=0).astype(int).tolist()
    return {
        "experiment": options.experiment,
        "code_version": ", ".join(sorted({r.code_version or "unknown" for r in results})) or "unknown",
        "options": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(options).items()},
        "flights": rows,
        "summary": {"flights": len(rows), "passed": [r["index"] for r in rows if r["verdict"] == "PASS"],
                    "failed": [r["index"] for r in rows if r["verdict"] != "PASS"],
                    "not_flown": [r["index"] for r in rows if r["status"] != "ok"],
                    "figures": stats, "wall_time_s": wall_s},
    }


def _three(v: list[float] | None, fmt: str = "{:.3f}") -> str:
    return "/".join(fmt.format(x) for x in v) if v else "-"


def _bound(bound: Any) -> str:
    if bound is None:
        return ""
    if isinstance(bound, tuple):
        return f"{bound[0]:g}-{bound[1]:g}"
    return f"<= {bound:g}"


def experiment_summary_text(campaign: dict[str, Any]) -> str:
    spec = _figure_spec(campaign["experiment"])
    s = campaign["summary"]
    o = campaign["options"]
    head = f"{'flight':>6} {'status':<7} {'start N/E m':>13} {'yaw':>7} {'mass':>6}"
    lines = [f"{campaign['experiment']}: {s['flights']} flights, seed {o['seed']}, code {campaign['code_version']}",
             head + "".join(f" | {title + ' ' + unit:<19}" for _, title, unit, *_ in spec) + " | verdict"]
    for r in campaign["flights"]:
        start = r["start_position_m"] or [math.nan, math.nan]
        line = (f"{r['index']:>6} {r['status'] + ('*' if r['retried'] else ''):<7} "
                f"{start[0]:6.2f}/{start[1]:6.2f} {r['start_yaw_deg'] or math.nan:6.1f}° "
                f"{r['mass_kg'] or math.nan:6.3f}")
        line += "".join(f" | {_three(r['figures'].get(key)):<19}" for key, *_ in spec)
        lines.append(line + f" | {r['verdict']}")
    for label in ("min", "median", "worst"):
        lines.append(f"{label:>6} {'':<7} {'':>13} {'':>7} {'':>6}"
                     + "".join(f" | {_three(s['figures'][key][label]):<19}" for key, *_ in spec))
    lines.append(f"{'paper':>6} {'003':<7} {'':>13} {'':>7} {'':>6}"
                 + "".join(f" | {_three(list(paper) if paper else None):<19}" for _, _, _, paper, _ in spec))
    lines.append(f"{'target':>6} {'':<7} {'':>13} {'':>7} {'':>6}"
                 + "".join(f" | {_bound(bound):<19}" for *_, bound in spec))
    if any("beats_paper" in f for f in s["figures"].values()):
        beats = [s["figures"][key].get("beats_paper") for key, *_ in spec]
        lines.append(f"{'beats':>6} {'paper':<7} {'(flights)':>13} {'':>7} {'':>6}"
                     + "".join(f" | {_three(b, '{:d}') if b else '':<19}" for b in beats))
    lines += ["", f"PASS {len(s['passed'])} of {s['flights']} (failed: {s['failed'] or 'none'}; "
                  f"did not finish: {s['not_flown'] or 'none'}); wall {s['wall_time_s']:.0f} s", "replay:"]
    lines += [f"  flight {r['index']:>4}: {r['replay']}" for r in campaign["flights"]]
    failures = [f"  flight {r['index']:>4}: {r['failure']}" for r in campaign["flights"] if r["failure"]]
    return "\n".join(line.rstrip() for line in lines + (["failures:", *failures] if failures else []))


def write_experiment_campaign(results: list[FlightResult], options: CampaignOptions, wall_s: float
                              ) -> dict[str, Any]:
    campaign = summarize_experiment(results, options, wall_s)
    (options.out_dir / "campaign.json").write_text(json.dumps(campaign, indent=2, default=float) + "\n")
    return campaign

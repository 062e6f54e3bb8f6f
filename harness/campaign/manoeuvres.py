"""Clearance by manoeuvre x direction relative to the camera (issue 29): where a weakness lives shows as a row.

Each campaign flight's draws record its operator's manoeuvres (kind, direction of motion relative to the camera's
axis, planned start and steps; :mod:`harness.campaign.sessions`). This module judges each manoeuvre's window of the
flight's truth with the one judge (:mod:`harness.judge`) and folds them into a table: for every (manoeuvre,
direction), how many were flown, the lowest clearance and the flight it came from. The windows are the plan's times
on the simulated clock, where the deterministic lock-step's operator starts at t = 0 (a plain lock-step flight's
operator joins a few seconds later: its windows are approximate).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from harness.campaign.safety import read_truth
from harness.judge import ArenaGeometry, judge
from quadlink.config import load_config
from sim_sitl.config import PhysicsConfig, ScenarioConfig

REST_HEIGHT_M = PhysicsConfig().body_size_m[2] / 2


@dataclass(frozen=True)
class ManoeuvreClearance:
    flight: int
    kind: str
    direction: str
    t_start_s: float
    t_end_s: float
    min_clearance_m: float


def manoeuvre_windows(record: dict[str, Any]) -> list[tuple[str, str, float, float]]:
    """(kind, direction, start, end) of every manoeuvre a flight's ``draws.json`` plans (simulated s)."""
    out = []
    for m in record.get("operator", {}).get("manoeuvres", []):
        steps = m.get("steps", [])
        duration = float(sum(s[3] for s in steps if len(s) > 3))
        t0 = float(m.get("t_plan_s", math.nan))
        out.append((str(m.get("kind", "?")), str(m.get("direction", "along")), t0, t0 + duration))
    return out


def flight_manoeuvres(folder: Path, index: int) -> list[ManoeuvreClearance]:
    """Each planned manoeuvre of the flight in ``folder`` judged on its truth (empty without truth or draws)."""
    draws, truth, scenario = folder / "draws.json", folder / "truth.tlog", folder / "scenario.yaml"
    if not (draws.is_file() and truth.is_file() and scenario.is_file()):
        return []
    series = read_truth(truth)
    geometry = ArenaGeometry(load_config(scenario, ScenarioConfig))
    out = []
    for kind, direction, t0, t1 in manoeuvre_windows(json.loads(draws.read_text())):
        sel = (series.t_pos_s >= t0) & (series.t_pos_s <= t1)
        if not np.any(sel):
            continue
        j = judge(series.t_pos_s[sel], series.p_local_ned_m[sel], geometry, REST_HEIGHT_M)
        out.append(ManoeuvreClearance(index, kind, direction, t0, t1, j.min_clearance_m))
    return out


def table(rows: list[ManoeuvreClearance]) -> list[dict[str, Any]]:
    """One row per (manoeuvre, direction): count, lowest clearance, its flight, median."""
    groups: dict[tuple[str, str], list[ManoeuvreClearance]] = {}
    for r in rows:
        if math.isfinite(r.min_clearance_m):
            groups.setdefault((r.kind, r.direction), []).append(r)
    out = []
    for (kind, direction), rs in sorted(groups.items()):
        worst = min(rs, key=lambda r: r.min_clearance_m)
        out.append({"manoeuvre": kind, "direction": direction, "count": len(rs),
                    "min_clearance_m": worst.min_clearance_m, "worst_flight": worst.flight,
                    "median_clearance_m": float(np.median([r.min_clearance_m for r in rs]))})
    return out


def table_text(rows: list[dict[str, Any]]) -> str:
    lines = ["manoeuvre      direction   flown   min clearance (flight)   median"]
    for r in rows:
        lines.append(f"{r['manoeuvre']:<14} {r['direction']:<10} {r['count']:>6}   {r['min_clearance_m']:.3f} m "
                     f"({r['worst_flight']:>4})          {r['median_clearance_m']:.2f} m")
    return "\n".join(lines)

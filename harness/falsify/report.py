"""The falsification report (issue 31): from a study, the lowest flights, the convergence and the distribution.

Pure but for :func:`write_report`. Works on any Optuna study whose trials were told by
:mod:`harness.falsify.search` (values: minimum true clearance, m; user attributes: status, finding, replay ...).

``DIR/falsify.json``: the summary (budget spent, best, the lowest flights with their parameters and replay
commands, the findings: every flight below 0.40 m and every flight in which a part died);
``DIR/convergence.png``: best clearance so far vs flights judged (trial order);
``DIR/distribution.png``: histogram of the clearances with 0.40 m (envelope) and 0.45 m (safe distance) marked.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

from harness.falsify.objective import ENVELOPE_M, SAFE_DISTANCE_M
from harness.falsify.space import HAPTIC_DIRECTIONS

LOWEST_SHOWN = 10


def _rows(study: Any) -> list[dict[str, Any]]:
    """One row per finished trial that counts (interrupted ones left out), in trial order."""
    import optuna

    interrupted = set(study.user_attrs.get("interrupted_trials", []))
    rows = []
    for t in study.get_trials(deepcopy=False):
        if t.number in interrupted or t.state not in (optuna.trial.TrialState.COMPLETE,
                                                      optuna.trial.TrialState.FAIL):
            continue
        value = t.value if t.state == optuna.trial.TrialState.COMPLETE else None
        env = t.user_attrs.get("envelope") or {}
        rows.append({"trial": t.number, "clearance_m": value, "status": t.user_attrs.get("status", "failed"),
                     "finding": bool(t.user_attrs.get("finding", value is None)),
                     "reason": t.user_attrs.get("reason", ""), "params": dict(t.params),
                     "replay": t.user_attrs.get("replay", ""), "folder": t.user_attrs.get("folder", ""),
                     "wall_s": t.user_attrs.get("wall_s"), "surface": env.get("surface"), "t_min_s": env.get("t_min_s"),
                     "moved_m": t.user_attrs.get("moved_m"),
                     "retried": bool(t.user_attrs.get("retried", False))})
    return rows


def convergence(rows: list[dict[str, Any]]) -> list[float]:
    """Best clearance after each judged flight (inf until the first value)."""
    best, out = math.inf, []
    for r in rows:
        if r["clearance_m"] is not None:
            best = min(best, r["clearance_m"])
        out.append(best)
    return out


def summary(study: Any, out_dir: Path, export_hint: bool = True) -> dict[str, Any]:
    rows = _rows(study)
    values = [r["clearance_m"] for r in rows if r["clearance_m"] is not None]
    ranked = sorted((r for r in rows if r["clearance_m"] is not None), key=lambda r: r["clearance_m"])
    findings = [r for r in rows if r["finding"]]
    for r in findings:
        r["export"] = f"quadlink falsify export {out_dir} --trial {r['trial']} tests/regression_flights/" \
                      f"falsify-{r['trial']:04d}" if export_hint else ""
    wall = [r["wall_s"] for r in rows if isinstance(r["wall_s"], (int, float))]
    return {
        "study": str(out_dir / "study.db"), "search": dict(study.user_attrs),
        "flights": len(rows), "judged": len(values), "failed": sum(r["status"] != "ok" for r in rows),
        "best_clearance_m": min(values) if values else None,
        "median_clearance_m": sorted(values)[len(values) // 2] if values else None,
        "below_envelope": sum(v < ENVELOPE_M for v in values),
        "below_safe_distance": sum(v < SAFE_DISTANCE_M for v in values),
        "envelope_m": ENVELOPE_M, "safe_distance_m": SAFE_DISTANCE_M,
        "mean_flight_wall_s": sum(wall) / len(wall) if wall else None,
        "lowest": ranked[:LOWEST_SHOWN], "findings": findings,
        "convergence_m": [v if math.isfinite(v) else None for v in convergence(rows)],
        "plots": ["convergence.png", "distribution.png"],
    }


def summary_text(s: dict[str, Any]) -> str:
    best = s["best_clearance_m"]
    lines = [f"flights judged {s['judged']} of {s['flights']} (failed {s['failed']}); best clearance "
             f"{best:.3f} m" if best is not None else f"flights {s['flights']}, none judged",
             f"below {s['envelope_m']:.2f} m: {s['below_envelope']}   below {s['safe_distance_m']:.2f} m: "
             f"{s['below_safe_distance']}", "", "lowest flights:"]
    for r in s["lowest"]:
        p = r["params"]
        flown = p.get("operator") if p.get("push_direction") in HAPTIC_DIRECTIONS else "offboard"
        moved = f"moved {r['moved_m']:.2f} m, " if isinstance(r.get("moved_m"), (int, float)) else ""
        lines.append(f"  trial {r['trial']:4d}  {r['clearance_m']:.3f} m ({r['surface']}, t {r['t_min_s'] or 0:.1f} s, "
                     f"{moved.rstrip(', ')})"
                     f"  {p.get('obstacle_kind')} {p.get('obstacle_distance_m', 0):.2f} m at "
                     f"{p.get('obstacle_bearing_deg', 0):+.0f} deg, push {p.get('push_direction')} "
                     f"{p.get('push_speed_fraction', 0):.2f} by {flown}, pan-scan "
                     f"{'on' if p.get('pan_scan') else 'off'}")
        lines.append(f"              re-fly: {r['replay']}")
    if s["findings"]:
        lines += ["", "findings (below the envelope, or a part died):"]
        for r in s["findings"]:
            lines.append(f"  trial {r['trial']:4d}  {r['reason']}")
            lines.append(f"              export: {r['export']}")
    return "\n".join(lines)


def write_report(study: Any, out_dir: Path) -> dict[str, Any]:
    """``falsify.json``, ``convergence.png`` and ``distribution.png`` in ``out_dir``; returns the summary."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s = summary(study, out_dir)
    (out_dir / "falsify.json").write_text(json.dumps(s, indent=2, default=float) + "\n")
    conv = [v if v is not None else math.nan for v in s["convergence_m"]]
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    ax.step(range(1, len(conv) + 1), conv, where="post", label="best so far")
    values = [r["clearance_m"] for r in _rows(study)]
    ax.plot(range(1, len(values) + 1), [v if v is not None else math.nan for v in values], ".", alpha=0.5,
            label="each flight")
    for y, label in ((ENVELOPE_M, "envelope 0.40 m"), (SAFE_DISTANCE_M, "safe distance 0.45 m")):
        ax.axhline(y, ls="--", lw=1, color="r" if y == ENVELOPE_M else "orange", label=label)
    ax.set_xlabel("flights judged")
    ax.set_ylabel("minimum true clearance (m)")
    ax.set_title(f"Falsification: convergence ({s['search'].get('sampler', '?')})")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out_dir / "convergence.png", dpi=100)
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    finite = [v for v in values if v is not None]
    if finite:
        ax.hist(finite, bins=max(5, min(40, len(finite))), color="tab:blue", alpha=0.8)
    for y, label in ((ENVELOPE_M, "envelope 0.40 m"), (SAFE_DISTANCE_M, "safe distance 0.45 m")):
        ax.axvline(y, ls="--", lw=1, color="r" if y == ENVELOPE_M else "orange", label=label)
    ax.set_xlabel("minimum true clearance (m)")
    ax.set_ylabel("flights")
    ax.set_title(f"Falsification: distribution ({len(finite)} flights)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out_dir / "distribution.png", dpi=100)
    plt.close(fig)
    return s

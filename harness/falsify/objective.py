"""The search's objective: one flown flight -> the number the optimiser minimises (issue 31).

Everything that judges a flight for the search goes through :func:`clearance_m`, so the whole-flight judge that
replaces :func:`harness.campaign.safety.envelope` is swapped in here and nowhere else. Today it reads the
envelope the campaign runner computed from the truth log (``FlightResult.envelope``: the minimum true distance
from the centre of mass to walls, objects and the ceiling, take-off and touchdown included).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from harness.campaign.runner import FlightResult
from harness.campaign.safety import read_truth

#: the safety envelope of issue 31: minimum true clearance to every non-floor surface over the whole flight
ENVELOPE_M = 0.40
#: the companion's configured safe distance (configs/companion.yaml reference.safe_distance_m)
SAFE_DISTANCE_M = 0.45


@dataclass(frozen=True)
class Verdict:
    clearance_m: float  # NaN: the flight left no truth to judge
    status: str  # the runner's status: ok | failed (a part died) | lost | cancelled
    finding: bool  # below the envelope, or a part of the stack died: a finding either way
    reason: str
    moved_m: float  # farthest horizontal distance from the take-off point (a clearance means little if it stayed)


def clearance_m(result: FlightResult) -> float:
    """The flight's minimum true clearance (m) to every non-floor surface; NaN when it left no truth."""
    value = result.envelope.get("min_nonfloor_m", math.nan)
    return float(value) if value is not None else math.nan


def moved_m(folder: Path) -> float:
    """Farthest horizontal distance (m) of the centre of mass from the take-off point (truth); NaN without truth."""
    path = folder / "truth.tlog"
    if not path.is_file():
        return math.nan
    p = read_truth(path).p_local_ned_m
    return float(np.max(np.hypot(p[:, 0], p[:, 1]))) if len(p) else math.nan


def judge(result: FlightResult) -> Verdict:
    c = clearance_m(result)
    moved = moved_m(Path(result.folder))
    if result.status in ("failed", "lost"):
        return Verdict(c, result.status, True, f"{result.status}: {result.failure}", moved)
    if math.isfinite(c) and c < ENVELOPE_M:
        return Verdict(c, result.status, True, f"clearance {c:.3f} m < {ENVELOPE_M:.2f} m", moved)
    return Verdict(c, result.status, False, "", moved)

"""Issue 31: every finding exported by ``quadlink falsify export`` into ``tests/regression_flights/NAME/`` flies again
here, from its fixed files, in the deterministic lock-step, and must now keep the envelope (0.40 m to every non-floor
surface over the whole flight) while still moving: a vehicle that stays on the spot passes any clearance check.

No folder, no test: the folders are added by hand from a study's findings (docs/falsification.md).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from harness.falsify.export import fly_regression
from harness.falsify.objective import ENVELOPE_M, judge
from harness.ports import free_port_offset

pytestmark = [pytest.mark.sitl, pytest.mark.slow]

REGRESSION_DIR = Path(__file__).resolve().parents[1] / "regression_flights"
FLIGHTS = sorted(p.parent for p in REGRESSION_DIR.glob("*/finding.json"))
OFFSET = free_port_offset()   # harness.ports: free now, reserved for this session
MIN_MOVED_M = 0.3  # the push must still take the vehicle somewhere ...
HELD_NEAR_M = 0.60  # ... or the layer held it within 0.15 m of its safe distance (0.45 m): as far as the room let it


@pytest.mark.parametrize("folder", FLIGHTS, ids=[p.name for p in FLIGHTS])
def test_regression_flight_keeps_the_envelope(folder: Path, tmp_path: Path) -> None:
    finding = json.loads((folder / "finding.json").read_text())
    result = fly_regression(folder, tmp_path / folder.name, OFFSET)
    verdict = judge(result)
    assert result.status == "ok", result.failure
    assert verdict.moved_m > MIN_MOVED_M or verdict.clearance_m <= HELD_NEAR_M, (
        f"moved only {verdict.moved_m:.2f} m and never came within {HELD_NEAR_M} m of anything "
        f"({verdict.clearance_m:.3f} m)")
    assert verdict.clearance_m >= ENVELOPE_M, (
        f"{folder.name}: {verdict.clearance_m:.3f} m (found at {finding['clearance_m']} m by trial "
        f"{finding['source']['trial']})")

"""Issue 19 in the SITL: paper 003's trajectory flown through the whole stack (SITL lock-step, bridge with the
geometric tracker, companion, a ground-station client streaming position + velocity + acceleration setpoints),
``harness.demo.paper003_cli.run_paper003`` — the code behind ``quadlink paper003 oval|hover``.

* the oval, flown as a campaign flight (issue 19's campaign: a drawn start pose turned -158 deg from north and a
  vehicle 8 % heavier than the stack's model, ``quadlink campaign --experiment paper003-oval``'s flight code
  without Ray): Tables 3-5 of paper 003 within issue 19's bounds, the truth's tracking error, the evidence that
  the companion flew it (its setpoints to the bridge carry the acceleration feed-forward, mask 1031), and the
  flight's folder (draws, result, PASS);
* a trajectory straight through a column: the companion's safety layer stops the vehicle short of it (minimum
  true distance to the column's surface >= 0.40 m, safe distance 0.45 m) — the trajectory yields;
* the hover with paper 003's three pushes (slow): each back within 5 cm in under 3 s.

Port offsets 5100-5700 (other SITL tests: 700-1000, 1000-2500, 3300-3800, 4300-4800).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from harness.campaign.experiments import draw_experiment_flight
from harness.campaign.runner import CampaignOptions, fly
from harness.demo.paper003 import ISSUE19_TARGETS
from harness.demo.paper003_cli import format_hover, run_paper003
from harness.ports import PORT_SLOT_STRIDE, free_port_offset
from quadlink import CONFIG_DIR
from quadlink.mavlink import mavlink
from quadlink.mavlink.setpoint_masks import TM_VELOCITY_ACCEL_YAW_RATE
from quadlink.mavlink.tlog import read_tlog

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(900)]

OFFSET = free_port_offset(slots=3)   # harness.ports: free now, reserved for this session
COLUMN_NE_M = (1.5, 1.5)      # configs/scenarios/paper003-obstacle.yaml (arena = local NED: start (0, 0), yaw 0)
COLUMN_RADIUS_M = 0.25
MIN_CLEARANCE_M = 0.40
# issue 19's figures (ISSUE19_TARGETS) are the estimate's against the desired path; the truth adds the odometry's
# drift over the flight, which the stack cannot see: on this test's draw (campaign flight 4, yaw -158 deg) x read
# 0.027 and 0.051 m in two flights, z 0.018-0.024 m over the six-flight campaign (0.064 m before the floor was
# levelled with the odometry's attitude)
TRUE_POSITION_BOUND_M = (0.07, 0.07, 0.07)


def _companion_setpoint_masks(tlog: Path) -> list[int]:
    return [m.type_mask for _, m in read_tlog(tlog)
            if m.get_type() == "SET_POSITION_TARGET_LOCAL_NED" and m.get_srcComponent() == 191
            and m.coordinate_frame == mavlink.MAV_FRAME_BODY_OFFSET_NED]


def test_oval_through_the_companion_within_paper_003s_bounds(tmp_path: Path) -> None:
    seed, index = 19, 4   # flight 4 of the README's campaign
    draws = draw_experiment_flight(seed, index, "paper003-oval").record
    assert abs(draws["arena"]["start"]["yaw_deg"]) > 90 and draws["vehicle"]["mass_scale"] > 1.05  # what it tests
    result = fly(CampaignOptions(1, seed, tmp_path, port_offset=OFFSET, experiment="paper003-oval",
                                 first_index=index), index, 0, 1)
    assert result.status == "ok", result.failure
    folder = Path(result.folder)
    assert json.loads((folder / "draws.json").read_text()) == draws == result.draws
    report = result.report
    assert report["start_yaw_deg"] == draws["arena"]["start"]["yaw_deg"]
    t = report["tables"]
    print(report["trajectory"])
    for key in ("table4_position_m", "table5_velocity_m_s", "table3_velocity_m_s",
                "true_position_vs_desired_m", "true_velocity_vs_desired_m_s"):
        print(key, np.round(t[key], 4), "paper", t["paper"].get(key))
    assert report["trajectory"]["samples"] > 200     # the 9 s at camera rate (30 Hz)
    for key, target in ISSUE19_TARGETS.items():
        assert np.all(np.asarray(t[key]) <= target), (key, t[key])
    assert np.all(np.asarray(t["true_position_vs_desired_m"]) <= TRUE_POSITION_BOUND_M), t["true_position_vs_desired_m"]
    assert np.all(np.asarray(t["true_velocity_vs_desired_m_s"]) <= ISSUE19_TARGETS["table5_velocity_m_s"])
    # the flight's own verdict agrees (asserted after the figures, so a failure names the figure that failed)
    assert json.loads((folder / "result.json").read_text())["headline"] == result.headline == "PASS"
    # the companion flew it: velocity + acceleration feed-forward to the bridge (not the client's setpoints raw)
    masks = _companion_setpoint_masks(folder / "companion.tlog")
    assert sum(m == TM_VELOCITY_ACCEL_YAW_RATE for m in masks) > 200, sorted(set(masks))


def test_a_trajectory_into_a_column_yields_to_it(tmp_path: Path) -> None:
    report = run_paper003("oval", tmp_path, port_offset=OFFSET + PORT_SLOT_STRIDE, plots=False,
                          scenario=str(CONFIG_DIR / "scenarios" / "paper003-obstacle.yaml"),
                          trajectory=CONFIG_DIR / "trajectories" / "into-column.yaml", lead_in_s=4.0, hold_s=4.0)
    truth = np.loadtxt(tmp_path / "truth.csv", delimiter=",").reshape(-1, 7)
    start_s = report["trajectory"]["start_s"]
    flying = truth[truth[:, 0] >= start_s - 4.0]
    d = np.hypot(flying[:, 1] - COLUMN_NE_M[0], flying[:, 2] - COLUMN_NE_M[1]) - COLUMN_RADIUS_M
    k = int(np.argmin(d))
    print(f"min true distance to the column {d[k]:.3f} m at t = {flying[k, 0]:.1f} s, p = {flying[k, 1:4]}")
    assert d[k] >= MIN_CLEARANCE_M, d[k]
    assert d[k] <= 0.8, f"never came near the column ({d[k]:.2f} m): it did not fly the trajectory"
    # the acceleration feed-forward was dropped while the safety layer constrained the velocity
    masks = _companion_setpoint_masks(tmp_path / "companion.tlog")
    assert any(m == TM_VELOCITY_ACCEL_YAW_RATE for m in masks) and any(m != TM_VELOCITY_ACCEL_YAW_RATE for m in masks)


@pytest.mark.slow   # ~60 s of flight in real time (the pushes at 30, 40, 50 s of SITL time)
def test_hover_back_within_3_s_of_each_push(tmp_path: Path) -> None:
    report = run_paper003("hover", tmp_path, port_offset=OFFSET + 2 * PORT_SLOT_STRIDE, plots=False)
    print(format_hover(report))
    rec = report["recoveries_truth"]
    assert len(rec) == 3
    for r in rec:
        assert 0.5 < r["peak_displacement_m"] < 1.0, r      # paper 003: ~0.7 m
        assert math.isfinite(r["back_after_s"]) and r["back_after_s"] < 3.0, r

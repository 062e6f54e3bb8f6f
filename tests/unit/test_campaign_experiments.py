"""Issue 19 in a campaign: the draws of paper 003's experiment flights (seeded, reproducible, in bounds, the path
clear of the walls) and the campaign report of the experiments."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from harness.campaign.draws import draw_flight, write_sitl_files
from harness.campaign.experiment_report import experiment_summary_text, summarize_experiment
from harness.campaign.experiments import (
    EXPERIMENTS,
    PATH_CLEARANCE_M,
    draw_experiment_flight,
    draw_start_clear_of,
    path_in_arena,
    path_xy_m,
)
from harness.campaign.runner import CampaignOptions, FlightResult
from harness.demo.paper003 import Paper003Series, Recovery, hover_pass, tables
from quadlink import CONFIG_DIR
from quadlink.config import load_config
from quadlink.errors import ConfigError
from quadlink.vehicle import load_vehicle
from sim_sitl.config import RoomConfig, ScenarioConfig, SceneObject, StartPose, load_scenario, load_sitl_config


def _wall_distance_m(room: RoomConfig, xy: np.ndarray) -> np.ndarray:
    """Distance to the nearest wall of an empty rectangular room, from its own geometry."""
    nx, ny = room.size_m
    return np.minimum(nx / 2 - np.abs(xy[:, 0]), ny / 2 - np.abs(xy[:, 1]))


@pytest.mark.parametrize("name", sorted(EXPERIMENTS))
def test_experiment_draws_are_seeded_reproducible_and_in_bounds(name: str, tmp_path: Path) -> None:
    nominal = load_vehicle("vehicle")
    starts = set()
    for i in range(12):
        d = draw_experiment_flight(20261202, i, name)
        again = draw_experiment_flight(20261202, i, name)
        assert d.record == again.record and d.scenario == again.scenario and d.vehicle == again.vehicle
        start = d.scenario.start
        assert d.record["arena"]["start"] == {"position_m": list(start.position_m), "yaw_deg": start.yaw_deg}
        assert -180.0 <= start.yaw_deg <= 180.0
        assert 0.9 * nominal.mass_kg <= d.vehicle["mass_kg"] <= 1.1 * nominal.mass_kg
        assert d.record["vehicle"]["mass_kg"] == d.vehicle["mass_kg"]
        # the whole path, flown from the drawn pose, keeps the clearance from the walls (the rooms are empty)
        arena = path_in_arena(start, path_xy_m(EXPERIMENTS[name].paper003))
        assert _wall_distance_m(d.scenario.room, arena).min() >= PATH_CLEARANCE_M - 1e-9
        assert d.record["arena"]["path_clearance_m"] == pytest.approx(_wall_distance_m(d.scenario.room, arena).min(),
                                                                      abs=1e-4)
        # flight i's vehicle and sensors are those of a teleop campaign's flight i of the same seed
        teleop = draw_flight(20261202, i, 30.0)
        assert d.vehicle == teleop.vehicle and d.sitl == teleop.sitl
        starts.add((start.position_m, start.yaw_deg))
    assert len(starts) == 12
    assert draw_experiment_flight(7, 0, name).record != draw_experiment_flight(8, 0, name).record
    # the files the SITL loads carry the draws, and the hover keeps its pushes
    d = draw_experiment_flight(20261202, 3, name)
    files = write_sitl_files(d.scenario, d.vehicle, d.sitl, d.record, tmp_path)
    assert load_config(files.scenario, ScenarioConfig) == d.scenario
    assert load_sitl_config(files.sitl).seed == d.record["sitl_seed"]
    assert json.loads(files.draws.read_text()) == d.record
    assert d.scenario.disturbances == load_scenario(EXPERIMENTS[name].scenario).disturbances


def test_the_clearance_covers_the_repulsions_reach() -> None:
    reference = yaml.safe_load((CONFIG_DIR / "companion.yaml").read_text())["reference"]
    assert PATH_CLEARANCE_M >= reference["influence_distance_m"] + 0.2


def test_start_avoids_objects_and_refuses_a_room_too_small() -> None:
    column = SceneObject(kind="cylinder", name="c", position_m=(0.0, 0.0, -1.5), radius_m=0.3, height_m=3.0)
    room = ScenarioConfig(room=RoomConfig(size_m=(8.0, 8.0)), objects=(column,))
    path = path_xy_m("oval")
    rng = np.random.default_rng(1)
    for _ in range(10):
        start, d = draw_start_clear_of(room, path, rng)
        arena = path_in_arena(start, path)
        to_column = np.linalg.norm(arena, axis=1) - 0.3
        assert min(to_column.min(), _wall_distance_m(room.room, arena).min()) == pytest.approx(d, abs=1e-6)
        assert d >= PATH_CLEARANCE_M
    with pytest.raises(ConfigError):
        draw_start_clear_of(ScenarioConfig(room=RoomConfig(size_m=(3.0, 3.0))), path, rng, tries=50)


def test_path_turns_with_the_start_yaw() -> None:
    path = np.array([[1.0, 0.0], [0.0, 1.0]])  # forward, right of the start heading
    east = path_in_arena(StartPose(position_m=(2.0, -1.0), yaw_deg=90.0), path)  # heading east
    np.testing.assert_allclose(east, [[2.0, 0.0], [1.0, -1.0]], atol=1e-12)


def _oval_result(index: int, offset_m: float, folder: Path) -> FlightResult:
    d = draw_experiment_flight(5, index, "paper003-oval")
    t = np.linspace(0.0, 9.0, 900)
    p_d = np.column_stack([np.cos(t), np.sin(t), -1.2 + 0 * t])
    v_d = np.column_stack([-np.sin(t), np.cos(t), 0 * t])
    p = p_d + offset_m
    report = {"experiment": "oval", "tables": tables(Paper003Series(t, p_d, v_d, p, v_d, p, v_d))}
    return FlightResult(index, "ok", 1, str(folder / f"flight-{index:04d}"), report=report, draws=d.record,
                        code_version="abc1234")


def test_report_of_an_oval_campaign(tmp_path: Path) -> None:
    results = [_oval_result(0, 0.01, tmp_path), _oval_result(1, 0.03, tmp_path), _oval_result(2, 0.07, tmp_path),
               FlightResult(3, "failed", 1, str(tmp_path / "flight-0003"), failure="ProcessDied: bridge",
                            draws=draw_experiment_flight(5, 3, "paper003-oval").record, code_version="abc1234")]
    options = CampaignOptions(4, 5, tmp_path, experiment="paper003-oval")
    campaign = summarize_experiment(results, options, 100.0)
    rows = campaign["flights"]
    assert [r["verdict"] for r in rows] == ["PASS", "PASS", "FAIL", "FAIL (no figures)"]
    t4 = campaign["summary"]["figures"]["table4_position_m"]
    assert t4["worst"] == pytest.approx([0.07] * 3) and t4["median"] == pytest.approx([0.03] * 3)
    assert t4["flights"] == 3
    assert t4["beats_paper"] == [2, 2, 1]   # 0.01 beats 0.057 / 0.066 / 0.013, 0.03 only x and y, 0.07 none
    assert campaign["summary"]["passed"] == [0, 1] and campaign["summary"]["failed"] == [2, 3]
    text = experiment_summary_text(campaign)
    assert "seed 5, code abc1234" in text and "PASS 2 of 4" in text
    assert "0.057/0.066/0.013" in text  # paper 003's Table 4 beside ours
    assert "2/2/1" in text
    assert (f"quadlink paper003 oval --scenario {tmp_path}/flight-0002/scenario.yaml "
            f"--sitl-config {tmp_path}/flight-0002/sitl.yaml --out {tmp_path}/flight-0002/replay") in text
    assert "ProcessDied: bridge" in text


def test_report_of_a_hover_campaign(tmp_path: Path) -> None:
    results = []
    for i, back_s in enumerate((1.7, 2.4, math.inf)):
        recoveries = [Recovery(30.0 + 10 * k, 0.7 + 0.05 * k, 1.2, back_s if k == 2 else 1.5) for k in range(3)]
        report = {"experiment": "hover", "recoveries_truth": [r.__dict__ for r in recoveries],
                  "pass": hover_pass(recoveries)}
        results.append(FlightResult(i, "ok", 1, str(tmp_path / f"flight-{i:04d}"), report=report,
                                    draws=draw_experiment_flight(5, i, "paper003-hover").record))
    campaign = summarize_experiment(results, CampaignOptions(3, 5, tmp_path, experiment="paper003-hover"), 1.0)
    assert [r["verdict"] for r in campaign["flights"]] == ["PASS", "PASS", "FAIL"]
    back = campaign["summary"]["figures"]["back_after_s"]
    assert back["worst"][2] == math.inf and back["median"] == pytest.approx([1.5, 1.5, 2.4])
    assert "beats_paper" not in back
    text = experiment_summary_text(campaign)
    assert "quadlink paper003 hover --scenario" in text and "PASS 2 of 3" in text

"""Issue 31: the falsification search's flight space, objective, study bookkeeping and report (no flights)."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import optuna
import pytest
import yaml
from click.testing import CliRunner

from companion.config import load_companion_config
from harness.campaign.offboard_client import load_plan, setpoint_at
from harness.campaign.runner import FlightResult
from harness.campaign.sessions import LANDING_S, TAKEOFF_S
from harness.falsify.objective import ENVELOPE_M, judge
from harness.falsify.report import convergence, summary, summary_text, write_report
from harness.falsify.search import _interrupt, counted, interrupted_trials
from harness.falsify.space import (
    MIN_START_CLEARANCE_M,
    MOTION_OFFSET_RAD,
    build_flight,
    choices,
    distributions,
    param_fields,
    params_from_dict,
    sample,
    suggest,
    write_flight,
)
from quadlink.config import load_config
from quadlink.errors import ConfigError
from sim_sitl.config import ScenarioConfig, SitlConfig
from sim_sitl.scenario_gen import nearest_obstacle_2d
from teleop.devices.script import load_script

DURATION_S = 26.0


def _no_walls(scenario: ScenarioConfig) -> ScenarioConfig:
    return dataclasses.replace(scenario, room=dataclasses.replace(scenario.room, walls=False))


def test_every_parameter_is_bounded_with_a_unit_or_has_choices() -> None:
    for f in param_fields():
        if choices(f) is None:
            lo, hi = f.metadata["low"], f.metadata["high"]
            assert lo is not None and hi is not None and lo < hi, f.name
            assert f.metadata["doc"], f.name
            assert f.metadata["unit"] or f.name == "sitl_seed", f.name
        else:
            assert len(choices(f)) >= 2, f.name


def test_out_of_bounds_points_are_refused_by_name(rng: np.random.Generator) -> None:
    p = sample(rng)
    for f in param_fields():
        if choices(f) is None:
            for bad in (f.metadata["low"] - 1, f.metadata["high"] + 1, math.nan):
                with pytest.raises(ConfigError, match=f.name):
                    dataclasses.replace(p, **{f.name: bad})
        else:
            with pytest.raises(ConfigError, match=f.name):
                dataclasses.replace(p, **{f.name: "sideways"})
    with pytest.raises(ConfigError, match="unknown"):
        params_from_dict({**dataclasses.asdict(p), "wind_m_s": 3.0})
    with pytest.raises(ConfigError, match="missing"):
        params_from_dict({k: v for k, v in dataclasses.asdict(p).items() if k != "mass_scale"})


def test_the_obstacle_is_of_the_points_material_and_an_older_studys_point_is_matte(rng: np.random.Generator) -> None:
    """The space draws the campaigns' hazards (an object the Xtion gets no return from); a trial of a study from
    before the parameter has none, and reads as the matte obstacle it flew."""
    p = dataclasses.replace(sample(rng), obstacle_material="dark")
    assert {o.material for o in build_flight(p, DURATION_S).scenario.objects} == {"dark"}
    older = {k: v for k, v in dataclasses.asdict(p).items() if k != "obstacle_material"}
    q = params_from_dict(older)
    assert q.obstacle_material == "matte"
    assert {o.material for o in build_flight(q, DURATION_S).scenario.objects} == {"matte"}
    assert "dark" not in build_flight(q, DURATION_S).scenario.description


def test_same_point_gives_the_same_files(rng: np.random.Generator, tmp_path: Path) -> None:
    for i in range(6):
        p = sample(rng)
        a, b = tmp_path / f"a{i}", tmp_path / f"b{i}"
        write_flight(build_flight(p, DURATION_S), a)
        write_flight(build_flight(params_from_dict(dataclasses.asdict(p)), DURATION_S), b)
        for name in ("scenario.yaml", "operator.yaml", "vehicle.yaml", "companion.yaml", "draws.json"):
            assert (a / name).read_bytes() == (b / name).read_bytes(), name
        sa, sb = (yaml.safe_load((d / "sitl.yaml").read_text()) for d in (a, b))
        assert Path(sa.pop("vehicle")).name == Path(sb.pop("vehicle")).name == "vehicle.yaml"
        assert Path(sa.pop("scenario")).name == Path(sb.pop("scenario")).name == "scenario.yaml"
        assert sa == sb
    # and a different point gives different files
    p, q = sample(rng), sample(rng)
    write_flight(build_flight(p, DURATION_S), tmp_path / "p")
    write_flight(build_flight(q, DURATION_S), tmp_path / "q")
    assert (tmp_path / "p" / "scenario.yaml").read_bytes() != (tmp_path / "q" / "scenario.yaml").read_bytes()


def test_every_sampled_point_is_a_valid_flight(rng: np.random.Generator) -> None:
    kinds = set()
    for _ in range(300):
        p = sample(rng)
        f = build_flight(p, DURATION_S)
        kinds.add((p.obstacle_kind, f.operator))
        sc = f.scenario
        assert f.record["start_clearance_m"] >= MIN_START_CLEARANCE_M
        # the obstacle is where the point says: its nearest surface at the distance (doorway: the wall's plane)
        d, point, _ = nearest_obstacle_2d(_no_walls(sc), sc.start.position_m, band_m=(-10.0, 10.0))
        if p.obstacle_kind == "doorway":
            assert d >= p.obstacle_distance_m - 1e-3
        else:
            assert d == pytest.approx(p.obstacle_distance_m, abs=2e-3), p.obstacle_kind
        if p.obstacle_kind in ("wall", "pole", "column", "box"):
            bearing = math.atan2(point[1], point[0]) - MOTION_OFFSET_RAD
            err = (bearing - math.radians(p.obstacle_bearing_deg) + math.pi) % (2 * math.pi) - math.pi
            assert abs(err) < 1e-2, p.obstacle_kind
        assert sc.room.height_m == pytest.approx(p.room_height_m, abs=1e-3)
        if p.room_height_entered:
            assert f.companion["reference"]["room_height_m"] == pytest.approx(p.room_height_m + p.room_height_error_m,
                                                                              abs=1e-3)
        else:
            assert f.companion["reference"]["room_height_m"] is None
        assert f.companion["pan_scan"]["enabled"] is p.pan_scan
        assert f.sitl["seed"] == p.sitl_seed
        if p.push_direction in ("across", "diagonal"):
            assert f.operator == "offboard"
        else:
            assert f.operator == p.operator
    assert len(kinds) == 12  # every obstacle with both operators


def test_written_files_load_with_the_parts_own_loaders(rng: np.random.Generator, tmp_path: Path) -> None:
    flown = set()
    for i in range(12):
        p = sample(rng)
        f = build_flight(p, DURATION_S)
        files, companion = write_flight(f, tmp_path / str(i))
        scenario = load_config(files.scenario, ScenarioConfig)
        assert len(scenario.objects) == len(f.scenario.objects)
        sitl = load_config(files.sitl, SitlConfig)
        assert sitl.seed == p.sitl_seed and Path(sitl.vehicle).is_file() and Path(sitl.scenario).is_file()
        cfg = load_companion_config(companion)
        assert cfg.pan_scan.enabled is p.pan_scan
        assert (cfg.reference.room_height_m is None) is not p.room_height_entered
        before, push, after = f.record["phases_s"]
        assert before + push + after == pytest.approx(DURATION_S - TAKEOFF_S - LANDING_S)
        assert push == pytest.approx(min(p.push_duration_s, DURATION_S - TAKEOFF_S - LANDING_S - before))
        if f.operator == "haptic":
            script = load_script(files.operator)
            assert script.end_s == pytest.approx(DURATION_S, abs=1e-3)
            assert [name for _, name in script.presses] == ["arm", "takeoff", "land"]
            force = script.force_at(TAKEOFF_S + before + push / 2)
            sign = 1.0 if p.push_direction == "along" else -1.0
            assert force[0] == pytest.approx(sign * p.push_speed_fraction * 1.6 * 1.1, abs=1e-3)
            assert force[1] == pytest.approx(p.push_yaw_rate_rad_s / 0.8 * 1.6 * 1.1, abs=1e-3)
        else:
            plan = load_plan(files.operator)
            sp = setpoint_at(plan, TAKEOFF_S + before + push / 2)
            assert sp is not None
            speed = math.hypot(sp.vx_m_s, sp.vy_m_s)
            assert speed == pytest.approx(0.6 * p.push_speed_fraction, abs=1e-3)
            # the push's angle from the camera's axis (45 deg right of the body's x)
            angle = math.degrees(math.atan2(sp.vy_m_s, sp.vx_m_s) - MOTION_OFFSET_RAD) % 360
            want = {"along": 0, "diagonal": 45, "across": 90, "against": 180}[p.push_direction]
            assert min(abs(angle - want), 360 - abs(angle - want)) < 0.1
        flown.add(f.operator)
    assert flown == {"haptic", "offboard"}


def test_suggest_asks_the_trial_for_the_whole_space() -> None:
    study = optuna.create_study(sampler=optuna.samplers.RandomSampler(seed=3))
    for _ in range(20):
        trial = study.ask()
        p = suggest(trial)
        assert trial.distributions == distributions()
        assert params_from_dict(dict(trial.params)) == p
        study.tell(trial, 1.0)


def _result(status: str, clearance: float, failure: str | None = None, folder: str = "/nonexistent") -> FlightResult:
    env = {"min_nonfloor_m": clearance, "surface": "obstacle", "t_min_s": 17.0} if math.isfinite(clearance) else {}
    return FlightResult(0, status, 1, folder, envelope=env, failure=failure)


def test_judge_calls_failed_flights_and_low_clearances_findings() -> None:
    assert not judge(_result("ok", 0.52)).finding
    low = judge(_result("ok", 0.31))
    assert low.finding and low.clearance_m == 0.31 and "0.310" in low.reason
    died = judge(_result("failed", math.nan, "companion exited with status 1"))
    assert died.finding and math.isnan(died.clearance_m) and "companion" in died.reason
    assert judge(_result("failed", 0.9, "bridge died")).finding
    assert math.isnan(judge(_result("ok", 0.5)).moved_m)  # no truth log: nothing moved that we know of


def _study_with_trials(rng: np.random.Generator) -> tuple[Any, list[float | None]]:
    """A study of real Optuna trials as the search tells them: clearances, one died flight, one interrupted."""
    study = optuna.create_study(direction="minimize")
    values: list[float | None] = [0.81, 0.62, 0.47, None, 0.38, 0.55, 0.43]
    for i, v in enumerate(values):
        p = dataclasses.asdict(sample(rng))
        attrs = {"status": "ok" if v is not None else "failed", "replay": f"quadlink demo --replay X/trial-{i:04d}",
                 "envelope": {"surface": "obstacle", "t_min_s": 15.0 + i}, "wall_s": 40.0 + i}
        attrs["finding"] = v is None or v < ENVELOPE_M
        attrs["reason"] = "failed: companion died" if v is None else ""
        state = optuna.trial.TrialState.COMPLETE if v is not None else optuna.trial.TrialState.FAIL
        study.add_trial(optuna.trial.create_trial(params=p, distributions=distributions(), value=v, state=state,
                                                  user_attrs=attrs))
    trial = study.ask()
    suggest(trial)
    _interrupt(study, trial.number, trial.params)  # Ctrl-C: not counted, its point enqueued again
    return study, values


def test_interrupted_trials_are_not_counted_and_fly_again(rng: np.random.Generator) -> None:
    study, values = _study_with_trials(rng)
    interrupted = interrupted_trials(study)
    assert interrupted == {len(values)}
    assert sum(counted(t, interrupted) for t in study.trials) == len(values)
    again = study.ask()
    assert suggest(again) == params_from_dict(study.trials[len(values)].params)  # the enqueued point comes first
    assert again.user_attrs["requeued_from"] == len(values)


def test_report_of_a_study(rng: np.random.Generator, tmp_path: Path) -> None:
    study, values = _study_with_trials(rng)
    s = write_report(study, tmp_path)
    assert s["flights"] == len(values) and s["judged"] == len(values) - 1 and s["failed"] == 1
    assert s["best_clearance_m"] == 0.38
    assert [r["clearance_m"] for r in s["lowest"]] == sorted(v for v in values if v is not None)
    assert s["below_envelope"] == 1 and s["below_safe_distance"] == 2  # 0.38, 0.43
    assert {r["trial"] for r in s["findings"]} == {3, 4}  # the died flight and the one below 0.40 m
    assert all(r["export"].startswith(f"quadlink falsify export {tmp_path} --trial ") for r in s["findings"])
    conv = s["convergence_m"]
    assert conv == [0.81, 0.62, 0.47, 0.47, 0.38, 0.38, 0.38]
    assert conv == convergence([{"clearance_m": v} for v in values])
    on_disk = json.loads((tmp_path / "falsify.json").read_text())
    assert on_disk["best_clearance_m"] == 0.38 and on_disk["lowest"][0]["replay"].endswith("trial-0004")
    for png in ("convergence.png", "distribution.png"):
        assert (tmp_path / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    text = summary_text(summary(study, tmp_path))
    assert "0.380 m" in text and "quadlink demo --replay X/trial-0004" in text and "export" in text


def test_cli_refuses_bad_input_in_one_line(tmp_path: Path) -> None:
    from harness.falsify.cli import command

    r = CliRunner().invoke(command, ["--budget", "2"])
    assert r.exit_code == 2 and "--out DIR" in r.output
    r = CliRunner().invoke(command, ["--out", str(tmp_path / "s")])
    assert r.exit_code == 2 and "--budget and --seed" in r.output
    r = CliRunner().invoke(command, ["--resume", str(tmp_path)])
    assert r.exit_code != 0 and "no search.json" in str(r.exception)


def test_samplers() -> None:
    from harness.falsify.search import make_sampler

    assert isinstance(make_sampler("tpe", 1, 5), optuna.samplers.TPESampler)
    assert isinstance(make_sampler("random", 1, 5), optuna.samplers.RandomSampler)
    try:
        import cmaes  # noqa: F401
    except ImportError:
        with pytest.raises(ConfigError, match="cmaes"):
            make_sampler("cmaes", 1, 5)
    else:
        assert isinstance(make_sampler("cmaes", 1, 5), optuna.samplers.CmaEsSampler)
    with pytest.raises(ConfigError, match="unknown sampler"):
        make_sampler("grid", 1, 5)


def test_study_on_disk_is_created_once_and_resumed(tmp_path: Path, rng: np.random.Generator) -> None:
    from harness.falsify.search import SearchOptions, load_search_options, open_study

    options = SearchOptions(budget=3, seed=4, out_dir=tmp_path / "s", sampler="tpe", startup_trials=5,
                            duration_s=21.0, address="ray://head:10001")
    with pytest.raises(ConfigError, match="no falsification study"):
        open_study(options, resume=True)
    study = open_study(options, resume=False)
    assert (tmp_path / "s" / "study.db").is_file()
    trial = study.ask()
    suggest(trial)
    study.tell(trial, 0.7)
    with pytest.raises(ConfigError, match="--resume"):
        open_study(options, resume=False)
    again = load_search_options(tmp_path / "s", budget=9, parallel=2)
    assert (again.seed, again.sampler, again.duration_s, again.budget, again.parallel) == (4, "tpe", 21.0, 9, 2)
    assert again.address is None  # where to fly is the command line's choice
    resumed = open_study(again, resume=True)
    assert [t.value for t in resumed.trials] == [0.7]
    assert resumed.sampler._n_startup_trials == 4  # the random exploration left: 5 - 1 flown

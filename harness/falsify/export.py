"""A finding as a regression flight (issue 31): the fixed files of one trial, flown again by a test.

:func:`export_trial` writes, into a folder of its own (e.g. ``tests/regression_flights/falsify-0012``), the files the
trial's point maps to (``scenario.yaml``, ``operator.yaml``, ``vehicle.yaml``, ``sitl.yaml``, ``companion.yaml``)
and ``finding.json`` (the point, the clearance found, the code version that found it). The files are fixed from
then on: a later change to the flight space does not change the regression flight. ``sitl.yaml`` names the
vehicle and the scenario by file name; :func:`materialize` copies the folder into a flight folder with the paths
the SITL loads, and :func:`fly_regression` flies it through the campaign runner in the deterministic lock-step.
"""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path
from typing import Any

import yaml

from harness.campaign.draws import FlightFiles
from harness.campaign.runner import FlightResult, fly_files
from harness.falsify.objective import ENVELOPE_M
from harness.falsify.search import STUDY_NAME, load_search_options, storage_url, trial_folder
from harness.falsify.space import build_flight, params_from_dict, write_flight
from quadlink.errors import ConfigError

log = logging.getLogger("harness.falsify")

FILES = ("scenario.yaml", "operator.yaml", "vehicle.yaml", "companion.yaml")


def export_trial(out_dir: Path, number: int, dest: Path) -> dict[str, Any]:
    """Write trial ``number`` of the study in ``out_dir`` as a regression flight in ``dest``; returns finding.json."""
    import optuna

    options = load_search_options(out_dir)
    study = optuna.load_study(study_name=STUDY_NAME, storage=storage_url(out_dir))
    trials = {t.number: t for t in study.get_trials(deepcopy=False)}
    if number not in trials or not trials[number].params:
        raise ConfigError(f"{out_dir}: no trial {number} with parameters (trials 0..{len(trials) - 1})")
    trial = trials[number]
    params = params_from_dict(dict(trial.params))
    if dest.exists() and any(dest.iterdir()):
        raise ConfigError(f"{dest}: exists and is not empty")
    flight = build_flight(params, options.duration_s, name=f"falsify-{number:04d}")
    files, _ = write_flight(flight, dest)
    sitl = yaml.safe_load(files.sitl.read_text())
    sitl["vehicle"], sitl["scenario"] = "vehicle.yaml", "scenario.yaml"  # by name: materialize() resolves them
    files.sitl.write_text(yaml.safe_dump(sitl, sort_keys=False))
    flown = trial_folder(out_dir, number)
    same = [name for name in FILES if (flown / name).is_file()
            and (flown / name).read_bytes() == (dest / name).read_bytes()]
    if flown.is_dir() and len(same) != len(FILES):
        log.warning("trial %d: %s differ from the flown files (the flight space changed since the search)",
                    number, ", ".join(sorted(set(FILES) - set(same))))
    clearance = trial.value if trial.state == optuna.trial.TrialState.COMPLETE else None
    finding = {"source": {"study": str(out_dir.resolve() / "study.db"), "trial": number,
                          "code_version": trial.user_attrs.get("code_version", "")},
               "clearance_m": clearance, "status": trial.user_attrs.get("status"),
               "finding": bool(trial.user_attrs.get("finding", False)), "reason": trial.user_attrs.get("reason", ""),
               "envelope_m": ENVELOPE_M, "duration_s": options.duration_s, "operator": flight.operator,
               "params": dict(trial.params), "files_equal_flown": sorted(same)}
    (dest / "finding.json").write_text(json.dumps(finding, indent=2) + "\n")
    return finding


def materialize(regression_dir: Path, flight_dir: Path) -> tuple[FlightFiles, Path, dict[str, Any]]:
    """Copy a regression flight's files into ``flight_dir`` with the SITL's paths made absolute."""
    finding_path = regression_dir / "finding.json"
    if not finding_path.is_file():
        raise ConfigError(f"{regression_dir}: not a regression flight (no finding.json)")
    finding = json.loads(finding_path.read_text())
    flight_dir.mkdir(parents=True, exist_ok=True)
    for name in (*FILES, "sitl.yaml", "finding.json", "draws.json"):
        if (regression_dir / name).is_file():
            shutil.copyfile(regression_dir / name, flight_dir / name)
    files = FlightFiles(flight_dir / "scenario.yaml", flight_dir / "operator.yaml", flight_dir / "vehicle.yaml",
                        flight_dir / "sitl.yaml", flight_dir / "draws.json")
    sitl = yaml.safe_load(files.sitl.read_text())
    sitl["vehicle"], sitl["scenario"] = str(files.vehicle.resolve()), str(files.scenario.resolve())
    files.sitl.write_text(yaml.safe_dump(sitl, sort_keys=False))
    return files, flight_dir / "companion.yaml", finding


def fly_regression(regression_dir: Path, flight_dir: Path, port_offset: int) -> FlightResult:
    """Fly an exported regression flight (deterministic lock-step) into ``flight_dir``; the runner judges it."""
    files, companion, finding = materialize(regression_dir, flight_dir)
    return fly_files(files, flight_dir, int(finding["source"]["trial"]), finding["operator"],
                     float(finding["duration_s"]), port_offset, 1, {"regression": finding},
                     companion_config=companion)


"""One campaign flight of a paper 003 experiment (I/O): draw, write the flight's files, fly, keep the figures.

What a Ray task runs for ``quadlink campaign --experiment paper003-oval|paper003-hover`` (the runner's
:func:`harness.campaign.runner.fly` hands over): the draws of :mod:`harness.campaign.experiments` written into
the flight's folder (``scenario.yaml`` with the drawn start pose, ``vehicle.yaml``, ``sitl.yaml``, ``draws.json``),
then :func:`harness.demo.paper003_cli.run_paper003` on the flight's port slot, which writes ``paper003.json``,
``series.csv``, ``truth.csv``, ``companion.tlog`` and ``logs/`` there. ``result.json`` as for a teleop flight.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

from harness.campaign.draws import write_sitl_files
from harness.campaign.experiments import draw_experiment_flight
from harness.campaign.runner import CampaignOptions, FlightResult, code_version, flight_folder, flight_ports
from harness.demo.orchestrator import kill_leftovers


def replay_command(paper003: str, folder: str) -> str:
    """The one line that flies a campaign flight's draws again (into ``FOLDER/replay``, with the plots)."""
    return (f"quadlink paper003 {paper003} --scenario {folder}/scenario.yaml --sitl-config {folder}/sitl.yaml "
            f"--out {folder}/replay")


def verdict(report: dict[str, Any]) -> bool | None:
    """Issue 19's targets met (every criterion of ``paper003.json``'s ``pass``), or None without figures."""
    checks = (report.get("tables") or {}).get("pass") if report.get("experiment") == "oval" else report.get("pass")
    return all(checks.values()) if checks else None


def fly_experiment(options: CampaignOptions, index: int, slot: int, attempt: int) -> FlightResult:
    from harness.demo.orchestrator import ProcessDied
    from harness.demo.paper003_cli import run_paper003

    folder = flight_folder(options.out_dir, index)
    if attempt > 1:
        kill_leftovers(folder / "logs")
        (folder / "logs" / "pids").unlink(missing_ok=True)
    draws = draw_experiment_flight(options.seed, index, options.experiment)
    files = write_sitl_files(draws.scenario, draws.vehicle, draws.sitl, draws.record, folder)
    offset = flight_ports(options.port_offset, slot)
    t0 = time.monotonic()
    result = FlightResult(index, "ok", attempt, str(folder), draws=draws.record, port_offset=offset,
                          node=os.uname().nodename, t_start_unix_s=time.time(), code_version=code_version())
    try:
        result.report = run_paper003(draws.experiment.paper003, folder, port_offset=offset, plots=False,
                                     scenario=str(files.scenario), sitl_config=str(files.sitl),
                                     journal=options.journal)
    except (ProcessDied, TimeoutError, RuntimeError) as exc:  # a part died, a wait ran out, airborne too late
        result.status, result.failure = "failed", f"{type(exc).__name__}: {exc}"
        report_path = Path(folder) / "paper003.json"
        if report_path.is_file():
            result.report = json.loads(report_path.read_text())
    result.wall_s = time.monotonic() - t0
    result.t_end_unix_s = time.time()
    ok = verdict(result.report)
    result.headline = {True: "PASS", False: "FAIL", None: "no figures"}[ok]
    (folder / "result.json").write_text(json.dumps(asdict(result), indent=2, default=float) + "\n")
    return result

"""Issue 31: ``quadlink falsify`` flies through the campaign runner. A 4-flight search at ``--parallel 2`` (2 flights,
then ``--resume`` to 4), the study on disk, the report, one replay bit for bit, and an export.

Short flights (20 s sessions: take-off, a 2 s push, landing) keep it CI-sized; what is checked is the plumbing, with
each trial's clearance matched against its own truth log and its own arena.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import optuna
import pytest
from click.testing import CliRunner

from harness.campaign.safety import envelope, read_truth
from harness.demo.cli import compare_reports, replay_flight
from harness.falsify.cli import command
from harness.falsify.export import materialize
from harness.falsify.search import STUDY_NAME, storage_url
from harness.falsify.space import params_from_dict
from harness.ports import free_port_offset
from quadlink.config import load_config
from quadlink.mavlink.tlog import read_tlog
from sim_sitl.config import ScenarioConfig

pytestmark = pytest.mark.sitl

# the falsification's port lane (offsets 4000-4900), one slice per test process
OFFSET = free_port_offset(slots=2)   # harness.ports: free now, reserved for this session


def _payloads(tlog: Path) -> list[bytes]:
    return [bytes(m.get_msgbuf()) for _, m in read_tlog(tlog)]


def test_four_flight_search_resume_report_replay_export(tmp_path: Path) -> None:
    out = tmp_path / "study"
    runner = CliRunner()
    first = runner.invoke(command, ["--budget", "2", "--parallel", "2", "--seed", "5", "--out", str(out),
                                    "--duration", "20", "--startup-trials", "2", "--port-offset", str(OFFSET)])
    assert first.exit_code == 0, (first.output, first.exception)
    second = runner.invoke(command, ["--resume", str(out), "--budget", "4", "--parallel", "2",
                                     "--port-offset", str(OFFSET)])
    assert second.exit_code == 0, (second.output, second.exception)
    assert "Falsification report" in second.output and "re-fly: quadlink demo --replay" in second.output

    # the study on disk: four judged flights, each a point of the space, each judged from its own truth
    study = optuna.load_study(study_name=STUDY_NAME, storage=storage_url(out))
    done = [t for t in study.trials if t.state == optuna.trial.TrialState.COMPLETE]
    assert len(study.trials) == 4 and len(done) == 4, [(t.number, t.state, t.user_attrs) for t in study.trials]
    assert study.user_attrs["duration_s"] == 20.0 and study.user_attrs["sampler"] == "tpe"
    for t in done:
        params_from_dict(dict(t.params))
        folder = out / f"trial-{t.number:04d}"
        scenario = load_config(folder / "scenario.yaml", ScenarioConfig)
        assert envelope(read_truth(folder / "truth.tlog"), scenario).min_nonfloor_m == pytest.approx(t.value)
        assert 0.0 < t.value < 5.0 and t.user_attrs["status"] == "ok"
        assert t.user_attrs["envelope"]["max_height_m"] > 0.6  # every flight took off
    # the report
    report = json.loads((out / "falsify.json").read_text())
    assert report["flights"] == 4 and report["best_clearance_m"] == pytest.approx(min(t.value for t in done))
    assert all(b is not None for b in report["convergence_m"])
    assert report["convergence_m"] == sorted(report["convergence_m"], reverse=True)
    for png in ("convergence.png", "distribution.png"):
        assert (out / png).stat().st_size > 5000
    # one replay, bit for bit: the lowest flight, re-flown by the command the report prints
    lowest = report["lowest"][0]
    assert lowest["replay"] == f"quadlink demo --replay {out / 'trial-{:04d}'.format(lowest['trial'])}"
    folder = Path(lowest["folder"])
    replayed, replay_dir = replay_flight(folder, port_offset=OFFSET, progress_every_s=30.0)
    original = json.loads((folder / "report.json").read_text())
    assert compare_reports(original, replayed) == []
    for log in ("truth.tlog", "companion.tlog", "bridge.tlog"):
        a, b = _payloads(folder / log), _payloads(replay_dir / log)
        assert len(a) > 1000 and a == b, log
    # an export: the same files as the flown trial, with sitl.yaml made portable
    dest = tmp_path / "regression"
    exported = runner.invoke(command, ["export", str(out), "--trial", str(lowest["trial"]), str(dest)])
    assert exported.exit_code == 0, (exported.output, exported.exception)
    finding = json.loads((dest / "finding.json").read_text())
    assert finding["files_equal_flown"] == ["companion.yaml", "operator.yaml", "scenario.yaml", "vehicle.yaml"]
    assert math.isclose(finding["clearance_m"], lowest["clearance_m"])
    files, companion, _ = materialize(dest, tmp_path / "materialized")
    assert companion.read_bytes() == (folder / "companion.yaml").read_bytes()
    assert files.scenario.read_bytes() == (folder / "scenario.yaml").read_bytes()


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return Path(f"/proc/{pid}/cmdline").is_file() and b"quadlink" in Path(f"/proc/{pid}/cmdline").read_bytes()


@pytest.mark.slow
def test_ctrl_c_keeps_the_study_resumable(tmp_path: Path) -> None:
    """Ctrl-C with two flights in the air: exit status 130, no part left running, the two trials recorded as
    interrupted and their points enqueued; --resume flies an interrupted point first."""
    out = tmp_path / "study"
    cmd = [sys.executable, "-m", "quadlink.cli", "falsify", "--budget", "3", "--parallel", "2", "--seed", "9",
           "--out", str(out), "--duration", "20", "--port-offset", str(OFFSET)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.monotonic() + 240.0
    pid_files = [out / f"trial-{n:04d}" / "logs" / "pids" for n in (0, 1)]
    while not all(p.is_file() and len(p.read_text().split()) >= 8 for p in pid_files):  # all four parts started
        assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()[0] if proc.poll() else ""
        time.sleep(0.5)
    time.sleep(3.0)
    parts = [int(line.split()[0]) for p in pid_files for line in p.read_text().splitlines() if line.strip()]
    proc.send_signal(signal.SIGINT)
    output, _ = proc.communicate(timeout=120.0)
    assert proc.returncode == 130, output
    assert "--resume" in output
    assert not [pid for pid in parts if _alive(pid)]
    study = optuna.load_study(study_name=STUDY_NAME, storage=storage_url(out))
    assert sorted(study.user_attrs["interrupted_trials"]) == [0, 1]
    waiting = study.get_trials(states=(optuna.trial.TrialState.WAITING,))
    assert sorted(t.user_attrs["requeued_from"] for t in waiting) == [0, 1]
    resumed = CliRunner().invoke(command, ["--resume", str(out), "--budget", "1", "--port-offset", str(OFFSET)])
    assert resumed.exit_code == 0, (resumed.output, resumed.exception)
    study = optuna.load_study(study_name=STUDY_NAME, storage=storage_url(out))
    done = study.get_trials(states=(optuna.trial.TrialState.COMPLETE,))
    assert len(done) == 1 and done[0].user_attrs["requeued_from"] in (0, 1)
    assert done[0].params == study.trials[done[0].user_attrs["requeued_from"]].params

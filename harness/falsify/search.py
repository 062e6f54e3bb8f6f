"""The search (issue 31): Optuna's ask/tell over the campaign runner's Ray pool, the study on disk.

Each trial is one flight: :func:`harness.falsify.space.suggest` asks the trial for a point, the point's files are
written and flown by the campaign runner (:class:`harness.campaign.runner.FlightPool`, one Ray task per flight,
``parallel`` port slots), and the flight's clearance (:func:`harness.falsify.objective.clearance_m`) is told back.
Up to ``parallel`` trials are asked before any is told; TPE's constant liar keeps them apart.

The study lives in ``DIR/study.db`` (Optuna's RDB storage on sqlite), so ``--resume DIR`` continues it, and what
the search was started with (seed, sampler, duration, ports) in ``DIR/search.json``. A trial is:

* COMPLETE with the clearance as its value, when the flight left a truth log (a flight in which a part of the
  stack died is COMPLETE too, with what it flew, and marked ``status=failed``: a finding, never dropped);
* FAIL with ``status`` failed or lost when there was nothing to judge (a finding, counted in the budget);
* FAIL with ``interrupted=True`` when Ctrl-C cancelled it: not counted, and its point is enqueued again, so
  ``--resume`` flies it first.
"""

from __future__ import annotations

import json
import logging
import math
import sys
import time
import warnings
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from harness.campaign.runner import FlightPool, FlightResult, PoolOptions, flight_ports, fly_files, progress_line
from harness.falsify.objective import judge
from harness.falsify.space import FlightParams, build_flight, suggest, write_flight
from quadlink.errors import ConfigError

log = logging.getLogger("harness.falsify")

STUDY_NAME = "falsify"
SAMPLERS = ("tpe", "cmaes", "random")
DEFAULT_PORT_OFFSET = 4000  # slot k flies on the demo's ports shifted by 4000 + 25 k (campaigns use 3000 + 25 k)


@dataclass(frozen=True)
class SearchOptions:
    budget: int  # flights to judge (interrupted ones do not count)
    seed: int
    out_dir: Path
    parallel: int = 1
    address: str | None = None
    sampler: str = "tpe"
    startup_trials: int = 10  # TPE/CMA-ES: random exploration before the model
    duration_s: float = 30.0  # simulated seconds of the operator's session (take-off 10 s, landing 8 s)
    port_offset: int = DEFAULT_PORT_OFFSET
    cpus_per_flight: float = 1.0


def trial_folder(out_dir: Path, number: int) -> Path:
    return out_dir / f"trial-{number:04d}"


def storage_url(out_dir: Path) -> str:
    return f"sqlite:///{(out_dir / 'study.db').resolve()}"


@dataclass(frozen=True)
class TrialFlight:
    """One trial's flight, for the campaign runner's pool (it travels to a Ray worker)."""

    params: FlightParams
    number: int
    out_dir: Path
    duration_s: float
    port_offset: int

    @property
    def index(self) -> int:
        return self.number

    @property
    def folder(self) -> Path:
        return trial_folder(self.out_dir, self.number)

    def fly(self, slot: int, attempt: int) -> FlightResult:
        from harness.demo.orchestrator import kill_leftovers

        if attempt > 1:
            kill_leftovers(self.folder / "logs")
            (self.folder / "logs" / "pids").unlink(missing_ok=True)
        flight = build_flight(self.params, self.duration_s, name=f"falsify-{self.number:04d}")
        files, companion = write_flight(flight, self.folder)
        return fly_files(files, self.folder, self.number, flight.operator, self.duration_s,
                         flight_ports(self.port_offset, slot), attempt, flight.record, companion_config=companion)


def make_sampler(name: str, seed: int, startup_trials: int) -> Any:
    import optuna

    if name == "tpe":
        return optuna.samplers.TPESampler(n_startup_trials=startup_trials, seed=seed, multivariate=True,
                                          constant_liar=True)
    if name == "random":
        return optuna.samplers.RandomSampler(seed=seed)
    if name == "cmaes":
        try:
            import cmaes  # noqa: F401 - Optuna's CMA-ES needs it
        except ImportError as exc:
            raise ConfigError("--sampler cmaes needs the 'cmaes' package (pip install cmaes)") from exc
        # CMA-ES models the numeric parameters; the categorical ones (kind, operator, direction, pan-scan) are
        # drawn by its independent sampler, which is random
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
            return optuna.samplers.CmaEsSampler(seed=seed, n_startup_trials=startup_trials,
                                                independent_sampler=optuna.samplers.RandomSampler(seed=seed),
                                                warn_independent_sampling=False)
    raise ConfigError(f"unknown sampler {name!r} (one of {', '.join(SAMPLERS)})")


def open_study(options: SearchOptions, resume: bool) -> Any:
    """Create the study in ``out_dir`` (refused if one is there) or load it (``resume``: refused if none is)."""
    import optuna

    meta_path = options.out_dir / "search.json"
    if resume:
        if not meta_path.is_file():
            raise ConfigError(f"{options.out_dir}: no falsification study to resume (no search.json)")
    elif meta_path.exists():
        raise ConfigError(f"{options.out_dir}: holds a study already; continue it with --resume {options.out_dir}")
    options.out_dir.mkdir(parents=True, exist_ok=True)
    # the sampler's state is not stored: a resumed search seeds it with the number of trials so far
    study = optuna.create_study(study_name=STUDY_NAME, storage=storage_url(options.out_dir), direction="minimize",
                                load_if_exists=resume, sampler=make_sampler(options.sampler, options.seed, 1))
    n_before = len(study.trials)
    study.sampler = make_sampler(options.sampler, options.seed + n_before, max(0, options.startup_trials - n_before))
    if not resume:
        meta = {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(options).items()}
        meta_path.write_text(json.dumps(meta, indent=2) + "\n")
        for key in ("duration_s", "seed", "sampler", "startup_trials"):
            study.set_user_attr(key, meta[key])
    return study


def load_search_options(out_dir: Path, **overrides: Any) -> SearchOptions:
    """The options a study was started with (``DIR/search.json``), with ``overrides`` (budget, parallel, ...)."""
    path = out_dir / "search.json"
    if not path.is_file():
        raise ConfigError(f"{out_dir}: no falsification study (no search.json)")
    meta = json.loads(path.read_text())
    meta["address"] = None  # where to fly is the command line's choice, not the study's
    meta.update({k: v for k, v in overrides.items() if v is not None})
    meta["out_dir"] = out_dir
    return SearchOptions(**meta)


def interrupted_trials(study: Any) -> set[int]:
    """The numbers of the trials that Ctrl-C (or a killed search) interrupted (a study user attribute)."""
    return set(study.user_attrs.get("interrupted_trials", []))


def counted(trial: Any, interrupted: set[int]) -> bool:
    """Does a finished trial count in the budget (every judged or failed flight; not an interrupted one)?"""
    import optuna

    if trial.number in interrupted:
        return False
    return trial.state in (optuna.trial.TrialState.COMPLETE, optuna.trial.TrialState.FAIL)


def _requeue_stale(study: Any) -> int:
    """Trials left RUNNING by a search that was killed: FAIL them as interrupted, enqueue their points again."""
    import optuna

    stale = study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.RUNNING,))
    for t in stale:
        _interrupt(study, t.number, t.params)
    return len(stale)


def _interrupt(study: Any, number: int, params: dict[str, Any]) -> None:
    """Record trial ``number`` as interrupted (FAIL, not counted) and enqueue its point for the next run."""
    import optuna

    study.set_user_attr("interrupted_trials", sorted(interrupted_trials(study) | {number}))
    study.tell(number, state=optuna.trial.TrialState.FAIL)
    if params:
        study.enqueue_trial(params, user_attrs={"requeued_from": number}, skip_if_exists=False)


def replay_command(out_dir: Path, number: int) -> str:
    return f"quadlink demo --replay {trial_folder(out_dir, number)}"


def _tell(study: Any, trial: Any, result: FlightResult, out_dir: Path) -> float:
    import optuna

    verdict = judge(result)
    attrs = {"status": result.status, "finding": verdict.finding, "reason": verdict.reason,
             "folder": result.folder, "wall_s": result.wall_s, "failure": result.failure,
             "envelope": result.envelope, "retried": result.attempts > 1, "code_version": result.code_version,
             "replay": replay_command(out_dir, trial.number), "moved_m": verdict.moved_m}
    for key, value in attrs.items():
        trial.set_user_attr(key, _plain(value))
    if result.status == "cancelled":
        _interrupt(study, trial.number, trial.params)
    elif math.isfinite(verdict.clearance_m):
        study.tell(trial, verdict.clearance_m)
    else:
        study.tell(trial, state=optuna.trial.TrialState.FAIL)
    return verdict.clearance_m


def _plain(value: Any) -> Any:
    """JSON-safe (Optuna stores user attributes as JSON): NaN and inf as None."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value


class SearchCancelled(KeyboardInterrupt):
    """Ctrl-C: the flights in the air were cancelled and their points enqueued again; the study is resumable."""


def run_search(options: SearchOptions, resume: bool = False, echo: Callable[[str], None] | None = None) -> Any:
    """Run (or continue) the search until ``budget`` flights are judged; returns the study. Ctrl-C cancels the
    flights in the air, records them as interrupted and raises :class:`SearchCancelled`."""
    import optuna

    say = echo or (lambda s: print(s, file=sys.stderr, end="" if s.startswith("\r") else "\n", flush=True))
    study = open_study(options, resume)
    stale = _requeue_stale(study)
    if stale:
        log.warning("%d trials of a killed search re-enqueued", stale)
    interrupted = interrupted_trials(study)
    done0 = sum(1 for t in study.get_trials(deepcopy=False) if counted(t, interrupted))
    pool = FlightPool(PoolOptions(options.out_dir, options.parallel, options.address, options.cpus_per_flight))
    running: dict[int, Any] = {}
    done, failed = done0, 0
    best = min((t.value for t in study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.COMPLETE,))),
               default=math.inf)
    t0 = time.monotonic()
    last: FlightResult | None = None
    tty = sys.stderr.isatty()
    log.info("study %s: %d flights judged, budget %d, sampler %s, %d in parallel", storage_url(options.out_dir),
             done0, options.budget, options.sampler, options.parallel)
    try:
        while done + len(running) < options.budget or running:
            while pool.free_slots and done + len(running) < options.budget:
                trial = study.ask()
                params = suggest(trial)
                pool.submit(TrialFlight(params, trial.number, options.out_dir, options.duration_s,
                                        options.port_offset))
                running[trial.number] = trial
            ready = pool.wait(2.0)
            for job, result in ready:
                trial = running.pop(job.index)
                clearance = _tell(study, trial, result, options.out_dir)
                if result.status == "cancelled":
                    continue
                done += 1
                failed += result.status != "ok"
                best = min(best, clearance) if math.isfinite(clearance) else best
                last = result
            line = progress_line(done - done0, options.budget - done0, len(running), pool.retried, failed,
                                 time.monotonic() - t0, last) + f" | best {best:.3f} m"
            if tty:
                say("\r" + line + "\x1b[K")
            elif ready:
                say(line)
    except KeyboardInterrupt:
        say(f"\ncancelling {len(running)} flights in the air ...")
        for job in pool.cancel():
            trial = running.pop(job.index)
            _interrupt(study, trial.number, trial.params)
        raise SearchCancelled(f"search cancelled; continue it with --resume {options.out_dir}") from None
    finally:
        pool.shutdown()
    if tty:
        say("\n")
    return study

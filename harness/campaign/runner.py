"""Run a campaign's flights on Ray (issue 15): one Ray task per flight, results streamed as they finish.

A flight (:func:`fly`) is the demo's orchestration (:func:`harness.demo.cli.run_demo`): the SITL in
lock-step, the bridge, the companion and the operator as separate processes over their real links, on the
ports of one per-flight block (:func:`flight_ports`); or, with ``experiment`` set, one of paper 003's
experiments (:func:`harness.campaign.experiment_flight.fly_experiment`) on the same ports. The task
reserves ``cpus_per_flight`` CPUs (``num_cpus``); at most ``parallel`` flights are in the air at once, each
on its own port slot.

How the code reaches the workers:

* embedded local Ray (the default, ``ray.init(num_cpus=<this machine's cores>)``): the workers are this
  machine's processes, started with this interpreter and this environment (``PYTHONPATH`` gets the
  repository root), so they import the same checkout;
* a cluster (``--address ray://HOST:10001`` or ``HOST:6379``): the repository is shipped as the job's
  ``runtime_env`` ``working_dir`` (code and ``configs/``, without tlogs and virtualenvs), and each node
  needs the dependencies (``pip install -e .`` of the same version, or the same container image). Flight
  folders are written on the node that flies them: give ``--out`` a shared filesystem to keep the tlogs;
  the reports and draws come back to the driver in any case.

A flight whose worker dies (``WorkerCrashedError``, a lost node) is retried once on the same port slot,
after its leftover processes are killed (``logs/pids``), and reported as retried. A part of the stack that
dies is a failed flight, not retried: it is a finding.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Protocol

from harness.campaign.draws import FlightFiles, Starvation, StarvationRange, draw_flight, write_flight_files
from harness.campaign.safety import Envelope, envelope, read_truth, truth_of_flight
from harness.cpu_share import BusyNeighbour, CpuShare
from harness.demo.cli import ROOM_HEIGHT_ENTRY_ERROR_M
from harness.demo.orchestrator import kill_leftovers
from harness.ports import PORT_SLOT_STRIDE
from quadlink import REPO_ROOT
from quadlink.config import load_config
from quadlink.errors import LinkError
from sim_sitl.config import ScenarioConfig

log = logging.getLogger("harness.campaign")

RAY_START_ATTEMPTS = 3
#: simulated time a flight may take beyond its session: in the plain lock-step (--no-deterministic) the SITL's
#: clock runs in real time until its lock-step clients connect, so the operator joins some seconds of simulated
#: time after t = 0 (more on a loaded machine); in the deterministic one it joins at t = 0. A flight ends when its
#: operator's session ends (and the vehicle has landed): this is only the bound
STARTUP_ALLOWANCE_S = 45.0
#: a session that ends with the vehicle still in the air (a refused landing, the operator gone) flies on this long
#: without its operator, until the companion's failsafe has landed it (10 s without a command, up to 15 s to move
#: clear of an object below, the descent): the envelope is that of a landing, not of a teardown in the air (the
#: bridge then landed wherever the vehicle was, on top of the object the companion had refused to land on)
LANDING_SETTLE_S = 45.0


class CampaignCancelled(KeyboardInterrupt):
    """Ctrl-C during a campaign: carries the flights that finished before it."""

    def __init__(self, results: list[FlightResult]) -> None:
        super().__init__(f"campaign cancelled after {len(results)} flights")
        self.results = results


def load_results(out_dir: Path) -> list[FlightResult]:
    """The finished flights of a campaign folder (each ``flight-NNNN/result.json``)."""
    out = []
    for path in sorted(out_dir.glob("flight-*/result.json")):
        data = json.loads(path.read_text())
        out.append(FlightResult(**{k: v for k, v in data.items() if k in FlightResult.__dataclass_fields__}))
    return out


@dataclass(frozen=True)
class CampaignOptions:
    flights: int
    seed: int
    out_dir: Path
    duration_s: float = 60.0
    parallel: int = 1
    address: str | None = None
    cpus_per_flight: float = 1.0
    port_offset: int = 3000  # slot k flies on the demo's ports shifted by port_offset + 25 k
    offboard_share: float = 0.0  # share of flights flown by the offboard client instead of MANUAL_CONTROL
    fixed_share: float = 0.2  # share of flights in paper-arena or office
    first_index: int = 0
    view: bool = False  # the operator image view in each flight (costs CPU, changes nothing in the flight)
    experiment: str = "teleop"  # or one of harness.campaign.experiments.EXPERIMENTS (paper003-oval, -hover)
    deterministic: bool = True  # the deterministic lock-step (quadlink.lockstep): a flight re-flies bit for bit
    realtime: bool = False  # every part on the wall clock, as on the vehicle (not deterministic; what starving needs)
    starve: StarvationRange | None = None  # real time only: draw each flight's CPU share and busy neighbour (issue 30)
    journal: bool = False  # each flight's companion journals its inputs (companion.qljn: quadlink replay-companion)

    def __post_init__(self) -> None:
        if self.starve is not None and not self.realtime:
            raise ValueError("a starved CPU only means something in real time: the lock-step waits for a slow part")


@dataclass(frozen=True)
class PoolOptions:
    """Where and how wide a :class:`FlightPool` flies: ``parallel`` flights at once, each on its own port slot."""

    out_dir: Path
    parallel: int = 1
    address: str | None = None  # a Ray cluster (ray://HOST:10001 or HOST:6379); None: an embedded local Ray
    cpus_per_flight: float = 1.0


@dataclass
class FlightResult:
    index: int
    status: str  # "ok" | "failed" | "lost" (worker died twice) | "cancelled"
    attempts: int
    folder: str
    report: dict[str, Any] = field(default_factory=dict)
    envelope: dict[str, Any] = field(default_factory=dict)
    draws: dict[str, Any] = field(default_factory=dict)
    failure: str | None = None
    wall_s: float = math.nan
    port_offset: int = 0
    node: str = ""
    t_start_unix_s: float = math.nan
    t_end_unix_s: float = math.nan
    headline: str = ""  # the flight's key figure for the progress line
    code_version: str = ""  # git describe of the checkout that flew it


def code_version() -> str:
    """``git describe --always --dirty`` of the checkout that runs ("unknown" outside git, e.g. a Ray cluster's
    shipped working_dir)."""
    try:
        out = subprocess.run(["git", "describe", "--always", "--dirty"], cwd=REPO_ROOT, capture_output=True,
                             text=True, timeout=10.0, check=True)
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return out.stdout.strip() or "unknown"


def flight_ports(port_offset: int, slot: int) -> int:
    """The demo's port offset for a port slot."""
    return port_offset + PORT_SLOT_STRIDE * slot


def flight_folder(out_dir: Path, index: int) -> Path:
    return out_dir / f"flight-{index:04d}"


def fly(options: CampaignOptions, index: int, slot: int, attempt: int,
        should_stop: Callable[[], bool] | None = None) -> FlightResult:
    """Draw, write and fly flight ``index`` on port slot ``slot`` (what a Ray task runs)."""
    if options.experiment != "teleop":
        from harness.campaign.experiment_flight import fly_experiment

        return fly_experiment(options, index, slot, attempt)
    folder = flight_folder(options.out_dir, index)
    if attempt > 1:
        kill_leftovers(folder / "logs")
        (folder / "logs" / "pids").unlink(missing_ok=True)
    draws = draw_flight(options.seed, index, options.duration_s, options.offboard_share, options.fixed_share,
                        options.starve)
    files = write_flight_files(draws, folder)
    return fly_files(files, folder, index, draws.session.kind, options.duration_s,
                     flight_ports(options.port_offset, slot), attempt, draws.record, should_stop=should_stop,
                     view=options.view, deterministic=options.deterministic,
                     room_height_error_m=draws.room_height_error_m, realtime=options.realtime,
                     starvation=draws.starvation, journal=options.journal)


def fly_files(files: FlightFiles, folder: Path, index: int, operator: str, duration_s: float, port_offset: int,
              attempt: int, record: dict[str, Any], should_stop: Callable[[], bool] | None = None,
              view: bool = False, deterministic: bool = True, companion_config: Path | None = None,
              room_height_error_m: float | None = ROOM_HEIGHT_ENTRY_ERROR_M, realtime: bool = False,
              starvation: Starvation | None = None, journal: bool = False) -> FlightResult:
    """Fly the flight whose files are written in ``folder`` (:class:`FlightFiles`: scenario, operator script or
    plan, SITL config) on the demo's ports shifted by ``port_offset``, judge it and write ``result.json``.
    ``companion_config``: the companion's YAML (default: the nominal one with the operator's entry of the room's
    height, the truth + ``room_height_error_m``; None: not entered). ``realtime``: every part on the wall clock
    (not deterministic). ``starvation``: the bridge and the companion in a CPU share, busy processes beside them
    (real time only); the share's figures go into the report as ``cpu_share``. ``journal``: the companion journals
    its inputs to ``companion.qljn`` in ``folder``."""
    from harness.demo.cli import run_demo
    from harness.demo.orchestrator import ProcessDied

    t0 = time.monotonic()
    result = FlightResult(index, "ok", attempt, str(folder), draws=record, port_offset=port_offset,
                          node=os.uname().nodename, t_start_unix_s=time.time(), code_version=code_version())
    scenario = load_config(files.scenario, ScenarioConfig)
    envelopes: list[Envelope] = []
    if starvation is not None and not realtime:
        raise ValueError("a starved flight flies in real time")
    try:
        with contextlib.ExitStack() as held:
            share = held.enter_context(CpuShare(starvation.cores)) if starvation is not None else None
            if starvation is not None and starvation.busy_neighbours:
                held.enter_context(BusyNeighbour(starvation.busy_neighbours))
            report = run_demo(str(files.scenario), duration_s + STARTUP_ALLOWANCE_S, folder, files.operator,
                              lockstep=not realtime,
                              port_offset=port_offset, progress_every_s=30.0, sitl_config=str(files.sitl),
                              operator=operator, should_stop=should_stop, view=view,
                              plots=False, on_flight=lambda f: envelopes.append(envelope(truth_of_flight(f), scenario)),
                              settle_s=LANDING_SETTLE_S, deterministic=deterministic and not view and not realtime,
                              companion_config=companion_config, room_height_error_m=room_height_error_m,
                              cpu_share=share, journal=journal)
            if share is not None and starvation is not None:
                report["cpu_share"] = {"cores": starvation.cores, "busy_neighbours": starvation.busy_neighbours,
                                       "cgroup_version": share.version, "throttled_s": share.throttled_s()}
        result.report = report
        if report.get("interrupted"):
            result.status = "cancelled"
    except ProcessDied as exc:
        result.status, result.failure = "failed", str(exc)
        report_path = folder / "report.json"
        if report_path.is_file():
            result.report = json.loads(report_path.read_text())
    result.wall_s = time.monotonic() - t0
    result.t_end_unix_s = time.time()
    truth = folder / "truth.tlog"
    if envelopes:
        result.envelope = asdict(envelopes[0])
    elif truth.is_file():  # a part died: the demo wrote no report, the truth log is still there
        result.envelope = asdict(envelope(read_truth(truth), scenario))
    result.headline = f"min d {result.envelope.get('min_nonfloor_m', math.nan):.2f} m"
    (folder / "result.json").write_text(json.dumps(asdict(result), indent=2, default=float) + "\n")
    return result


class FlightJob(Protocol):
    """One flight for :class:`FlightPool`: picklable (it travels to a Ray worker), flown by :meth:`fly`."""

    @property
    def index(self) -> int: ...

    @property
    def folder(self) -> Path: ...

    def fly(self, slot: int, attempt: int) -> FlightResult: ...


@dataclass(frozen=True)
class CampaignFlight:
    """Flight ``index`` of a campaign (its draws come from the campaign's seed)."""

    options: CampaignOptions
    index: int

    @property
    def folder(self) -> Path:
        return flight_folder(self.options.out_dir, self.index)

    def fly(self, slot: int, attempt: int) -> FlightResult:
        return fly(self.options, self.index, slot, attempt)


def _ray_task(job: FlightJob, slot: int, attempt: int) -> FlightResult:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname).1s %(name)s: %(message)s")
    return job.fly(slot, attempt)


def _init_ray(options: PoolOptions | CampaignOptions) -> Any:
    import ray

    if options.address:
        runtime_env = {"working_dir": str(REPO_ROOT),
                       "excludes": [".git", ".venv", "*.tlog", "*.qlcf", "*.png", "flight-report*", "campaign-*",
                                    "__pycache__", str(options.out_dir)]}
        try:
            ray.init(address=options.address, runtime_env=runtime_env, log_to_driver=False)
        except ConnectionError as exc:   # no cluster there, or one that wants a token: one line, not a traceback
            raise LinkError(f"Ray cluster at {options.address}: {exc}. A cluster with token authentication (this "
                            "Ray's default) needs its token on this machine (Ray's token-auth docs), or "
                            "RAY_AUTH_MODE=disabled on the cluster and here, on a trusted network") from None
    else:
        # workers inherit this environment: make sure they import this checkout
        paths = [str(REPO_ROOT)] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]
        os.environ["PYTHONPATH"] = os.pathsep.join(dict.fromkeys(paths))
        for attempt in range(1, RAY_START_ATTEMPTS + 1):
            try:
                ray.init(num_cpus=os.cpu_count() or 1, include_dashboard=False, log_to_driver=False,
                         object_store_memory=200 * 1024 * 1024, configure_logging=False)
                break
            except Exception as exc:  # noqa: BLE001 - Ray raises a bare Exception when its node starts too slowly
                if "timed out during startup" not in str(exc) or attempt == RAY_START_ATTEMPTS:
                    raise
                # Ray waits a fixed 30 s for its raylet; on a loaded machine that is not always enough
                log.warning("local Ray did not start in time (attempt %d of %d); retrying", attempt,
                            RAY_START_ATTEMPTS)
                ray.shutdown()
    return ray


def _fmt_s(s: float) -> str:
    if not math.isfinite(s):
        return "--:--"
    s = int(s)
    return f"{s // 3600:d}:{s // 60 % 60:02d}:{s % 60:02d}" if s >= 3600 else f"{s // 60:02d}:{s % 60:02d}"


def progress_line(done: int, total: int, running: int, retried: int, failed: int, elapsed_s: float,
                  last: FlightResult | None = None, width: int = 24) -> str:
    """``[#######.....] 7/20 running 2 retried 0 failed 1 elapsed 05:10 ETA 09:36 | last ...`` (pure)."""
    filled = int(width * done / total) if total else width
    eta = elapsed_s / done * (total - done) if done else math.nan
    text = (f"[{'#' * filled}{'.' * (width - filled)}] {done}/{total} running {running} retried {retried} "
            f"failed {failed} elapsed {_fmt_s(elapsed_s)} ETA {_fmt_s(eta)}")
    if last is not None:
        text += f" | flight {last.index} {last.status} {last.headline} ({last.wall_s:.0f} s)"
    return text


class FlightPool:
    """Flights in the air as Ray tasks (one per port slot), results as they land.

    :meth:`submit` a :class:`FlightJob` when :attr:`free_slots` is not zero, :meth:`wait` for the next results.
    A job whose worker dies is flown again once on the same slot (after its leftover parts are killed) and marked
    retried; twice: "lost". A bug in the flight code comes back as a "failed" result. :meth:`cancel` interrupts
    the flights in the air (each stops its parts in order), waits up to 20 s and kills leftovers by pid. The
    campaign (:func:`run_campaign`) and the falsification search (``harness.falsify``) both fly through it.
    """

    def __init__(self, options: PoolOptions) -> None:
        self.options = options
        self.ray = _init_ray(options)
        from ray.exceptions import NodeDiedError, WorkerCrashedError

        try:
            from ray.exceptions import LocalRayletDiedError
            self._lost: tuple[type[BaseException], ...] = (WorkerCrashedError, NodeDiedError, LocalRayletDiedError)
        except ImportError:  # older Ray
            self._lost = (WorkerCrashedError, NodeDiedError)
        self._task = self.ray.remote(num_cpus=options.cpus_per_flight, max_retries=0)(_ray_task)
        self._slots = list(range(max(1, options.parallel)))
        self.pending: dict[Any, tuple[FlightJob, int, int]] = {}  # ref -> (job, slot, attempt)
        self.retried = 0
        options.out_dir.mkdir(parents=True, exist_ok=True)

    @property
    def free_slots(self) -> int:
        return len(self._slots)

    @property
    def running(self) -> int:
        return len(self.pending)

    def submit(self, job: FlightJob) -> None:
        if not self._slots:
            raise RuntimeError("no free port slot: wait for a flight to land first")
        self._submit(job, self._slots.pop(0), 1)

    def _submit(self, job: FlightJob, slot: int, attempt: int) -> None:
        self.pending[self._task.remote(job, slot, attempt)] = (job, slot, attempt)

    def wait(self, timeout_s: float = 2.0) -> list[tuple[FlightJob, FlightResult]]:
        """The flights that landed within ``timeout_s`` (possibly none)."""
        if not self.pending:
            return []
        ready, _ = self.ray.wait(list(self.pending), num_returns=1, timeout=timeout_s)
        out = []
        for ref in ready:
            job, slot, attempt = self.pending.pop(ref)
            try:
                result = self.ray.get(ref)
            except self._lost as exc:
                if attempt == 1:
                    self.retried += 1
                    log.warning("flight %d: worker lost (%s); retrying once", job.index, type(exc).__name__)
                    self._submit(job, slot, 2)
                    continue
                result = FlightResult(job.index, "lost", attempt, str(job.folder), failure=f"worker lost twice: {exc}")
                kill_leftovers(job.folder / "logs")
            except self.ray.exceptions.RayTaskError as exc:  # a bug in the flight code: report, go on
                result = FlightResult(job.index, "failed", attempt, str(job.folder),
                                      failure=str(exc).splitlines()[-1])
            self._slots.append(slot)
            out.append((job, result))
        return out

    def cancel(self) -> list[FlightJob]:
        """Interrupt the flights in the air; returns their jobs."""
        from ray.exceptions import TaskCancelledError

        jobs = [job for job, _, _ in self.pending.values()]
        _cancel(self.ray, self.pending, TaskCancelledError)
        self.pending.clear()
        return jobs

    def shutdown(self) -> None:
        self.ray.shutdown()


def run_campaign(options: CampaignOptions, on_result: Callable[[FlightResult], None] | None = None,
                 echo: Callable[[str], None] = print) -> list[FlightResult]:
    """Fly the campaign on Ray; ``on_result`` sees each flight as it finishes. Ctrl-C cancels cleanly."""
    pool = FlightPool(PoolOptions(options.out_dir, options.parallel, options.address, options.cpus_per_flight))
    queue = list(range(options.first_index, options.first_index + options.flights))
    results: list[FlightResult] = []
    failed = 0
    t0 = time.monotonic()
    last: FlightResult | None = None
    tty = sys.stdout.isatty()
    try:
        while queue or pool.running:
            while queue and pool.free_slots:
                pool.submit(CampaignFlight(options, queue.pop(0)))
            ready = pool.wait(2.0)
            for _, result in ready:
                if result.status != "ok":
                    failed += 1
                results.append(result)
                last = result
                if on_result is not None:
                    on_result(result)
            line = progress_line(len(results), options.flights, pool.running, pool.retried, failed,
                                 time.monotonic() - t0, last)
            if tty:
                echo("\r" + line + "\x1b[K")
            elif ready:
                echo(line)
    except KeyboardInterrupt:
        echo(f"\ncancelling {pool.running} flights in the air ...")
        pool.cancel()
        raise CampaignCancelled(sorted(results, key=lambda r: r.index)) from None
    finally:
        pool.shutdown()
    if tty:
        echo("\n")
    return sorted(results, key=lambda r: r.index)


def _cancel(ray: Any, pending: dict[Any, tuple[FlightJob, int, int]], cancelled: type[BaseException]) -> None:
    """Interrupt the running flights (their stacks stop their parts), then kill whatever is left by pid."""
    for ref in pending:
        ray.cancel(ref, force=False)  # KeyboardInterrupt in the task: run_demo stops its parts in order
    deadline = time.monotonic() + 20.0
    refs = list(pending)
    while refs and time.monotonic() < deadline:
        ready, refs = ray.wait(refs, num_returns=len(refs), timeout=1.0)
    for job, _, _ in pending.values():
        killed = kill_leftovers(job.folder / "logs")
        if killed:
            log.warning("flight %d: killed leftover parts %s", job.index, killed)

"""Run the stack's processes together: start in order, watch, stop cleanly (issue 8).

Each part runs as its own ``quadlink`` subprocess over the real links, its output in
``DIR/logs/NAME.log``. If any part dies, everything stops and the reason is reported; Ctrl-C stops
everything in reverse order (SIGINT, then SIGTERM, then SIGKILL after bounded waits).
"""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import psutil

log = logging.getLogger(__name__)

PIDS_FILE = "pids"  # in the log folder: "PID NAME" per started part


def kill_leftovers(log_dir: Path) -> list[int]:
    """Kill (SIGKILL, whole process group) the parts listed in ``log_dir/pids`` that still run.

    For a supervisor after the process that ran the :class:`Stack` died without stopping it. A pid is killed
    only if it still runs ``quadlink`` code (a recycled pid belongs to someone else). Returns the pids killed.
    """
    path = log_dir / PIDS_FILE
    killed: list[int] = []
    if not path.is_file():
        return killed
    for line in path.read_text().splitlines():
        try:
            pid = int(line.split()[0])
            proc = psutil.Process(pid)
            if not any("quadlink" in part for part in proc.cmdline()):
                continue
            os.killpg(pid, signal.SIGKILL)
            killed.append(pid)
        except (ValueError, IndexError, psutil.NoSuchProcess, psutil.AccessDenied, psutil.ZombieProcess,
                ProcessLookupError, PermissionError):
            continue
    return killed


@dataclass(frozen=True)
class ProcessSpec:
    name: str
    args: tuple[str, ...]  # arguments after ``quadlink`` (or after ``python -m MODULE``)
    ready_after_s: float = 0.5  # settle time before the next part starts
    env: dict[str, str] = field(default_factory=dict)
    module: str = "quadlink.cli"  # a part that is not a quadlink subcommand (the campaign's offboard client)


@dataclass
class Running:
    spec: ProcessSpec
    popen: subprocess.Popen[bytes]
    log_path: Path
    cpu_s: float = 0.0
    cpu_sampled_at_s: float = float("-inf")   # monotonic time of the last CPU sample


class ProcessDied(RuntimeError):
    """A part of the flight ended it: ``name`` exited with ``returncode`` (``tail``: the end of its log), or
    ``message`` says what else did."""

    def __init__(self, name: str, returncode: int, tail: str, message: str | None = None) -> None:
        super().__init__(message or f"{name} exited with status {returncode}: {tail}")
        self.name = name
        self.returncode = returncode


class JudgementVoid(ProcessDied):
    """The flight ran, but what judges it cannot be trusted (another vehicle's ground truth in its track)."""

    def __init__(self, why: str) -> None:
        super().__init__("judge", 0, "", message=why)


def _die_with_parent() -> Callable[[], None] | None:
    """On Linux, a part gets SIGTERM when the process that started it dies, however it dies: a runner killed by
    SIGTERM or SIGKILL (no ``finally`` runs) left a bridge and a companion flying on, on the same ports as the next
    run. Only from the main thread: the signal follows the thread that forked."""
    if not sys.platform.startswith("linux") or threading.current_thread() is not threading.main_thread():
        return None
    import ctypes

    libc = ctypes.CDLL(None, use_errno=True)
    parent = os.getpid()

    def set_pdeathsig() -> None:
        libc.prctl(1, signal.SIGTERM)   # PR_SET_PDEATHSIG
        if os.getppid() != parent:      # the parent died before the prctl
            os._exit(1)
    return set_pdeathsig


def _tail(path: Path, lines: int = 3) -> str:
    try:
        text = path.read_text(errors="replace").strip().splitlines()
    except OSError:
        return ""
    return " | ".join(text[-lines:])


class Stack:
    """A set of ``quadlink`` subprocesses with logs in ``log_dir``. :meth:`check` samples each part's CPU time
    at most every ``cpu_sample_period_s`` (a sample walks /proc for the part's children: sampled on every check,
    at the flight loops' 50 Hz, it took ~0.45 of a core in the harness's process); :meth:`cpu_seconds` and
    :meth:`stop` sample every part."""

    def __init__(self, log_dir: Path, cpu_sample_period_s: float = 1.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.log_dir = log_dir
        self.cpu_sample_period_s = cpu_sample_period_s
        self.clock = clock
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.running: list[Running] = []

    def start(self, spec: ProcessSpec) -> Running:
        log_path = self.log_dir / f"{spec.name}.log"
        argv = [sys.executable, "-m", spec.module, *spec.args]
        env = {**os.environ, "PYTHONUNBUFFERED": "1", **spec.env}
        with open(log_path, "wb") as out:
            popen = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                     env=env, start_new_session=True, preexec_fn=_die_with_parent())
        running = Running(spec, popen, log_path)
        self.running.append(running)
        # each part leads its own process group: a supervisor whose runner died kills them by these ids
        with open(self.log_dir / PIDS_FILE, "a") as pids:
            pids.write(f"{popen.pid} {spec.name}\n")
        log.info("started %s (pid %d): %s %s", spec.name, popen.pid,
                 "quadlink" if spec.module == "quadlink.cli" else f"python -m {spec.module}", " ".join(spec.args))
        deadline = time.monotonic() + spec.ready_after_s
        while time.monotonic() < deadline:
            self.check()
            time.sleep(0.05)
        return running

    def check(self, may_finish: frozenset[str] = frozenset()) -> set[str]:
        """Raise :class:`ProcessDied` if a part has exited, unless it is in ``may_finish`` and exited 0.

        Returns the names of the parts that finished cleanly; also samples CPU time.
        """
        finished = set()
        now = self.clock()
        for r in self.running:
            if now - r.cpu_sampled_at_s >= self.cpu_sample_period_s:
                r.cpu_sampled_at_s = now
                self._sample_cpu(r)
            code = r.popen.poll()
            if code is None:
                continue
            if code == 0 and r.spec.name in may_finish:
                finished.add(r.spec.name)
                continue
            raise ProcessDied(r.spec.name, code, _tail(r.log_path))
        return finished

    @staticmethod
    def _sample_cpu(r: Running) -> None:
        try:
            proc = psutil.Process(r.popen.pid)
            total = proc.cpu_times()
            cpu = total.user + total.system
            for child in proc.children(recursive=True):
                ct = child.cpu_times()
                cpu += ct.user + ct.system
            r.cpu_s = max(r.cpu_s, cpu)
        except (psutil.NoSuchProcess, psutil.AccessDenied, psutil.ZombieProcess):
            pass

    def cpu_seconds(self) -> dict[str, float]:
        for r in self.running:
            self._sample_cpu(r)
        return {r.spec.name: r.cpu_s for r in self.running}

    def stop(self, timeout_s: float = 8.0) -> dict[str, int | None]:
        """Stop all parts in reverse start order; returns their exit statuses."""
        for r in self.running:
            self._sample_cpu(r)
        codes: dict[str, int | None] = {}
        for r in reversed(self.running):
            codes[r.spec.name] = self._stop_one(r, timeout_s)
        return codes

    @staticmethod
    def _stop_one(r: Running, timeout_s: float) -> int | None:
        if r.popen.poll() is not None:
            return r.popen.returncode
        for sig, wait_s in ((signal.SIGINT, timeout_s), (signal.SIGTERM, 3.0), (signal.SIGKILL, 3.0)):
            try:
                os.killpg(r.popen.pid, sig)
            except ProcessLookupError:
                break
            try:
                code = r.popen.wait(timeout=wait_s)
                if sig != signal.SIGINT:
                    log.warning("%s needed %s to stop", r.spec.name, signal.Signals(sig).name)
                return code
            except subprocess.TimeoutExpired:
                continue
        return r.popen.poll()

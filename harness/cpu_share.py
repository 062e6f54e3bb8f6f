"""A starved CPU, as a companion board meets it: a CPU share for some processes and a busy neighbour (issue 30).

:class:`CpuShare` holds processes to a fraction of one core with the kernel's CFS bandwidth control — cgroup v2's
``cpu.max`` where the unified hierarchy has the cpu controller, else cgroup v1's ``cpu.cfs_quota_us`` /
``cpu.cfs_period_us`` — over a 20 ms period (so a 0.35-core share is 7 ms of CPU in every 20 ms, as an Odroid-class
budget for this machine). It needs root (or a delegated cgroup); :class:`CpuShareUnavailable` says why not.
:class:`BusyNeighbour` is a process that spins at the same priority, the other thing that runs on a real vehicle's
board. Both undo themselves on exit, Ctrl-C included.
"""

from __future__ import annotations

import contextlib
import itertools
import os
import subprocess
import sys
from pathlib import Path
from types import TracebackType

from quadlink.errors import QuadlinkError

CGROUP_ROOT = Path("/sys/fs/cgroup")
DEFAULT_PERIOD_US = 20_000
_names = itertools.count()


class CpuShareUnavailable(QuadlinkError):
    """No CFS bandwidth control to be had here (no cgroup with the cpu controller, or no permission)."""


def _v2_root(root: Path) -> Path | None:
    controllers = root / "cgroup.controllers"
    if controllers.is_file() and "cpu" in controllers.read_text().split():
        return root
    return None


def _v1_root(root: Path) -> Path | None:
    for name in ("cpu", "cpu,cpuacct"):
        d = root / name
        if (d / "cpu.cfs_quota_us").is_file():
            return d
    return None


class CpuShare:
    """``with CpuShare(0.35) as share: share.add(pid)``: the processes added share ``cores`` of CPU time."""

    def __init__(self, cores: float, period_us: int = DEFAULT_PERIOD_US, root: Path = CGROUP_ROOT) -> None:
        if not 0.01 <= cores <= 64.0:
            raise ValueError(f"a CPU share of {cores} cores is out of range (0.01..64)")
        self.cores, self.period_us = cores, int(period_us)
        self.quota_us = max(1000, round(cores * self.period_us))
        self._root = root
        self._dir: Path | None = None
        self._parent: Path | None = None
        self.version = 0
        self.pids: list[int] = []

    def __enter__(self) -> CpuShare:
        name = f"quadlink-share-{os.getpid()}-{next(_names)}"
        v2, v1 = _v2_root(self._root), _v1_root(self._root)
        try:
            if v2 is not None:
                self._parent, self._dir, self.version = v2, v2 / name, 2
                self._dir.mkdir()
                (self._dir / "cpu.max").write_text(f"{self.quota_us} {self.period_us}\n")
            elif v1 is not None:
                self._parent, self._dir, self.version = v1, v1 / name, 1
                self._dir.mkdir()
                (self._dir / "cpu.cfs_period_us").write_text(f"{self.period_us}\n")
                (self._dir / "cpu.cfs_quota_us").write_text(f"{self.quota_us}\n")
            else:
                raise CpuShareUnavailable(f"no cgroup with the cpu controller under {self._root}")
        except OSError as exc:
            self._remove()
            raise CpuShareUnavailable(f"cannot set a CPU share under {self._root}: {exc}") from exc
        return self

    def add(self, pid: int) -> None:
        """Move a process (all its threads, and the children it starts from now on) into the share."""
        if self._dir is None:
            raise RuntimeError("CpuShare.add outside its with-block")
        try:
            (self._dir / "cgroup.procs").write_text(f"{int(pid)}\n")
        except OSError as exc:
            raise CpuShareUnavailable(f"cannot move pid {pid} into {self._dir}: {exc}") from exc
        self.pids.append(int(pid))

    def throttled_s(self) -> float:
        """CPU time the share's processes were held back (cpu.stat), s; nan where the kernel does not say."""
        if self._dir is None:
            return float("nan")
        with contextlib.suppress(OSError, ValueError):
            stat = dict(line.split() for line in (self._dir / "cpu.stat").read_text().splitlines() if line.strip())
            if "throttled_usec" in stat:
                return int(stat["throttled_usec"]) / 1e6
            if "throttled_time" in stat:
                return int(stat["throttled_time"]) / 1e9
        return float("nan")

    def _remove(self) -> None:
        if self._dir is None:
            return
        if self._parent is not None and (self._dir / "cgroup.procs").is_file():
            with contextlib.suppress(OSError):
                for pid in (self._dir / "cgroup.procs").read_text().split():
                    with contextlib.suppress(OSError):   # a process that already ended
                        (self._parent / "cgroup.procs").write_text(f"{pid}\n")
        with contextlib.suppress(OSError):
            self._dir.rmdir()
        self._dir = None

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self._remove()


class BusyNeighbour:
    """A process that spins on one core at the stack's priority until the with-block ends."""

    def __init__(self, processes: int = 1) -> None:
        self.processes = processes
        self._popen: list[subprocess.Popen[bytes]] = []

    def __enter__(self) -> BusyNeighbour:
        for _ in range(self.processes):
            self._popen.append(subprocess.Popen([sys.executable, "-c", "while True: pass"],
                                                stdin=subprocess.DEVNULL, start_new_session=True))
        return self

    @property
    def pids(self) -> list[int]:
        return [p.pid for p in self._popen]

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        for p in self._popen:
            p.kill()
        for p in self._popen:
            with contextlib.suppress(subprocess.TimeoutExpired):
                p.wait(5.0)
        self._popen.clear()

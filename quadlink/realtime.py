"""Real-time scheduling for a process whose latency tail matters (the bridge's 500 Hz IMU path).

``set_realtime_priority(n)`` puts the calling process under Linux ``SCHED_FIFO`` at priority ``n`` (1-99) — what
a systemd unit's ``CPUSchedulingPolicy=fifo`` / ``CPUSchedulingPriority=n`` does — so that a busy board's other
work cannot keep it waiting for a CPU. Threads started afterwards inherit the policy, so call it before the
process starts its threads. It needs ``CAP_SYS_NICE`` (root, ``setcap cap_sys_nice+ep`` on the interpreter, or
the systemd unit); without it, or on a system with no ``SCHED_FIFO``, it logs why and the process runs on at
normal priority: a missing privilege must not stop the flight stack.

``set_nice(n)`` is the milder request for a process that computes a lot (the companion's perception): a real-time
policy on a CPU-bound process would take whole cores from everything else, so it asks the normal scheduler for a
larger share (``nice`` -20..19; below 0 needs the same privilege), below the bridge's ``SCHED_FIFO``.
"""

from __future__ import annotations

import logging
import os

from quadlink.errors import ConfigError

log = logging.getLogger(__name__)

MAX_PRIORITY = 99


def set_realtime_priority(priority: int) -> bool:
    """``SCHED_FIFO`` at ``priority`` for this process; 0 leaves the scheduling alone. True if it applied."""
    if not 0 <= priority <= MAX_PRIORITY:
        raise ConfigError(f"real-time priority {priority}: must be 0 (off) or 1-{MAX_PRIORITY}")
    if priority == 0:
        return False
    setter = getattr(os, "sched_setscheduler", None)
    policy = getattr(os, "SCHED_FIFO", None)
    if setter is None or policy is None:
        log.warning("real-time priority %d requested but this system has no SCHED_FIFO: normal priority", priority)
        return False
    try:
        setter(0, policy, os.sched_param(priority))
    except PermissionError:
        log.warning("real-time priority %d refused (needs CAP_SYS_NICE: run as root, give the interpreter "
                    "cap_sys_nice, or set CPUSchedulingPolicy=fifo in its systemd unit): normal priority", priority)
        return False
    except OSError as exc:
        log.warning("real-time priority %d failed (%s): normal priority", priority, exc)
        return False
    log.info("running under SCHED_FIFO, priority %d", priority)
    return True


MIN_NICE, MAX_NICE = -20, 19


def set_nice(nice: int) -> bool:
    """This process's niceness to ``nice`` (0 leaves it alone); True if it applied. Never raises for a missing
    privilege or an old kernel: it logs why and the process runs on."""
    if not MIN_NICE <= nice <= MAX_NICE:
        raise ConfigError(f"nice {nice}: must be in {MIN_NICE}..{MAX_NICE} (0: leave it)")
    if nice == 0:
        return False
    setter, getter = getattr(os, "setpriority", None), getattr(os, "getpriority", None)
    which = getattr(os, "PRIO_PROCESS", None)
    if setter is None or getter is None or which is None:
        log.warning("nice %d requested but this system has no setpriority: normal priority", nice)
        return False
    try:
        setter(which, 0, nice)
    except PermissionError:
        log.warning("nice %d refused (a negative nice needs CAP_SYS_NICE or an RLIMIT_NICE): normal priority", nice)
        return False
    except OSError as exc:
        log.warning("nice %d failed (%s): normal priority", nice, exc)
        return False
    log.info("running at nice %d", getter(which, 0))
    return True

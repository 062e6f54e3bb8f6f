"""Issue 30: the envelope on a starved CPU. The companion and the bridge held to 0.35 of a core of this machine as
it ran when that share was validated (CFS bandwidth control over a 20 ms period: an Odroid-class budget), scaled to
the machine's speed now (harness/machine_speed.py), with a busy process beside the stack, an operator pushing
toward the south wall for 30 s in real time, the shipped failsafe timeouts: the vehicle keeps 0.40 m from every
surface, failsafes included. Without a cgroup to use (no root), two busy neighbours starve it instead, and the test
says so."""

from __future__ import annotations

import contextlib
import re
from pathlib import Path

import numpy as np
import pytest
from flight_harness import flight

from harness.cpu_share import BusyNeighbour, CpuShare, CpuShareUnavailable
from harness.machine_speed import REFERENCE_WORK_CPU_S, starved_cores, work_cpu_s
from harness.ports import free_port_offset

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(900)]

MIN_CLEARANCE_M = 0.40
OFFSET = free_port_offset()   # harness.ports: free now, reserved for this session


def _status_figures(log: Path) -> list[tuple[float, float]]:
    """(data age p50, max) in ms from the companion's status lines."""
    out = []
    for m in re.finditer(r"data age p50 ([\d.]+) ms max ([\d.]+) ms", log.read_text(errors="replace")):
        out.append((float(m.group(1)), float(m.group(2))))
    return out


@pytest.mark.slow   # a 30 s real-time flight (~2.5 min): CI's time (it left CI on 39d0bc8 when its share was in
#                     absolute cores and this machine ran ~2x slower than when the share was chosen)
def test_a_starved_companion_pushed_into_a_wall_keeps_its_distance(tmp_path: Path) -> None:
    work_s = work_cpu_s()
    cores = starved_cores(work_s)
    with contextlib.ExitStack() as stack:
        try:
            share: CpuShare | None = stack.enter_context(CpuShare(cores))
            stack.enter_context(BusyNeighbour(1))
            how = (f"{cores} core (0.35 core of the machine that validated it: the work took {work_s:.3f} s, "
                   f"{REFERENCE_WORK_CPU_S:.3f} s at the reference; cgroup v{share.version}) + a busy neighbour")
        except CpuShareUnavailable as exc:
            share = None
            stack.enter_context(BusyNeighbour(2))
            how = f"two busy neighbours (no CPU share: {exc})"
        with flight(tmp_path, offset=OFFSET, lockstep=False, shipped_timeouts=True, cpu_share=share) as f:
            f.take_off()
            t0, p0 = f.t_s, f.p_arena.copy()
            f.run_for(30.0, lambda: f.manual(700))
            s = f.log.min_surface()
            figures = _status_figures(tmp_path / "logs" / "companion.log")
            throttled = share.throttled_s() if share is not None else float("nan")
            print(f"starved by {how}: {f.log.summary()}; throttled {throttled:.1f} s; data age p50/max (ms) "
                  f"{figures}; holds: {[t for t in f.log.statustexts if 'old: holding' in t]}")
            assert s is not None and s.clearance.surface_m >= MIN_CLEARANCE_M, f.log.summary()
            moved = float(np.linalg.norm(f.p_arena[:2] - p0[:2]))
            assert moved > 0.5, f"moved {moved:.2f} m in 30 s: starved or not, the operator flies"
            assert f.t_s > t0 + 25.0
            assert figures, "the companion's status line reports the data age"

"""How fast this machine runs now, for CPU shares that mean the same starvation on a slower or faster machine
(issue 30).

A share in cores (:class:`harness.cpu_share.CpuShare`) is a fixed amount of CPU time, so the same 0.35 core is a
harsher budget on a machine that runs the code more slowly. This one ran the companion at 0.265 core-s per second
of flight (``benchmarks/bench_companion.py``) when the starved flights' 0.35 core was chosen and validated (40 of
40 flights), and at 0.48–0.61 core-s/s weeks later on the same code, when CI's starved flight could no longer fly.

:func:`work_cpu_s` is a fixed piece of work in the companion's mix — image filters and warps, array arithmetic,
small-object Python — that imports nothing of this project, so a change to the stack's own speed does not move it
(the benchmarks judge that); only the machine does. :func:`scaled_cores` gives the share that is to the machine
now what a share was to it at a reference measure.
"""

from __future__ import annotations

import math
import struct
import time
from collections.abc import Callable

import cv2
import numpy as np

# On this machine on 2026-12-07 (2 cores): the work's CPU time (the median of six measures, 0.26-0.37 s: the
# machine's speed drifts by that much within minutes), measured around bench_companion's companion CPU of 0.569
# core-s/s on 655a2cd, which was 0.265 when the starved flights' 0.35 core was validated; and what 0.35 core then is
REFERENCE_WORK_CPU_S = 0.34
REFERENCE_DATE = "2026-12-07"
STARVED_CORES_AT_REFERENCE = 0.35 * 0.569 / 0.265   # 0.75 core: the validated share's fraction of the need


def _image_work(rng: np.random.Generator, reps: int) -> float:
    img = rng.random((240, 320), dtype=np.float32)
    map_x = (np.arange(320, dtype=np.float32)[None, :] + 0.37).repeat(240, axis=0)
    map_y = (np.arange(240, dtype=np.float32)[:, None] + 0.61).repeat(320, axis=1)
    acc = 0.0
    for _ in range(reps):
        gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3)
        gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3)
        warped = cv2.remap(img, map_x, map_y, cv2.INTER_LINEAR)
        r = warped - img
        w = 6.0 / (5.0 + r * r / 0.01)
        pick = np.argpartition(np.abs(gx) + np.abs(gy), -4000, axis=None)[-4000:]
        J = np.stack([gx.ravel()[pick], gy.ravel()[pick], r.ravel()[pick]], axis=1)
        acc += float(np.linalg.solve(J.T @ (J * w.ravel()[pick, None]) + np.eye(3), J.T @ r.ravel()[pick])[0])
    return acc


def _python_work(reps: int) -> float:
    acc = 0.0
    state: dict[str, float] = {}
    pack = struct.Struct("<Qfff").pack
    for i in range(reps):
        x, y, z = i * 1e-3, math.sin(i * 1e-3), math.cos(i * 1e-3)
        msg = pack(i, x, y, z)
        state["x"], state["y"], state["z"] = x, y, z
        acc += len(msg) * 1e-6 + min(max(state["y"], -0.5), 0.5)
    return acc


def work_cpu_s(passes: int = 3, cpu_clock: Callable[[], float] = time.process_time) -> float:
    """CPU seconds of the fixed work (~0.3 s on the reference machine), the least of ``passes`` passes (the one least
    disturbed by other processes)."""
    if passes < 1:
        raise ValueError(f"need at least one pass, got {passes}")
    best = math.inf
    for _ in range(passes):
        rng = np.random.default_rng(0)
        t0 = cpu_clock()
        _image_work(rng, 100)
        _python_work(100_000)
        best = min(best, cpu_clock() - t0)
    return best


def scaled_cores(cores_at_reference: float, measured_s: float, reference_s: float) -> float:
    """The share that is to this machine now what ``cores_at_reference`` was when the work took ``reference_s``:
    ``cores_at_reference * measured_s / reference_s`` (a machine twice as slow gets twice the cores)."""
    if not (measured_s > 0.0 and reference_s > 0.0 and cores_at_reference > 0.0):
        raise ValueError(f"cores {cores_at_reference}, measured {measured_s} s and reference {reference_s} s must "
                         "be > 0")
    return cores_at_reference * measured_s / reference_s


def starved_cores(work_s: float) -> float:
    """The starved flights' share on this machine now (their validated 0.35 core, scaled), to the millicore, for a
    work time ``work_s`` of :func:`work_cpu_s`."""
    return round(scaled_cores(STARVED_CORES_AT_REFERENCE, work_s, REFERENCE_WORK_CPU_S), 3)

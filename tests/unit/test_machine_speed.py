"""harness/machine_speed.py: a CPU share scaled to the machine's speed now, measured by work the stack cannot move."""

from __future__ import annotations

import ast
import inspect

import pytest

from harness import machine_speed
from harness.machine_speed import scaled_cores, work_cpu_s


def test_a_machine_twice_as_slow_gets_twice_the_cores() -> None:
    assert scaled_cores(0.35, 0.6, 0.3) == pytest.approx(0.70)
    assert scaled_cores(0.35, 0.15, 0.3) == pytest.approx(0.175)
    assert scaled_cores(0.35, 0.3, 0.3) == pytest.approx(0.35)
    for bad in ((0.35, 0.0, 0.3), (0.35, 0.3, float("nan")), (0.0, 0.3, 0.3), (0.35, -1.0, 0.3)):
        with pytest.raises(ValueError):
            scaled_cores(*bad)


def test_the_work_is_timed_on_the_injected_clock_and_the_least_disturbed_pass_counts() -> None:
    readings = iter([0.0, 5.0, 10.0, 12.0, 20.0, 23.0])   # passes of 5, 2 and 3 CPU seconds
    assert work_cpu_s(passes=3, cpu_clock=lambda: next(readings)) == 2.0
    with pytest.raises(ValueError):
        work_cpu_s(passes=0)


def test_the_work_imports_nothing_of_the_stack() -> None:
    """A change to the stack's own speed must not move the measure (the benchmarks judge that), only the machine."""
    tree = ast.parse(inspect.getsource(machine_speed))
    roots = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            roots |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module:
            roots.add(node.module.split(".")[0])
    assert roots <= {"__future__", "math", "struct", "time", "collections", "cv2", "numpy"}, roots
    assert machine_speed.REFERENCE_WORK_CPU_S > 0.0

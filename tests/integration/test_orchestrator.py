"""The harness's process supervisor (harness/demo/orchestrator.py): its CPU figures at a bounded cost."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from harness.demo.orchestrator import ProcessSpec, Stack


def test_check_samples_cpu_once_per_period_and_the_figures_are_sampled_at_the_end(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A flight loop calls check() at 50 Hz; each sample walks /proc for the part's children (it took ~0.45 of a
    core in the harness when every check sampled). check() samples a part at most once per period of its clock;
    cpu_seconds() samples every part, so the flight's figures are as of its end."""
    now_s = [100.0]
    stack = Stack(tmp_path, cpu_sample_period_s=1.0, clock=lambda: now_s[0])
    sampled: list[str] = []
    real = Stack._sample_cpu
    monkeypatch.setattr(Stack, "_sample_cpu", staticmethod(lambda r: (sampled.append(r.spec.name), real(r))))
    # a part that starts Python and its http.server (some CPU), then idles
    stack.start(ProcessSpec("idle", ("0", "--bind", "127.0.0.1"), ready_after_s=0.0, module="http.server"))
    try:
        for _ in range(200):
            stack.check()
        assert sampled == ["idle"]
        first_s = stack.running[0].cpu_s
        now_s[0] += 0.999
        stack.check()
        assert sampled == ["idle"]
        now_s[0] += 0.001
        stack.check()
        assert sampled == ["idle", "idle"]
        time.sleep(1.0)            # its imports done; check() on a frozen clock does not see them ...
        for _ in range(50):
            stack.check()
        assert len(sampled) == 2
        cpu = stack.cpu_seconds()  # ... cpu_seconds() does
        assert len(sampled) == 3
        assert cpu["idle"] > 0.02 and cpu["idle"] >= first_s
    finally:
        stack.stop(timeout_s=3.0)

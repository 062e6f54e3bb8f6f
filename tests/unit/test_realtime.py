"""Real-time priority: applied when allowed, a warning (never an exception) when refused, bad values rejected."""

from __future__ import annotations

import logging
import os

import pytest

from quadlink import realtime
from quadlink.errors import ConfigError


def test_zero_leaves_the_scheduling_alone(monkeypatch: pytest.MonkeyPatch) -> None:
    calls: list[tuple[int, int, int]] = []
    monkeypatch.setattr(os, "sched_setscheduler", lambda pid, pol, p: calls.append((pid, pol, p.sched_priority)),
                        raising=False)
    assert realtime.set_realtime_priority(0) is False
    assert calls == []


def test_priority_applies_sched_fifo_to_this_process(monkeypatch: pytest.MonkeyPatch) -> None:
    calls: list[tuple[int, int, int]] = []
    monkeypatch.setattr(os, "sched_setscheduler", lambda pid, pol, p: calls.append((pid, pol, p.sched_priority)),
                        raising=False)
    monkeypatch.setattr(os, "SCHED_FIFO", 1, raising=False)
    assert realtime.set_realtime_priority(20) is True
    assert calls == [(0, 1, 20)]


@pytest.mark.parametrize("error", [PermissionError(1, "Operation not permitted"), OSError(22, "Invalid argument")])
def test_refusal_is_a_warning_and_normal_priority(monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture,
                                                  error: OSError) -> None:
    def refuse(*_: object) -> None:
        raise error

    monkeypatch.setattr(os, "sched_setscheduler", refuse, raising=False)
    monkeypatch.setattr(os, "SCHED_FIFO", 1, raising=False)
    with caplog.at_level(logging.WARNING, logger="quadlink.realtime"):
        assert realtime.set_realtime_priority(20) is False
    assert "normal priority" in caplog.text
    if isinstance(error, PermissionError):
        assert "CAP_SYS_NICE" in caplog.text


def test_no_sched_fifo_on_this_system_is_a_warning(monkeypatch: pytest.MonkeyPatch,
                                                   caplog: pytest.LogCaptureFixture) -> None:
    monkeypatch.delattr(os, "sched_setscheduler", raising=False)
    with caplog.at_level(logging.WARNING, logger="quadlink.realtime"):
        assert realtime.set_realtime_priority(10) is False
    assert "no SCHED_FIFO" in caplog.text


@pytest.mark.parametrize("bad", [-1, 100])
def test_out_of_range_is_a_config_error(bad: int) -> None:
    with pytest.raises(ConfigError, match="1-99"):
        realtime.set_realtime_priority(bad)


def test_bridge_config_rejects_an_out_of_range_priority() -> None:
    from firmware_bridge.daemon import BridgeConfig

    assert BridgeConfig().realtime_priority == 0
    with pytest.raises(ValueError, match="realtime_priority"):
        BridgeConfig(realtime_priority=120)


# ---------------------------------------------------------------- nice (the companion)
def test_nice_zero_leaves_the_process_alone(monkeypatch: pytest.MonkeyPatch) -> None:
    calls: list[tuple[int, int, int]] = []
    monkeypatch.setattr(os, "setpriority", lambda which, who, n: calls.append((which, who, n)), raising=False)
    assert realtime.set_nice(0) is False
    assert calls == []


def test_nice_applies_to_this_process(monkeypatch: pytest.MonkeyPatch) -> None:
    calls: list[tuple[int, int, int]] = []
    monkeypatch.setattr(os, "setpriority", lambda which, who, n: calls.append((which, who, n)), raising=False)
    monkeypatch.setattr(os, "getpriority", lambda which, who: -5, raising=False)
    assert realtime.set_nice(-5) is True
    assert calls == [(os.PRIO_PROCESS, 0, -5)]


def test_nice_refused_is_a_warning(monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    def refuse(*_: object) -> None:
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(os, "setpriority", refuse, raising=False)
    with caplog.at_level(logging.WARNING, logger="quadlink.realtime"):
        assert realtime.set_nice(-5) is False
    assert "CAP_SYS_NICE" in caplog.text and "normal priority" in caplog.text


@pytest.mark.parametrize("bad", [-21, 20])
def test_nice_out_of_range_is_a_config_error(bad: int) -> None:
    with pytest.raises(ConfigError, match="-20..19"):
        realtime.set_nice(bad)


def test_a_positive_nice_really_lowers_this_process_in_a_child() -> None:
    """The real call, in a child process (a raised nice cannot be lowered again without the privilege)."""
    import subprocess
    import sys

    code = ("import os, quadlink.realtime as r; ok = r.set_nice(7); "
            "print(ok, os.getpriority(os.PRIO_PROCESS, 0))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    if os.getpriority(os.PRIO_PROCESS, 0) > 7:
        pytest.skip("this test runs niced above 7: lowering it to 7 needs the privilege")
    assert out.stdout.split() == ["True", "7"]

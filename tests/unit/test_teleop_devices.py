"""Device backends: the virtual device against the analytic solution of eq. (1), scripts, errors."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from quadlink.config import CONFIG_DIR
from quadlink.errors import ConfigError, LinkError
from teleop.config import DeviceConfig
from teleop.devices import open_device
from teleop.devices.script import load_script
from teleop.devices.virtual import ScriptedOperator, VirtualDevice, step_dynamics

SCRIPTS = sorted((CONFIG_DIR / "teleop_scripts").glob("*.yaml"))


def analytic(t: float, m: float, c: float, f: float, q0: float = 0.0, v0: float = 0.0) -> tuple[float, float]:
    """m q'' + c q' = f, constant f: q(t), q'(t)."""
    v_inf = f / c
    v = v_inf + (v0 - v_inf) * math.exp(-c * t / m)
    q = q0 + v_inf * t + (v0 - v_inf) * (m / c) * (1 - math.exp(-c * t / m))
    return q, v


def write_script(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "s.yaml"
    path.write_text(text)
    return path


def test_step_dynamics_matches_analytic_solution_at_any_step():
    m, c = np.array([0.25, 0.5, 1.0]), np.array([2.0, 1.0, 0.5])
    f = np.array([1.0, -0.5, 0.2])
    for dt in (1e-3, 7e-3):
        q, v = np.zeros(3), np.zeros(3)
        n = int(round(0.35 / dt))
        for _ in range(n):
            q, v = step_dynamics(q, v, f, dt, m, c)
        for i in range(3):
            qa, va = analytic(n * dt, m[i], c[i], f[i])
            assert q[i] == pytest.approx(qa, rel=1e-9, abs=1e-12)
            assert v[i] == pytest.approx(va, rel=1e-9, abs=1e-12)


def test_undamped_axis_is_constant_acceleration():
    q, v = step_dynamics(np.zeros(3), np.array([0.1, 0, 0]), np.array([0.5, 0, 0]), 0.2, np.ones(3), np.zeros(3))
    assert q[0] == pytest.approx(0.1 * 0.2 + 0.5 * 0.5 * 0.04)
    assert v[0] == pytest.approx(0.1 + 0.5 * 0.2)


def test_virtual_device_scripted_push_follows_eq1(tmp_path):
    cfg = DeviceConfig(mass_kg=(0.25, 0.25, 0.25), damping_n_s_m=(2.0, 2.0, 2.0), workspace_m=(0.5, 0.5, 0.5))
    script = load_script(write_script(tmp_path, "steps:\n  - push: forward\n    force_n: 0.4\n    duration_s: 1.0\n"
                                                "  - release: true\n    duration_s: 1.0\n"))
    dev = VirtualDevice(cfg, ScriptedOperator(script))
    dev.poll(100.0)                      # the script starts at the first poll
    for k in range(1, 501):              # 0.5 s at 1 kHz, no device force
        state = dev.poll(100.0 + k * 1e-3)
    qa, va = analytic(0.5, 0.25, 2.0, 0.4)
    assert state.q_m[0] == pytest.approx(qa, rel=1e-6)
    assert state.qdot_m_s[0] == pytest.approx(va, rel=1e-6)
    assert state.q_m[1] == 0.0 and state.q_m[2] == 0.0
    np.testing.assert_allclose(state.operator_force_n, [0.4, 0.0, 0.0])
    # a device force equal and opposite to the push holds the handle's velocity constant
    dev.set_force(np.array([-0.4, 0.0, 0.0]))
    v_before = dev.poll(100.6).qdot_m_s[0]
    v_after = dev.poll(100.9).qdot_m_s[0]
    assert v_after == pytest.approx(v_before * math.exp(-2.0 * 0.3 / 0.25), rel=1e-6)


def test_workspace_is_a_hard_stop():
    cfg = DeviceConfig(workspace_m=(0.05, 0.05, 0.05))
    dev = VirtualDevice(cfg)
    dev.poll(0.0)
    dev.set_force(np.array([5.0, -5.0, 0.0]))
    state = dev.poll(2.0)
    assert state.q_m[0] == pytest.approx(0.05) and state.q_m[1] == pytest.approx(-0.05)
    assert state.qdot_m_s[0] == 0.0 and state.qdot_m_s[1] == 0.0


def test_script_timeline_and_buttons(tmp_path):
    script = load_script(write_script(tmp_path, """
name: t
steps:
  - button: arm
  - wait_s: 1.5
  - button: takeoff
  - push: sideways
    force_n: 1.0
    duration_s: 2
  - force_d_n: [0.5, 0.0, -0.5]
    duration_s: 1
  - push: up
    force_n: 2.0
    duration_s: 0.5
  - button: land
"""))
    assert script.end_s == pytest.approx(5.0)
    assert script.presses == ((0.0, "arm"), (1.5, "takeoff"), (5.0, "land"))
    np.testing.assert_allclose(script.force_at(1.0), 0.0)
    np.testing.assert_allclose(script.force_at(2.0), [0.0, 1.0, 0.0])
    np.testing.assert_allclose(script.force_at(4.0), [0.5, 0.0, -0.5])
    np.testing.assert_allclose(script.force_at(4.7), [0.0, 0.0, -2.0])   # up is -z in D (NED)
    np.testing.assert_allclose(script.force_at(6.0), 0.0)
    dev = VirtualDevice(DeviceConfig(), ScriptedOperator(script))
    presses = list(dev.poll(10.0).buttons)
    t = 10.0
    while not dev.finished:
        t += 0.01
        presses += dev.poll(t).buttons
    assert presses == ["arm", "takeoff", "land"]


@pytest.mark.parametrize("text, key", [
    ("steps:\n  - push: forward\n    duration_s: 1\n", "needs force_n"),
    ("steps:\n  - push: forward\n    force_n: 1\n", "needs duration_s"),
    ("steps:\n  - push: north\n    force_n: 1\n    duration_s: 1\n", "steps[0].push"),
    ("steps:\n  - button: fly\n", "steps[0].button"),
    ("steps:\n  - wait_s: 1\n    button: arm\n", "exactly one"),
    ("steps:\n  - wiat_s: 1\n", "steps[0].wiat_s"),
    ("steps:\n  - wait_s: -1\n", "duration must be >= 0"),
    ("name: x\n", "steps"),
])
def test_bad_scripts_name_the_step(tmp_path, text, key):
    with pytest.raises(ConfigError) as err:
        load_script(write_script(tmp_path, text))
    assert key in str(err.value) and "s.yaml" in str(err.value)


@pytest.mark.parametrize("path", SCRIPTS, ids=[p.stem for p in SCRIPTS])
def test_shipped_scripts_parse(path):
    script = load_script(path)
    assert script.end_s > 0 and script.segments


def test_unavailable_backends_are_one_line_errors():
    for name, package in (("omega", "forcedimension-core"), ("gamepad", "pygame")):
        try:
            dev = open_device(name, DeviceConfig())
        except LinkError as exc:
            assert package in str(exc) and "\n" not in str(exc)
        else:  # pragma: no cover - only on a machine with the SDK/joystick
            dev.close()
    with pytest.raises(ConfigError):
        open_device("gamepad", DeviceConfig(), script="x.yaml")


def test_script_on_the_vehicle_clock_waits_and_follows_it(tmp_path):
    """--script-clock vehicle: nothing happens before the first feedback; then the script follows vehicle time
    (here running at a quarter of the device's wall time, like a lock-stepped SITL)."""
    script = load_script(write_script(tmp_path, "steps:\n  - wait_s: 1.0\n  - button: arm\n"
                                                "  - push: forward\n    force_n: 1.0\n    duration_s: 1.0\n"))
    vehicle_t: list[float | None] = [None]
    op = ScriptedOperator(script, lambda: vehicle_t[0])
    dev = VirtualDevice(DeviceConfig(), op)
    presses: list[str] = []
    t = 0.0
    for _ in range(100):                      # 1 s of wall time without feedback: the script waits
        presses += dev.poll(t).buttons
        t += 0.01
    assert presses == [] and not dev.finished
    np.testing.assert_allclose(op.force_at(t), 0.0)
    vehicle_t[0] = 50.0
    forces = []
    k = 0
    while not dev.finished and t < 20.0:
        vehicle_t[0] += 0.0025                # vehicle time at 1/4 of wall time
        k += 1
        if k % 50 == 0:                       # a clock that sometimes jumps back must not replay the script
            vehicle_t[0] -= 0.3
            presses += dev.poll(t).buttons
            vehicle_t[0] += 0.3
        state = dev.poll(t)
        presses += state.buttons
        forces.append((vehicle_t[0] - 50.0, state.operator_force_n[0]))
        t += 0.01
    assert presses == ["arm"]
    assert dev.finished and t == pytest.approx(1.0 + 8.0, abs=0.1)    # 2 s of vehicle time = 8 s of wall time
    pushing = [tv for tv, f in forces if f > 0.5]
    assert min(pushing) == pytest.approx(1.0, abs=0.01) and max(pushing) == pytest.approx(2.0, abs=0.01)

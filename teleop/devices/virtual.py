"""Virtual haptic device: eq. (1) ``M q'' + C q' = tau + f`` with diagonal M, C (a Cartesian
handle: no Coriolis coupling, C is the mechanism's viscous friction), the operator force f from a
script or the keyboard.

:func:`step_dynamics` is the exact zero-order-hold solution of eq. (1) over one step (constant
force), so the simulated handle matches the analytic solution at any step size; the workspace is a
hard stop (position clamped, outward velocity zeroed).
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from teleop.config import DeviceConfig
from teleop.devices.base import DeviceState, HapticDevice
from teleop.devices.script import OperatorScript

Vec3 = NDArray[np.float64]


def _step_axis(q: float, v: float, u: float, dt_s: float, m: float, c: float) -> tuple[float, float]:
    """Exact solution of m q'' + c q' = u over dt_s (u constant)."""
    if c * dt_s / m < 1e-9:  # undamped: constant acceleration
        a = u / m
        return q + v * dt_s + 0.5 * a * dt_s * dt_s, v + a * dt_s
    v_inf = u / c                          # terminal velocity
    decay = math.exp(-c * dt_s / m)
    return q + v_inf * dt_s + (v - v_inf) * (m / c) * (1.0 - decay), v_inf + (v - v_inf) * decay


def step_dynamics(q_m: Vec3, qdot_m_s: Vec3, force_n: Vec3, dt_s: float, mass_kg: Vec3,
                  damping_n_s_m: Vec3) -> tuple[Vec3, Vec3]:
    """Exact solution of eq. (1) per axis over ``dt_s`` with the force held constant."""
    out = [_step_axis(float(q_m[i]), float(qdot_m_s[i]), float(force_n[i]), dt_s, float(mass_kg[i]),
                      float(damping_n_s_m[i])) for i in range(3)]
    return np.array([o[0] for o in out]), np.array([o[1] for o in out])


def clamp_workspace(q_m: Vec3, qdot_m_s: Vec3, workspace_m: Vec3) -> tuple[Vec3, Vec3]:
    q = np.clip(q_m, -workspace_m, workspace_m)
    v = qdot_m_s.copy()
    v[(q >= workspace_m) & (v > 0)] = 0.0
    v[(q <= -workspace_m) & (v < 0)] = 0.0
    return q, v


class OperatorSource:
    """Where the virtual device's operator force and button presses come from (times: since the first poll)."""

    def force_at(self, t_s: float) -> Vec3:
        return np.zeros(3)

    def presses_between(self, t0_s: float, t1_s: float) -> tuple[str, ...]:
        return ()

    def finished(self, t_s: float) -> bool:
        return False

    def close(self) -> None:
        pass


class ScriptedOperator(OperatorSource):
    """Plays an :class:`OperatorScript`.

    ``script_clock=None``: the script runs on the device's (wall) time. Otherwise ``script_clock()``
    returns another time in seconds (e.g. the vehicle's, from TELEOP_FEEDBACK, so a script keeps step
    with a lock-stepped SITL that runs slower than real time) or None while that time is unknown (the
    script then waits at its start).
    """

    def __init__(self, script: OperatorScript, script_clock: Callable[[], float | None] | None = None) -> None:
        self.script = script
        self.script_clock = script_clock
        self._origin_s: float | None = None
        self._script_s = 0.0
        self._last_s = -1.0

    def script_time(self, t_s: float) -> float:
        """Seconds into the script; never goes back (a clock that jumps back holds the script)."""
        if self.script_clock is None:
            return t_s
        now = self.script_clock()
        if now is None or not np.isfinite(now):
            return max(self._script_s, 0.0)
        if self._origin_s is None:
            self._origin_s = now
        self._script_s = max(self._script_s, now - self._origin_s)
        return self._script_s

    def force_at(self, t_s: float) -> Vec3:
        return self.script.force_at(self.script_time(t_s))

    def presses_between(self, t0_s: float, t1_s: float) -> tuple[str, ...]:
        if self.script_clock is None:
            return self.script.presses_between(t0_s, t1_s)
        now = self.script_time(t1_s)
        if self._origin_s is None:
            return ()
        presses = self.script.presses_between(self._last_s, now)
        self._last_s = max(self._last_s, now)
        return presses

    def finished(self, t_s: float) -> bool:
        return self.script_time(t_s) >= self.script.end_s and (self.script_clock is None or self._origin_s is not None)


class VirtualDevice(HapticDevice):
    """eq. (1) integrated at the force-loop rate (sub-stepped at <= 1 ms if polled slower)."""

    name = "virtual"
    has_force_output = True

    def __init__(self, cfg: DeviceConfig, operator: OperatorSource | None = None,
                 max_step_s: float = 1e-3, on_finished: Callable[[], None] | None = None) -> None:
        self.cfg = cfg
        self.operator = operator or OperatorSource()
        self.mass_kg = np.asarray(cfg.mass_kg, dtype=float)
        self.damping = np.asarray(cfg.damping_n_s_m, dtype=float)
        self.workspace = np.asarray(cfg.workspace_m, dtype=float)
        self._m, self._c, self._w = (tuple(float(x) for x in a) for a in (cfg.mass_kg, cfg.damping_n_s_m,
                                                                         cfg.workspace_m))
        self.max_step_s = max_step_s
        self.q_m = np.zeros(3)
        self.qdot_m_s = np.zeros(3)
        self._tau_n = np.zeros(3)
        self._t0_s: float | None = None
        self._t_s: float | None = None
        self._lock = threading.Lock()

    def elapsed_s(self, t_s: float) -> float:
        return 0.0 if self._t0_s is None else t_s - self._t0_s

    def poll(self, t_s: float) -> DeviceState:
        with self._lock:
            if self._t0_s is None:
                self._t0_s = self._t_s = t_s
                presses = self.operator.presses_between(-1.0, 0.0)
                f = self.operator.force_at(0.0)
                return DeviceState(t_s, self.q_m.copy(), self.qdot_m_s.copy(), presses, f)
            assert self._t_s is not None
            t_prev = self._t_s - self._t0_s
            t_now = t_s - self._t0_s
            t = t_prev
            q, v = self.q_m.tolist(), self.qdot_m_s.tolist()     # plain floats: this runs at 1 kHz
            tau = self._tau_n.tolist()
            while t < t_now - 1e-12:
                dt = min(self.max_step_s, t_now - t)
                f = self.operator.force_at(t).tolist()
                for i in range(3):
                    q[i], v[i] = _step_axis(q[i], v[i], tau[i] + f[i], dt, self._m[i], self._c[i])
                    w = self._w[i]
                    if q[i] >= w:          # the workspace is a hard stop
                        q[i], v[i] = w, min(v[i], 0.0)
                    elif q[i] <= -w:
                        q[i], v[i] = -w, max(v[i], 0.0)
                t += dt
            self.q_m, self.qdot_m_s = np.array(q), np.array(v)
            self._t_s = t_s
            presses = self.operator.presses_between(t_prev, t_now)
            return DeviceState(t_s, self.q_m.copy(), self.qdot_m_s.copy(), presses, self.operator.force_at(t_now))

    def set_force(self, force_d_n: Vec3) -> None:
        with self._lock:
            self._tau_n = np.where(np.isfinite(force_d_n), force_d_n, 0.0)

    @property
    def finished(self) -> bool:
        return self._t_s is not None and self._t0_s is not None and self.operator.finished(self._t_s - self._t0_s)

    def close(self) -> None:
        self.operator.close()

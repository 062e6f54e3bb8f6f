"""A released handle in a force loop closed through a delayed link: the case passivity control is for.

Pure simulation (no I/O, its own time), built from the station's real parts: the handle is the virtual
device's eq. (1) (:func:`teleop.devices.virtual.step_dynamics`, exact ZOH, workspace stop), the force is
:func:`teleop.force.force_law` with q~ from :func:`teleop.force.q_tilde` (eqs. (15)-(16)), and the
passivity controller is :class:`teleop.passivity.PassivityController`, run by the force loop's own tick
(:func:`teleop.force_loop.tau_passive`).

Model of the rest of the loop (forward axis x only):

* the command is eq. (2) without the dead-bands: ``v_cmd = k_v q_x`` (``k_v`` from the mapping config);
* it reaches the vehicle half a round trip later; the vehicle tracks it as a first-order lag
  (``vehicle_time_constant_s``);
* its velocity comes back half a round trip later, sampled at ``feedback_rate_hz`` (TELEOP_FEEDBACK).

Scenario: from rest, the operator's hand (a stiff spring-damper to a reference, ``hand_*``) pushes the
handle to ``q0_m`` over ``push_s`` and holds it there (the vehicle cruises at ``k_v q0``) until t = 0,
then lets go; afterwards no hand force (``f = 0`` in eq. (1)). The observer runs from the start, so the
energy the hand stored in the spring is on its account. Without delay the handle returns to rest; with
a long round trip the cue ``K (q - q~)`` keeps pulling the handle toward where it was a round trip ago.
Times in the result are relative to the release (negative before it).

**Long ticks.** On a loaded machine the force loop misses its 1 ms deadline: with
``long_tick_probability > 0`` a tick lasts a random whole number of ``dt_s`` up to ``long_tick_max_s``
(seeded). The handle, the link and the vehicle still advance every ``dt_s`` (as the virtual device
sub-steps eq. (1)); the force computed at a tick is held until the next one, and the force loop's tick is
given the nominal period, as :func:`teleop.force_loop.run_force_loop` gives it.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from teleop.config import TeleopConfig
from teleop.devices.base import DeviceState
from teleop.devices.virtual import clamp_workspace, step_dynamics
from teleop.force import VehicleMotion, force_law, q_tilde
from teleop.force_loop import tau_passive
from teleop.mapping import mapping_gains
from teleop.passivity import PassivityController, PassivityReport


@dataclass(frozen=True)
class DelayedLoop:
    round_trip_s: float = 0.3
    vehicle_time_constant_s: float = 0.2
    feedback_rate_hz: float = 30.0
    q0_m: float = 0.04
    push_s: float = 1.0              # hand ramps the handle 0 -> q0 over this time, then holds
    hold_s: float = 2.0              # then holds it this long (the vehicle reaches k_v q0), then releases
    hand_stiffness_n_m: float = 400.0
    hand_damping_n_s_m: float = 15.0
    duration_s: float = 8.0          # after the release
    dt_s: float = 0.001
    long_tick_probability: float = 0.0   # chance that a force-loop tick lasts longer than dt_s (a loaded machine)
    long_tick_max_s: float = 0.02        # such a tick lasts a whole number of dt_s, uniform in (dt_s, this]
    seed: int = 0                        # of the long ticks


@dataclass(frozen=True)
class LoopRun:
    t_s: NDArray[np.float64]
    q_x_m: NDArray[np.float64]
    qdot_x_m_s: NDArray[np.float64]
    force_x_n: NDArray[np.float64]
    energy_x_j: NDArray[np.float64]          # observed energy of the x port over time
    report: PassivityReport

    def rms_velocity_m_s(self, after_s: float = 0.0) -> float:
        """RMS handle velocity from ``after_s`` after the release to the end."""
        v = self.qdot_x_m_s[self.t_s >= after_s]
        return float(np.sqrt(np.mean(v * v)))


def simulate_release(cfg: TeleopConfig, loop: DelayedLoop, passivity_on: bool) -> LoopRun:
    gains = mapping_gains(cfg.mapping, cfg.device)
    dev = cfg.device
    mass, damping, workspace = (np.array(x, dtype=float) for x in (dev.mass_kg, dev.damping_n_s_m, dev.workspace_m))
    pc = PassivityController(replace(cfg.passivity, enabled=passivity_on), dev.mass_kg)
    t_release = loop.push_s + loop.hold_s
    n = int(round((t_release + loop.duration_s) / loop.dt_s))
    half = max(int(round(loop.round_trip_s / 2 / loop.dt_s)), 0)
    feedback_every = max(int(round(1.0 / (loop.feedback_rate_hz * loop.dt_s))), 1)
    uplink: deque[float] = deque([0.0] * half)           # commands in flight to the vehicle
    downlink: deque[float] = deque([0.0] * half)         # vehicle velocities in flight back
    v_vehicle = v_fb = 0.0
    decay = math.exp(-loop.dt_s / loop.vehicle_time_constant_s)
    q = np.zeros(3)
    qd = np.zeros(3)
    out = np.zeros((n, 5))
    rng = np.random.default_rng(loop.seed)
    max_steps = max(int(round(loop.long_tick_max_s / loop.dt_s)), 1)
    next_tick = 0
    tau = np.zeros(3)
    for k in range(n):
        t = k * loop.dt_s
        hand = np.zeros(3)
        if t < t_release:
            q_ref = loop.q0_m * min(t / loop.push_s, 1.0)
            hand[0] = loop.hand_stiffness_n_m * (q_ref - q[0]) - loop.hand_damping_n_s_m * qd[0]
        # the network: command out, vehicle, feedback back (each a FIFO of 1 ms samples)
        uplink.append(gains.k_v_xy_per_s * float(q[0]))
        v_cmd_at_vehicle = uplink.popleft()
        v_vehicle = v_cmd_at_vehicle + (v_vehicle - v_cmd_at_vehicle) * decay
        downlink.append(v_vehicle)
        v_back = downlink.popleft()
        if k % feedback_every == 0:
            v_fb = v_back
        qt = q_tilde(VehicleMotion((v_fb, 0.0, 0.0), 0.0, 0.0, 0.0), gains)
        if k == next_tick:   # the force loop's tick, as run_force_loop does it (nominal period given)
            tau_law = force_law(q, qd, qt, cfg.force, dev.force_limit_n)
            tau = tau_passive(pc, t, DeviceState(t, q, qd), tau_law, loop.dt_s, dev.force_limit_n)
            long_tick = max_steps > 1 and rng.random() < loop.long_tick_probability
            next_tick = k + (int(rng.integers(2, max_steps + 1)) if long_tick else 1)
        out[k] = (t - t_release, q[0], qd[0], tau[0], pc.energy_j[0])
        q, qd = step_dynamics(q, qd, tau + hand, loop.dt_s, mass, damping)
        q, qd = clamp_workspace(q, qd, workspace)
    return LoopRun(out[:, 0], out[:, 1], out[:, 2], out[:, 3], out[:, 4], pc.report())


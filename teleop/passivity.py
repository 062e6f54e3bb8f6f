"""Time-domain passivity observer and controller on the haptic device's port. Pure: state in, force out.

Hannaford & Ryu, "Time-domain passivity control of haptic interfaces", IEEE Trans. Robot. Autom.
18(1), 2002; Ryu, Kwon & Hannaford, "Stable teleoperation with time-domain passivity control",
IEEE Trans. Robot. Autom. 20(2), 2004 (the same observer on the ports of a two-port network, and the
split of the port energy into input and output energy).

**The network and its port.** Everything behind the handle — the force law of eq. (15), the mapping
to MANUAL_CONTROL, the link to the vehicle and back (with its delay), the vehicle, eqs. (16)-(18) — is
one network the handle is connected to. It takes the handle's motion and answers with the force tau
the device applies. Each D axis is one port (the gains of eq. (15) are diagonal).

**Sign convention.** Power flows *into* the network when the handle moves against the force:
``P_i = -tau_i q'_i``. The observed energy ``E_i = sum -tau_i dq_i`` (the work the hand did on the
network, minus the work the network did on the hand) is >= 0 for a passive network: the spring and
damping of eq. (15) store or burn what the hand puts in, so ``E_i`` is their stored energy plus their
dissipation. A delayed cue ``K (q - q~)`` can return more than it received; then ``E_i < 0`` and the
network is active: it is what makes a released handle oscillate under delay.

**Observer** (H&R 2002 eq. (7), in work form): the force is held constant over each force-loop period
(zero-order hold), so the exact work of the period that just ended is ``-tau_i(n-1) (q_i(n) - q_i(n-1))``;
no velocity estimate enters the account, and the force counted is the one the device really applied
(after the controller and the saturation).

**Controller** (H&R 2002 eqs. (9)-(10)): before applying the force of eq. (15), predict the energy at
the end of the coming period with the current velocity, ``E_i + (-tau_i q'_i) T``; if it is negative,
add a damping ``alpha_i = -E_pred / (T q'_i^2)`` on the device side (``tau_i -= alpha_i q'_i``), which
dissipates exactly the excess over the period. The damping is bounded (``max_damping_n_s_m``, a
sampled damper is stable only for ``alpha T / M < 2``) and its force too (``max_force_n``); below
``min_speed_m_s`` nothing can be dissipated and the deficit waits. ``T`` is the period that just ended
as measured by the observer (at least the nominal one): on a loaded machine a tick lasts 5-30 ms, not 1.

**Why H&R alone leaves a deficit.** It acts only *after* the energy is negative, and only through a
damping. (a) On a slow handle a damping cannot take back what a force does: it dissipates at most
``max_damping_n_s_m v^2 T`` per period while the force does ``|tau| v T``, and nothing below
``min_speed_m_s``. In a delayed demo flight the deficit was on the yaw axis, that case: the vehicle's own
yaw (the pan-scan tracking error) moved q~, the cue pushed the released handle at 2-3 mm/s, the damping
chattered at its 150 N s/m cap and the deficit crept on. (b) Its prediction assumes the force does ``tau q' T`` over
one nominal period; when a tick lasts 20 ms instead of 1 (a loaded machine), the force held over it
(zero-order hold) does ``tau q' T + tau^2 T^2 / (2 M)``, and a damping at its cap held 20 ms
(``alpha T / M = 12``) reverses the handle and pushes it back: the damper itself becomes active. Both
are on the account before any damping can answer (flown: -3.2 mJ at 150 ms one way, -6.6 mJ at 300 ms,
against epsilon = 1 mJ; reproduced in tests/unit/test_teleop_passivity.py).

**Passivity layer** (``tank_layer``, behind the controller): the energy tank of Franken, Stramigioli,
Misra, Secchi & Macchelli, "Bilateral telemanipulation with time delays: a two-layer approach combining
passivity and transparency", IEEE Trans. Robotics 27(4), 2011 (section IV: the transparency layer asks
for a force, the passivity layer lets the port deliver only the energy its tank holds). Here the tank of
axis i is its observed energy ``E_i`` (what the hand put in, minus what the network gave back). The
force about to be held over the coming period is bounded so that the work it can do on the hand,
predicted with the handle's own motion and the force's acceleration of the device mass ``M``,

    W(s) = s tau d + s^2 tau^2 T_p^2 / (2 M),   d = q' T_p (+ a_o T_p^2 / 2 when a_o pushes along tau)

never exceeds the tank: ``s`` is the largest value in [0, 1] with ``W(s) <= max(E_i, 0)``. When the
account allows it (``W(1) <= E_i``, every tick of a passive loop) the force is untouched, so the spring
and damping of eq. (15) keep the operator's feel; otherwise the force that would do work on the hand is
scaled down, and a force opposing the motion is cut to what does no net work over the period (a
damping that would stop the handle, reverse it and push it back past where it started gives energy).
``T_p`` is the *measured* period: the longest of the last ``period_hold_s`` (at least the nominal one),
as a long tick is the sign of a loaded machine and the next one is as likely to be long; a tick longer
than any of that window is not foreseen. ``a_o`` is the
acceleration of the handle by everything but the network over the last period (the hand, the friction:
``(q'(n) - q'(n-1)) / T - tau(n-1) / M``), counted only where it carries the handle along the force
(more work out), never to allow more. What is left unforeseen (a longer tick, a hand that changes its
push within the period) is what epsilon is for. The saturation after the layer only scales the force
down further, which ``W`` being convex with ``W(0) = 0`` keeps within the tank.

``energy_cap_j > 0`` caps each port's credit (an energy tank with a ceiling): a long passive history
then cannot hide a later active phase. It only removes credit, so the loop stays passive; 0 = no cap
(plain H&R). The spring and damping of eq. (15) are untouched while the account holds their energy:
the controller only adds damping while the observed energy is negative, the layer only scales a force
whose predicted work the account does not hold.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

from teleop.config import PassivityConfig, Vec3Cfg


@dataclass(frozen=True)
class PassivityReport:
    """Running account of the port energy, summed over the D axes (J), and the last damping."""

    observed_j: float          # E = sum of the axes' observed energy (>= 0: passive so far)
    min_observed_j: float      # the lowest E of any axis so far (the figure to compare with -epsilon)
    input_j: float             # energy the hand put into the network (sum of positive work)
    output_j: float            # energy the network delivered to the hand (sum of negative work): "injected"
    dissipated_j: float        # energy the controller's damping removed
    damping_n_s_m: float       # largest alpha_i applied at the last tick


class PassivityController:
    """Observer always on (the energy is logged either way); the damping and the layer only with ``cfg.enabled``.

    ``mass_kg``: the device's effective mass per axis (``DeviceConfig.mass_kg``), for the layer's prediction.
    """

    def __init__(self, cfg: PassivityConfig, mass_kg: Vec3Cfg) -> None:
        if min(mass_kg) <= 0.0 or not all(math.isfinite(m) for m in mass_kg):
            raise ValueError("passivity: the device mass must be finite and > 0")
        self.cfg = cfg
        self.mass_kg = tuple(float(m) for m in mass_kg)
        self.period_s = 0.0         # the period that just ended, as measured (0 before the second tick)
        self.period_peak_s = 0.0    # the longest over the last cfg.period_hold_s
        self._periods = _WindowMax()
        self.energy_j = [0.0, 0.0, 0.0]     # observed energy per axis
        self.min_energy_j = 0.0
        self.input_j = 0.0
        self.output_j = 0.0
        self.dissipated_j = 0.0
        self._alpha = [0.0, 0.0, 0.0]
        self._q_prev: list[float] | None = None
        self._tau_prev = [0.0, 0.0, 0.0]
        self._pc_prev = [0.0, 0.0, 0.0]     # the controller's part of the last applied force
        self._t_prev: float | None = None
        self._v_prev: list[float] | None = None    # the velocity at the last control (for the layer)

    def observe(self, t_s: float, q_m: list[float]) -> None:
        """Account the work of the period that ended at ``t_s`` (the force of the last ``applied``).

        The lists given here and to ``applied`` are kept, not copied (1 kHz): pass fresh ones.
        """
        if self._t_prev is not None:
            dt = t_s - self._t_prev
            if math.isfinite(dt) and dt > 0.0:
                self.period_s = dt
                self._periods.append_period(t_s, dt)
                self.period_peak_s = self._periods.max_s(t_s - self.cfg.period_hold_s)
        if self._q_prev is not None:
            cap = self.cfg.energy_cap_j
            for i in range(3):
                dq = q_m[i] - self._q_prev[i]
                work_in = -self._tau_prev[i] * dq
                if work_in >= 0.0:
                    self.input_j += work_in
                else:
                    self.output_j -= work_in
                self.dissipated_j += -self._pc_prev[i] * dq    # >= 0: alpha q' dq with dq along q'
                e = self.energy_j[i] + work_in
                self.energy_j[i] = min(e, cap) if cap > 0.0 else e
                self.min_energy_j = min(self.min_energy_j, self.energy_j[i])
        self._q_prev = q_m
        self._t_prev = t_s

    def control(self, qdot_m_s: list[float], tau_n: list[float], period_s: float) -> list[float]:
        """The force to apply instead of ``tau_n`` (eq. (15)'s output), when enabled: plus the H&R damping,
        then bounded by the passivity layer. ``period_s`` is the nominal period (a floor for the measured one)."""
        cfg = self.cfg
        out = list(tau_n)
        if not cfg.enabled:
            self._alpha = [0.0, 0.0, 0.0]
            return out
        t_hr = max(period_s, self.period_s)            # H&R: the coming period is like the one that ended
        t_pred = max(period_s, self.period_peak_s)     # the layer: the longest recent period
        for i in range(3):
            self._alpha[i] = 0.0
            v = qdot_m_s[i]
            if not math.isfinite(v):
                v = 0.0
            if abs(v) >= cfg.min_speed_m_s and v != 0.0:
                e_pred = self.energy_j[i] - tau_n[i] * v * t_hr
                if e_pred < 0.0:
                    alpha = min(-e_pred / (t_hr * v * v), cfg.max_damping_n_s_m, cfg.max_force_n / abs(v))
                    self._alpha[i] = alpha
                    out[i] = tau_n[i] - alpha * v
            if cfg.tank_layer:
                drift = v * t_pred        # the handle's own motion over the period, without the network's force
                if self._v_prev is not None and self.period_s > 0.0:
                    # acceleration by everything else (hand, friction) over the last period; counted only
                    # where it carries the handle along the force (more work out), never to allow more
                    a_other = (v - self._v_prev[i]) / self.period_s - self._tau_prev[i] / self.mass_kg[i]
                    if a_other * out[i] > 0.0 and math.isfinite(a_other):
                        drift += 0.5 * a_other * t_pred * t_pred
                out[i] *= tank_scale(out[i], drift, t_pred, self.mass_kg[i], self.energy_j[i])
        self._v_prev = [v if math.isfinite(v) else 0.0 for v in qdot_m_s]
        return out

    def applied(self, tau_applied_n: list[float], tau_law_n: list[float]) -> None:
        """What the device really got (after saturation), and what eq. (15) asked for: for the account.

        The controller's share is the difference, so a saturation that cut the damping is counted as
        such (it dissipated less than planned; the deficit stays in the observed energy).
        """
        self._tau_prev = tau_applied_n
        self._pc_prev = [a - b for a, b in zip(tau_applied_n, tau_law_n)]

    def report(self) -> PassivityReport:
        return PassivityReport(sum(self.energy_j), self.min_energy_j, self.input_j, self.output_j,
                               self.dissipated_j, max(self._alpha))


class _WindowMax:
    """Sliding-window maximum of the measured periods (a monotonic queue: O(1) per tick)."""

    def __init__(self) -> None:
        self._q: deque[tuple[float, float]] = deque()     # (end time, period), periods decreasing

    def append_period(self, t_s: float, period_s: float) -> None:
        while self._q and self._q[-1][1] <= period_s:
            self._q.pop()
        self._q.append((t_s, period_s))

    def max_s(self, since_s: float) -> float:
        while len(self._q) > 1 and self._q[0][0] < since_s:
            self._q.popleft()
        return self._q[0][1] if self._q else 0.0


def tank_scale(tau_n: float, drift_m: float, period_s: float, mass_kg: float, tank_j: float) -> float:
    """The passivity layer's factor s in [0, 1] on one axis' force (Franken et al. 2011, see the module).

    The largest s with ``W(s) = s a + s^2 b <= max(tank_j, 0)``: ``a = tau drift`` (the work along the
    handle's own motion over the period, ``drift_m`` = q' T plus the other forces' push along tau),
    ``b = tau^2 T^2 / (2 M)`` (the force's own acceleration of the mass over the period T). Exactly 1.0
    when the tank holds ``W(1)``, so a passive loop's force is untouched bit for bit.
    """
    budget = max(tank_j, 0.0)
    a = tau_n * drift_m
    b = tau_n * tau_n * period_s * period_s / (2.0 * mass_kg)
    if a + b <= budget:
        return 1.0
    if not (math.isfinite(a) and math.isfinite(b)) or b <= 0.0:
        return 0.0
    disc = math.sqrt(a * a + 4.0 * b * budget)
    s = (-a + disc) / (2.0 * b) if a < 0.0 else (2.0 * budget / (a + disc) if a + disc > 0.0 else 0.0)
    return min(max(s, 0.0), 1.0)

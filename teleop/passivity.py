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
``min_speed_m_s`` nothing can be dissipated and the deficit waits. What is not dissipated in one period
stays in ``E_i`` and is corrected in the next, so ``E_i`` returns to >= 0 within a few periods.

``energy_cap_j > 0`` caps each port's credit (an energy tank with a ceiling): a long passive history
then cannot hide a later active phase. It only removes credit, so the loop stays passive; 0 = no cap
(plain H&R). The spring and damping of eq. (15) are untouched: the controller only adds damping, and
only while the observed energy is negative.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from teleop.config import PassivityConfig


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
    """Observer always on (the energy is logged either way); the damping only with ``cfg.enabled``."""

    def __init__(self, cfg: PassivityConfig) -> None:
        self.cfg = cfg
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

    def observe(self, t_s: float, q_m: list[float]) -> None:
        """Account the work of the period that ended at ``t_s`` (the force of the last ``applied``).

        The lists given here and to ``applied`` are kept, not copied (1 kHz): pass fresh ones.
        """
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
        """The force to apply instead of ``tau_n`` (eq. (15)'s output): plus the damping, when enabled."""
        cfg = self.cfg
        out = list(tau_n)
        for i in range(3):
            self._alpha[i] = 0.0
            v = qdot_m_s[i]
            if not cfg.enabled or abs(v) < cfg.min_speed_m_s or not math.isfinite(v):
                continue
            e_pred = self.energy_j[i] - tau_n[i] * v * period_s
            if e_pred >= 0.0:
                continue
            alpha = min(-e_pred / (period_s * v * v), cfg.max_damping_n_s_m, cfg.max_force_n / abs(v))
            self._alpha[i] = alpha
            out[i] = tau_n[i] - alpha * v
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

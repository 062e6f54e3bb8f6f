"""Horizontal velocity from the accelerometer's drag reading, learnt in flight (pure, step-based).

A multirotor's accelerometer does not see its tilt the way a fixed sensor would: thrust acts along the body's z axis,
so the body x and y specific force is what the air does to the airframe, the body and rotor drag, nearly
proportional to the velocity through the air (Leishman, Macdonald, Beard and McLain, IEEE Control Systems 2014;
PX4's EKF2 fuses it with EKF2_BCOEF_XY/EKF2_MCOEF, ArduPilot's EK3 with EK3_DRAG_BCOEF/EK3_DRAG_MCOEF):

    f_q,xy = -k v_q,xy + b          (f: specific force, body FRD; k in 1/s; b: the accelerometer's residual bias)

A tilt error does not enter it, which is what makes it useful when the odometry is gone: level flight on the board's
own attitude estimate (~0.5-1 deg off) slides 0.1-0.3 m/s (a campaign's failed take-off drifted 0.2 m/s into a
wall; the companion-less landing drifts ~0.5 m), and the IMU's integral carries the same error. Here k and b are not
configured but learnt per axis while the odometry is good (a least-squares fit of f against the odometry's body
velocity, with exponential forgetting), and used only once the fit has seen enough motion to be trusted.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

FORCE_LOWPASS_TAU_S = 0.2      # the accelerometer's 10-bit steps and noise, averaged
FIT_MEMORY_S = 30.0            # the fit forgets older samples with this time constant
MIN_SPEED_SPREAD_M_S = 0.05    # the fit's samples must spread this much in speed (std) before it is used
MIN_FIT_TIME_S = 3.0           # ... and cover this much flight
K_RANGE_1_S = (0.05, 5.0)      # a drag coefficient outside this is no fit of a multirotor (1/s)


@dataclass
class _AxisFit:
    """Exponentially weighted sums of one axis's samples (v, f): n, sum v, sum f, sum v^2, sum v f."""

    n: float = 0.0
    v: float = 0.0
    f: float = 0.0
    vv: float = 0.0
    vf: float = 0.0

    def add(self, v_m_s: float, f_m_s2: float, weight: float, decay: float) -> None:
        self.n = self.n * decay + weight
        self.v = self.v * decay + weight * v_m_s
        self.f = self.f * decay + weight * f_m_s2
        self.vv = self.vv * decay + weight * v_m_s * v_m_s
        self.vf = self.vf * decay + weight * v_m_s * f_m_s2

    def fit(self) -> tuple[float, float, float] | None:
        """(k, b, speed spread) of f = -k v + b, or None without samples."""
        if self.n <= 0.0:
            return None
        mv, mf = self.v / self.n, self.f / self.n
        var_v = self.vv / self.n - mv * mv
        if var_v <= 1e-9:
            return None
        cov = self.vf / self.n - mv * mf
        k = -cov / var_v
        return k, mf + k * mv, math.sqrt(var_v)


def low_pass(previous: NDArray[np.float64] | None, value: NDArray[np.float64], dt_s: float,
             tau_s: float) -> NDArray[np.float64]:
    """One step of a first-order low-pass (time constant ``tau_s``): ``value`` itself when there is no previous
    output, else the previous output moved toward it by dt/tau of the way (all of it at most). The drag's fit and
    the bridge's drag gate put the odometry's velocity through the same filter as the force reading."""
    v = np.asarray(value, dtype=float)
    if previous is None:
        return v.copy()
    return previous + (v - previous) * min(dt_s / max(tau_s, 1e-3), 1.0)


@dataclass
class DragVelocity:
    """Learns f = -k v + b per body axis from the odometry, and gives v from f when asked."""

    memory_s: float = FIT_MEMORY_S
    force_tau_s: float = FORCE_LOWPASS_TAU_S
    _f_lp: NDArray[np.float64] = field(default_factory=lambda: np.zeros(2))
    _v_lp: NDArray[np.float64] | None = None   # the odometry's velocity through the same low-pass as the force
    _axes: tuple[_AxisFit, _AxisFit] = field(default_factory=lambda: (_AxisFit(), _AxisFit()))
    _fit_time_s: float = 0.0
    _primed: bool = False

    def update(self, dt_s: float, f_q_xy_m_s2: NDArray[np.float64], v_q_xy_m_s: NDArray[np.float64] | None) -> None:
        """One IMU sample: the body x, y specific force; ``v_q_xy_m_s`` the odometry's body velocity now (None: no
        odometry to learn from, or the vehicle not flying)."""
        dt_s = min(max(float(dt_s), 0.0), 0.1)
        f = np.asarray(f_q_xy_m_s2, dtype=float)[:2]
        if not np.all(np.isfinite(f)):
            return
        if not self._primed:
            self._f_lp = f.copy()
            self._primed = True
        self._f_lp += (f - self._f_lp) * min(dt_s / max(self.force_tau_s, 1e-3), 1.0)
        v = None if v_q_xy_m_s is None else np.asarray(v_q_xy_m_s, dtype=float)[:2]
        if v is None or not np.all(np.isfinite(v)):
            self._v_lp = None
            return
        # the velocity through the force's low-pass, so that the fit compares like with like (no lag between them)
        self._v_lp = low_pass(self._v_lp, v, dt_s, self.force_tau_s)
        decay = math.exp(-dt_s / self.memory_s)
        for axis, fit in enumerate(self._axes):
            fit.add(float(self._v_lp[axis]), float(self._f_lp[axis]), dt_s, decay)
        self._fit_time_s += dt_s

    def coefficients(self, nominal_k_1_s: float = 0.0) -> tuple[tuple[float, float], tuple[float, float]] | None:
        """((k_x, b_x), (k_y, b_y)) once both axes are fitted on enough motion. Without that motion (a take-off and
        a hover teach too little: the companion killed at 1.9 m drifted 0.56-0.63 m on the way down), an axis takes
        ``nominal_k_1_s`` (> 0: the vehicle's identified drag, as PX4's EKF2_MCOEF) with its bias from the flight so
        far -- in a hover the mean force is the bias. None before MIN_FIT_TIME_S of flight, or with neither."""
        if self._fit_time_s < MIN_FIT_TIME_S:
            return None
        out = []
        for fit in self._axes:
            r = fit.fit()
            if r is not None and r[2] >= MIN_SPEED_SPREAD_M_S and K_RANGE_1_S[0] <= r[0] <= K_RANGE_1_S[1]:
                out.append((r[0], r[1]))
            elif nominal_k_1_s > 0.0 and fit.n > 0.0:
                out.append((nominal_k_1_s, (fit.f + nominal_k_1_s * fit.v) / fit.n))
            else:
                return None
        return out[0], out[1]

    @property
    def learnt(self) -> bool:
        return self.coefficients() is not None

    def velocity_q_xy(self, nominal_k_1_s: float = 0.0) -> NDArray[np.float64] | None:
        """The body x, y velocity the drag says (m/s), or None before the fit is trusted (see :meth:`coefficients`
        for ``nominal_k_1_s``)."""
        c = self.coefficients(nominal_k_1_s)
        if c is None:
            return None
        (kx, bx), (ky, by) = c
        return np.array([(bx - self._f_lp[0]) / kx, (by - self._f_lp[1]) / ky])

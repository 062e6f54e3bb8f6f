"""The 1€ filter (Casiez, Roussel, Vogel, CHI 2012): an adaptive low-pass whose cut-off rises with speed.

``fc = min_cutoff + beta |dx/dt|``; smoothing factor ``alpha = 1 / (1 + tau / dt)`` with
``tau = 1 / (2 pi fc)``. Works on vectors (speed = norm of the filtered derivative); a unit-quaternion
variant keeps the sign continuous and renormalises.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class OneEuroConfig:
    min_cutoff_hz: float = 1.0
    beta: float = 0.5             # cut-off increase per unit of speed (s/m for positions)
    d_cutoff_hz: float = 1.0      # cut-off of the derivative estimate


def _alpha(cutoff_hz: float, dt: float) -> float:
    tau = 1.0 / (2.0 * math.pi * cutoff_hz)
    return 1.0 / (1.0 + tau / dt)


class OneEuroFilter:
    """1€ filter on a small vector (scalar math per component: numpy costs more than the arithmetic here)."""

    def __init__(self, config: OneEuroConfig | None = None) -> None:
        self.config = config or OneEuroConfig()
        self._x: list[float] | None = None
        self._dx: list[float] | None = None
        self._t: float | None = None

    def reset(self) -> None:
        self._x = self._dx = None
        self._t = None

    @property
    def value(self) -> NDArray[np.float64] | None:
        return None if self._x is None else np.array(self._x)

    def __call__(self, stamp_s: float, x: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.array(self.filter(stamp_s, np.asarray(x, dtype=float).tolist()))

    def filter(self, stamp_s: float, xs: list[float]) -> list[float]:
        """One sample as Python floats (the per-frame path of the velocity estimator)."""
        if self._x is None or self._t is None or self._dx is None:
            self._x, self._dx, self._t = list(xs), [0.0] * len(xs), stamp_s
            return list(xs)
        dt = stamp_s - self._t
        if dt <= 0.0:
            return list(self._x)
        self._t = stamp_s
        cfg = self.config
        a_d = _alpha(cfg.d_cutoff_hz, dt)
        self._dx = [d + a_d * ((v - x0) / dt - d) for v, x0, d in zip(xs, self._x, self._dx, strict=True)]
        cutoff = cfg.min_cutoff_hz + cfg.beta * math.sqrt(sum(d * d for d in self._dx))
        a = _alpha(cutoff, dt)
        self._x = [x0 + a * (v - x0) for v, x0 in zip(xs, self._x, strict=True)]
        return list(self._x)


class OneEuroQuaternion:
    """1€ filter on a unit quaternion [w, x, y, z]: sign-continuous, renormalised."""

    def __init__(self, config: OneEuroConfig | None = None) -> None:
        self._f = OneEuroFilter(config)

    def reset(self) -> None:
        self._f.reset()

    def __call__(self, stamp_s: float, q_wxyz: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.array(self.filter(stamp_s, np.asarray(q_wxyz, dtype=float).tolist()))

    def filter(self, stamp_s: float, q_wxyz: list[float]) -> list[float]:
        prev = self._f._x
        if prev is not None and sum(a * b for a, b in zip(q_wxyz, prev, strict=True)) < 0.0:
            q_wxyz = [-v for v in q_wxyz]
        out = self._f.filter(stamp_s, q_wxyz)
        k = 1.0 / math.sqrt(sum(v * v for v in out))
        return [v * k for v in out]

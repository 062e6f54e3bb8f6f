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
    def __init__(self, config: OneEuroConfig | None = None) -> None:
        self.config = config or OneEuroConfig()
        self._x: NDArray[np.float64] | None = None
        self._dx: NDArray[np.float64] | None = None
        self._t: float | None = None

    def reset(self) -> None:
        self._x = self._dx = None
        self._t = None

    @property
    def value(self) -> NDArray[np.float64] | None:
        return None if self._x is None else self._x.copy()

    def __call__(self, stamp_s: float, x: NDArray[np.float64]) -> NDArray[np.float64]:
        x = np.asarray(x, dtype=float)
        if self._x is None or self._t is None or self._dx is None:
            self._x, self._dx, self._t = x.copy(), np.zeros_like(x), stamp_s
            return x.copy()
        dt = stamp_s - self._t
        if dt <= 0.0:
            return self._x.copy()
        self._t = stamp_s
        cfg = self.config
        dx = (x - self._x) / dt
        self._dx = self._dx + _alpha(cfg.d_cutoff_hz, dt) * (dx - self._dx)
        cutoff = cfg.min_cutoff_hz + cfg.beta * float(np.linalg.norm(self._dx))
        self._x = self._x + _alpha(cutoff, dt) * (x - self._x)
        return self._x.copy()


class OneEuroQuaternion:
    """1€ filter on a unit quaternion [w, x, y, z]: sign-continuous, renormalised."""

    def __init__(self, config: OneEuroConfig | None = None) -> None:
        self._f = OneEuroFilter(config)

    def reset(self) -> None:
        self._f.reset()

    def __call__(self, stamp_s: float, q_wxyz: NDArray[np.float64]) -> NDArray[np.float64]:
        q = np.asarray(q_wxyz, dtype=float)
        prev = self._f.value
        if prev is not None and float(q @ prev) < 0.0:
            q = -q
        out = self._f(stamp_s, q)
        return out / np.linalg.norm(out)

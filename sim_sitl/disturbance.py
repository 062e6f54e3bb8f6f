"""External pushes on the simulated vehicle (pure): scheduled force pulses, for paper 003's perturbation experiment.

Paper 003 ("System Stabilization"): the vehicle hovers and a person pushes it ~0.7 m along z, then y, then x;
it must be back within 3 s each time. Here a push is a force applied at the centre of mass (no torque), in the
arena's NED frame, constant over ``[start_s, start_s + duration_s)``: its impulse is ``force * duration``
(an impulse J on a body of mass m changes its velocity by J / m). A short pulse (tens of ms) is a kick; a longer
one (~0.5-1 s) is closer to a hand moving the vehicle.

Pushes come from the scenario (``ScenarioConfig.disturbances``: a scripted schedule, SITL time from its start,
needs no wire) or at run time from :meth:`DisturbanceSchedule.push` (what a command on a link would call).
:class:`sim_sitl.vehicle_sim.SimVehicle` asks :meth:`DisturbanceSchedule.force_ned_n` for every physics
substep and :class:`sim_sitl.world.World` adds it to the rotor and drag forces.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from quadlink.errors import ConfigError


@dataclass(frozen=True)
class Push:
    """One force pulse on the vehicle (arena NED, N), from ``start_s`` (SITL time) for ``duration_s``."""

    start_s: float = 0.0
    duration_s: float = 0.1
    force_ned_n: tuple[float, float, float] = (0.0, 0.0, 0.0)
    name: str = ""

    def __post_init__(self) -> None:
        if not (math.isfinite(self.start_s) and self.start_s >= 0.0):
            raise ConfigError(f"push {self.name!r}: start_s must be >= 0, got {self.start_s}")
        if not (math.isfinite(self.duration_s) and self.duration_s > 0.0):
            raise ConfigError(f"push {self.name!r}: duration_s must be > 0, got {self.duration_s}")
        if len(self.force_ned_n) != 3 or not all(math.isfinite(f) for f in self.force_ned_n):
            raise ConfigError(f"push {self.name!r}: force_ned_n must be 3 finite numbers (N)")

    @property
    def impulse_ned_n_s(self) -> NDArray[np.float64]:
        return np.asarray(self.force_ned_n, dtype=float) * self.duration_s

    @classmethod
    def from_impulse(cls, start_s: float, impulse_ned_n_s: tuple[float, float, float], duration_s: float = 0.05,
                     name: str = "") -> Push:
        """A pulse delivering ``impulse_ned_n_s`` (N s) over ``duration_s``."""
        f = np.asarray(impulse_ned_n_s, dtype=float) / duration_s
        return cls(start_s, duration_s, (float(f[0]), float(f[1]), float(f[2])), name)


class DisturbanceSchedule:
    """The pushes in effect at any time: the scripted ones plus those added at run time (they add up)."""

    def __init__(self, pushes: tuple[Push, ...] | list[Push] = ()) -> None:
        self._pushes: list[Push] = sorted(pushes, key=lambda p: p.start_s)

    @property
    def pushes(self) -> tuple[Push, ...]:
        return tuple(self._pushes)

    def push(self, now_s: float, force_ned_n: tuple[float, float, float], duration_s: float, name: str = "") -> Push:
        """Start a push now (a command's effect); returns it."""
        p = Push(now_s, duration_s, force_ned_n, name)
        self._pushes.append(p)
        self._pushes.sort(key=lambda q: q.start_s)
        return p

    def force_ned_n(self, t_s: float) -> NDArray[np.float64]:
        """The total external force at SITL time ``t_s`` (zero when no push is active)."""
        f = np.zeros(3)
        for p in self._pushes:
            if p.start_s > t_s:
                break
            if t_s < p.start_s + p.duration_s:
                f += np.asarray(p.force_ned_n, dtype=float)
        return f

    def active(self, t_s: float) -> bool:
        return any(p.start_s <= t_s < p.start_s + p.duration_s for p in self._pushes)

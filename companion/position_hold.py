"""Hold the place where the reference stops the vehicle (pure state machine, no clock, no I/O).

The reference is a velocity: when the safety constraints cut a push to zero (the vehicle at the safe distance, or
squeezed between map points so that no velocity meets every constraint), the autopilot is asked for v = 0, and a
velocity loop asked for zero does not stay in place: its tracking error integrates into a creep. With the board
flying on its own attitude estimate (~0.5-1 deg off) the CI corner push crept 3-6 cm/s toward the unseen wall for
six seconds with a zero reference and came to 0.36 m of it (0.19-0.52 m over eight runs): the repulsion did not
act because it never pushes toward sectors the map has not looked at, and a squeezed projection has nothing else.

The same creep with no command at all: a falsification finding (an offboard script that had stopped, 0.6 m from a
partition the camera did not see) crept 2-4 cm/s for six seconds to 0.27 m of it. PX4's position mode and
ArduPilot's LOITER hold a position when the sticks are centred; so does this: whenever the reference (after the
safety layer) is slower than ``engage_below_m_s`` horizontally, whatever the reason (blocked, nothing commanded,
HOLD), it anchors the odometry's position and adds ``-gain (p - anchor)`` (at most ``max_speed_m_s``) to the
reference; the anchor moves on with what is left of the reference (a slow way out of the safe distance is followed,
not fought). The anchor is a place the vehicle occupied a moment ago, so going back to it needs no map: it is the
one motion that is safe toward a sector the camera has not looked at. The hold lets go as soon as the reference is
faster than ``release_above_m_s`` — with nothing commanded, ``release_idle_above_m_s``, the correction's own
limit: a slow repulsion then moves the anchor (a failsafe landing's look round let go for one and drifted 0.35 m
with its velocity loop's error while it turned) — and re-anchors if the vehicle is more than ``max_offset_m`` from
the anchor (an odometry reset or a push it could not resist: going back that far is a move, not a hold).

Frames: the odometry's world (levelled, NED-like, yaw ``yaw_rad`` from the world x axis); the correction is added in
H (x along the heading), like every reference velocity.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from companion.reference import ReferenceOutput
from quadlink.frames import Rz


@dataclass(frozen=True)
class PositionHoldParams:
    enabled: bool = True
    gain_per_s: float = 1.0           # m/s of correction per m of offset from the anchor
    max_speed_m_s: float = 0.15       # the correction's limit (a creep of a few cm/s needs far less)
    engage_below_m_s: float = 0.02    # a reference slower than this (horizontally) holds the place
    release_above_m_s: float = 0.05   # a reference faster than this lets go
    release_idle_above_m_s: float = 0.15   # ... with nothing commanded (the correction's own limit): a slow
                                      # repulsion moves the anchor, it does not drop the hold (falsify s12 t32)
    max_offset_m: float = 0.5         # farther from the anchor than this: re-anchor where the vehicle is

    def __post_init__(self) -> None:
        if not self.gain_per_s >= 0.0:
            raise ValueError(f"gain_per_s must be >= 0, got {self.gain_per_s}")
        if not 0.0 <= self.max_speed_m_s <= 1.0:
            raise ValueError(f"max_speed_m_s must be in [0, 1] m/s, got {self.max_speed_m_s}")
        if not 0.0 <= self.engage_below_m_s <= min(self.release_above_m_s, self.release_idle_above_m_s):
            raise ValueError("need 0 <= engage_below_m_s <= release_above_m_s and release_idle_above_m_s, got "
                             f"{self.engage_below_m_s}, {self.release_above_m_s} and {self.release_idle_above_m_s}")
        if not self.max_offset_m > 0.0:
            raise ValueError(f"max_offset_m must be > 0, got {self.max_offset_m}")


def world_to_h(e_w_m: NDArray[np.float64], yaw_rad: float) -> NDArray[np.float64]:
    """A horizontal world vector in H (x along the heading ``yaw_rad``, y to its right): Rz(yaw)^T e."""
    return (Rz(yaw_rad)[:2, :2].T @ np.asarray(e_w_m, dtype=float)[:2]).astype(float)


def h_to_world(v_h: NDArray[np.float64], yaw_rad: float) -> NDArray[np.float64]:
    """A horizontal vector in H in the world (the inverse of :func:`world_to_h`): Rz(yaw) v."""
    return (Rz(yaw_rad)[:2, :2] @ np.asarray(v_h, dtype=float)[:2]).astype(float)


class PositionHold:
    """Anchors where the reference stops the vehicle and pulls it back to that place (see module doc)."""

    def __init__(self, params: PositionHoldParams | None = None) -> None:
        self.params = params or PositionHoldParams()
        self._anchor_w_m: NDArray[np.float64] | None = None
        self._stamp_s: float | None = None

    @property
    def anchor_w_m(self) -> NDArray[np.float64] | None:
        return None if self._anchor_w_m is None else self._anchor_w_m.copy()

    @property
    def holding(self) -> bool:
        return self._anchor_w_m is not None

    def reset(self) -> None:
        self._anchor_w_m = None
        self._stamp_s = None

    def step(self, stamp_s: float, ref: ReferenceOutput, position_w_m: ArrayLike | None, yaw_rad: float,
             odometry_ok: bool, in_control: bool) -> ReferenceOutput:
        """This frame's reference (frame stamp ``stamp_s``) with the hold's correction (``ref`` itself when not
        holding)."""
        p = self.params
        pos = None if position_w_m is None else np.asarray(position_w_m, dtype=float).reshape(-1)
        usable = (p.enabled and in_control and odometry_ok and pos is not None and pos.size >= 2
                  and bool(np.all(np.isfinite(pos[:2]))) and math.isfinite(yaw_rad))
        v = np.asarray(ref.v_ref_h_m_s, dtype=float)
        speed = math.hypot(float(v[0]), float(v[1])) if np.all(np.isfinite(v[:2])) else math.inf
        fresh = self._stamp_s is not None and math.isfinite(stamp_s)
        dt_s = min(max(stamp_s - self._stamp_s, 0.0), 0.2) if fresh and self._stamp_s is not None else 0.0
        self._stamp_s = stamp_s if math.isfinite(stamp_s) else self._stamp_s
        v_cmd = np.asarray(ref.v_operator_h_m_s, dtype=float)
        commanded = not (np.all(np.isfinite(v_cmd[:2])) and math.hypot(float(v_cmd[0]), float(v_cmd[1]))
                         <= p.engage_below_m_s)
        release = p.release_above_m_s if commanded else p.release_idle_above_m_s
        if not usable or speed > (release if self.holding else p.engage_below_m_s):
            self._anchor_w_m = None
            return ref
        assert pos is not None
        here = pos[:2].copy()
        if self._anchor_w_m is not None:
            self._anchor_w_m = self._anchor_w_m + dt_s * h_to_world(v[:2], yaw_rad)
        if self._anchor_w_m is None or float(np.linalg.norm(here - self._anchor_w_m)) > p.max_offset_m:
            self._anchor_w_m = here
        correction = -p.gain_per_s * world_to_h(here - self._anchor_w_m, yaw_rad)
        size = float(np.linalg.norm(correction))
        if size > p.max_speed_m_s:
            correction *= p.max_speed_m_s / size
        if size == 0.0:
            return ref
        out = v.copy()
        out[:2] += correction
        return dataclasses.replace(ref, v_ref_h_m_s=out)

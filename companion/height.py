"""The vehicle's height for the safety layer: the odometry's, held to the floor the camera sees (pure).

The reference counts the height from the take-off pose (:func:`companion.reference.reference_velocity`: 0 on
the landing gear, ``takeoff_height_m`` below the body centre's height above the floor). The odometry gives
that height as long as it started on the ground and does not drift; neither holds in general (campaign
flight 28: the odometry started 0.2 m up, and the climb came 0.2 m closer to a 2.14 m ceiling than its limit;
CI: a full climb in paper-arena came within 0.24 m of the ceiling the same way).

:func:`perception.floor.measure_floor` measures the body centre's height above the floor in each depth
image where the floor is in view. This estimator keeps the odometry's smooth, fast height and learns the
offset between it and the floor's (a first-order filter, ``time_constant_s``); without a floor in view the
offset is kept. With the odometry lost, the floor of the current frame alone gives the height (or nothing).

The floor is the lowest surface: once the offset is learnt, a "floor" more than ``max_rise_m`` above the one
tracked is the top of something the camera sees without the floor (a box, a desk) and is not taken; a deeper
one is (the tracked one was a top, or the odometry drifted). A vehicle turning on the spot over a 1.37 m box
saw only its top for a second, its height fell 1.3 m within 0.5 s, the autopilot declared its odometry lost and
landed on the box (campaign 7, flight 8, re-flown with the failsafe's look round).
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class HeightParams:
    """``takeoff_height_m``: the body centre above the floor on the landing gear (where the odometry's height
    is 0); ``time_constant_s``: how fast the floor's measurements pull the odometry's height; 0 disables
    the floor (the odometry's height alone, taken as verified); ``fix_max_age_s``: how long after the last
    floor seen the height still counts as verified."""

    takeoff_height_m: float = 0.1
    time_constant_s: float = 0.5
    fix_max_age_s: float = 4.0
    max_rise_m: float = 0.25   # a surface this much above the tracked floor is an object's top (the landing
                               # check's min_top_m: lower tops are landed on, and count as floor here too)
    drift_m_s: float = 0.01    # how fast the odometry's height may drift from the floor's while none is seen


MAX_UNCERTAINTY_M = 0.3   # the drift bound stops growing here (30 s without the floor): a vehicle over a dark floor
                          # is sent no lower than 0.3 m under its ceiling limit


class HeightEstimator:
    """Height above the take-off pose (m, up), fused per camera frame; see the module's docstring."""

    def __init__(self, params: HeightParams) -> None:
        self.params = params
        self.offset_m: float | None = None       # floor's height minus the odometry's, filtered
        self._last_floor_s: float | None = None
        self.height_m: float | None = None       # the last estimate

    def verified(self, stamp_s: float) -> bool:
        """The height was checked against the floor within ``fix_max_age_s`` (or the floor is not used)."""
        if self.params.time_constant_s <= 0.0:
            return self.height_m is not None
        return self._last_floor_s is not None and 0.0 <= stamp_s - self._last_floor_s <= self.params.fix_max_age_s

    def uncertainty_m(self, stamp_s: float) -> float:
        """How far the height may have drifted since the floor last checked it: ``drift_m_s`` per second (the
        odometry's vertical drift; the floor is out of range high up, in a 2.4 m room above ~1.8 m). The ceiling
        limit keeps this much more (:func:`companion.vertical_limits.ceiling_height_m`): flying at 1.9 m with no
        floor in view for 7 s, the odometry's height rose 1.5 cm while the vehicle rose 5 cm, and an entry 0.1 m
        high took the vehicle to 0.392 m of the ceiling (falsify seed 4 on 601b29b: six flights at 0.392-0.399 m).
        0 with the floor not used; never seen: 0 (nothing was learnt to drift from)."""
        if self.params.time_constant_s <= 0.0 or self._last_floor_s is None:
            return 0.0
        return min(self.params.drift_m_s * max(stamp_s - self._last_floor_s, 0.0), MAX_UNCERTAINTY_M)

    def update(self, stamp_s: float, odometry_height_m: float | None, floor_height_m: float | None) -> float | None:
        """The height at ``stamp_s`` from the odometry's height (above its start; None = lost) and the body
        centre's height above the floor seen in this frame (None = not in view)."""
        p = self.params
        floor_m = None   # the floor's height above the take-off pose
        if p.time_constant_s > 0.0 and floor_height_m is not None and math.isfinite(floor_height_m):
            floor_m = floor_height_m - p.takeoff_height_m
        odo_m = odometry_height_m if odometry_height_m is not None and math.isfinite(odometry_height_m) else None
        if odo_m is not None and floor_m is not None and self.offset_m is not None \
                and floor_m - odo_m < self.offset_m - p.max_rise_m:
            floor_m = None   # higher than the floor tracked: an object's top, not the floor (see the module doc)
        if odo_m is not None and floor_m is not None:
            innovation = floor_m - odo_m
            if self.offset_m is not None and innovation > self.offset_m + p.max_rise_m:
                self.offset_m = innovation   # deeper than the floor tracked: that was a top, this is the floor
            elif self.offset_m is None or self._last_floor_s is None:
                self.offset_m = innovation
            else:
                dt = max(stamp_s - self._last_floor_s, 0.0)
                self.offset_m += (1.0 - math.exp(-dt / p.time_constant_s)) * (innovation - self.offset_m)
            self._last_floor_s = stamp_s
        if odo_m is not None:
            self.height_m = odo_m + (self.offset_m or 0.0)
        else:
            self.height_m = floor_m
        return self.height_m

    def summary(self) -> str:
        """The height and the floor's offset for the progress line."""
        h, off = self.height_m, self.offset_m
        return "height ?" if h is None else f"height {h:.2f} m (floor {'?' if off is None else f'{off:+.2f}'})"

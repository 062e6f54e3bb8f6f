"""Vertical safety: a ceiling and a floor margin from what the vehicle can know (issue 14; pure).

The camera looks 30 deg down and never sees the ceiling, so the climb is bounded by what is configured,
like PX4's (``GF_MAX_VER_DIST``) and ArduPilot's (``FENCE_ALT_MAX``) altitude fences: a maximum height
above the take-off floor and/or the room's height (its ceiling, minus the safe distance). Ceiling points
that the obstacle map holds (seen earlier, e.g. under a low beam) act through the reference's 3D
constraints (:mod:`companion.obstacle_points`, ``out_of_band_3d``).

The height is the odometry's, above the take-off floor (NED: height = -z of the position). Both limits
use the reference's closing-speed law with its stopping distance (:func:`companion.avoidance.
limit_speed_toward_obstacles`): the climb speed is at most ``k (h_max - h - t_stop max(v_up, 0))``, the
descent speed near the floor at most ``k (h - h_min - t_stop max(v_down, 0))`` — zero at ``h_min`` and
negative (climb back) below it. The floor is exempt only for take-off and landing, which the autopilot
flies (TAKEOFF/LAND modes), not this reference.

With the height unknown (odometry lost) no climb is allowed toward a configured ceiling and no descent is
allowed at all: the vehicle holds its altitude (the mode machine holds it anyway). With the height not
*verified* — no floor seen for a while (:class:`companion.height.HeightEstimator`), so it rests on the
odometry alone, whose vertical scale can be far off while the camera sees only a close wall (campaign
2026-12-03 flight 5: a 0.94 m climb measured as 0.35 m, 0.10 m from a 2.24 m ceiling) — no climb is allowed
toward a configured ceiling either; descending and the floor margin still work on the estimate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from quadlink.safety import SAFE_DISTANCE_M


@dataclass(frozen=True)
class VerticalParams:
    """Configured vertical limits (m, above the take-off floor) and the law's gain and stopping time.

    ``max_height_m``: the altitude fence (None = none). ``room_height_m``: the ceiling's height as the operator
    entered it (None = unknown); the vehicle keeps ``safe_distance_m`` below it, and ``room_height_error_m`` more:
    an entry is a tape measure's reading or a guess, and one 0.10 m high put a campaign flight 0.34 m from a
    2.10 m ceiling. ``floor_min_height_m``: the lowest height the reference flies to (the descent slows toward it
    from ``floor_min_height_m + max_descent / gain``).
    """

    max_height_m: float | None = None
    room_height_m: float | None = None
    safe_distance_m: float = SAFE_DISTANCE_M
    floor_min_height_m: float = 0.3
    gain_per_s: float = 1.2
    stopping_time_s: float = 0.8
    room_height_error_m: float = 0.0


@dataclass(frozen=True)
class VerticalLimits:
    """The vertical limits in force at one instant (for the ground station; m and m/s, up positive).

    ``ceiling_height_m``: the highest height the reference flies to (inf: no limit); ``floor_height_m``
    the lowest; ``max_climb_m_s`` / ``max_descent_m_s``: the speed bounds now (negative: the vehicle is
    sent back, down resp. up); ``height_m``: the height they were computed from (nan: unknown)."""

    ceiling_height_m: float
    floor_height_m: float
    max_climb_m_s: float
    max_descent_m_s: float
    height_m: float

    @property
    def limiting(self) -> bool:
        return math.isfinite(self.max_climb_m_s) or math.isfinite(self.max_descent_m_s)


def ceiling_height_m(params: VerticalParams, height_uncertainty_m: float = 0.0) -> float:
    """The highest height the vehicle's centre may reach: the fence, the room's ceiling as entered minus its possible
    error, the safe distance and how far the height may have drifted since the floor last checked it
    (``height_uncertainty_m``, :meth:`companion.height.HeightEstimator.uncertainty_m`)."""
    limits = [math.inf]
    if params.max_height_m is not None:
        limits.append(params.max_height_m)
    if params.room_height_m is not None:
        drift = height_uncertainty_m if math.isfinite(height_uncertainty_m) and height_uncertainty_m > 0.0 else 0.0
        limits.append(params.room_height_m - max(params.room_height_error_m, 0.0) - params.safe_distance_m - drift)
    return min(limits)


def vertical_limits(height_m: float | None, v_up_est_m_s: float | None, params: VerticalParams,
                    height_verified: bool = True, height_uncertainty_m: float = 0.0,
                    baro_height_m: float | None = None) -> VerticalLimits:
    """The climb and descent bounds at ``height_m`` (above take-off) moving up at ``v_up_est_m_s``;
    ``height_verified`` False: no climb toward a configured ceiling (see the module's docstring);
    ``height_uncertainty_m``: the height's possible drift, kept from the room's ceiling too; ``baro_height_m``: the
    autopilot's barometer-fused height on the same scale (None: none fresh): the ceiling is kept from the higher of
    the two. An odometry degrading before it fails can stop measuring a climb: the search's trial 31 (seed 15,
    ``392dd2d``) read 1.85-1.93 m while the vehicle rose to 2.2 m under a 2.0 m limit, the barometer's height
    within 0.1 m of the truth all along."""
    top = ceiling_height_m(params, height_uncertainty_m)
    bottom = params.floor_min_height_m
    if height_m is None or not math.isfinite(height_m):
        return VerticalLimits(top, bottom, 0.0 if math.isfinite(top) else math.inf, 0.0, math.nan)
    v_up = 0.0 if v_up_est_m_s is None or not math.isfinite(v_up_est_m_s) else v_up_est_m_s
    k, t_stop = params.gain_per_s, params.stopping_time_s
    h_top = height_m if baro_height_m is None or not math.isfinite(baro_height_m) else max(height_m, baro_height_m)
    climb = k * (top - h_top - t_stop * max(v_up, 0.0)) if math.isfinite(top) else math.inf
    if not height_verified and math.isfinite(top):
        climb = min(climb, 0.0)
    descent = k * (height_m - bottom - t_stop * max(-v_up, 0.0))
    return VerticalLimits(top, bottom, climb, descent, height_m)


def apply_vertical_limits(v_h_m_s: ArrayLike, limits: VerticalLimits) -> tuple[NDArray[np.float64], bool]:
    """Clamp the vertical component of a velocity in H (NED: z down) to the limits; changed?"""
    v = np.array(v_h_m_s, dtype=float)
    up = -v[2]
    clamped = min(up, limits.max_climb_m_s)
    clamped = max(clamped, -limits.max_descent_m_s)
    if limits.max_climb_m_s < -limits.max_descent_m_s:   # cannot happen with a sane config: hold
        clamped = 0.0
    changed = clamped != up
    v[2] = -clamped
    return v, bool(changed)

"""Is there something under the vehicle to land on other than the floor? (pure; issue 14)

The autopilot's LAND descends vertically wherever the vehicle is: over a desk or a box it sets the vehicle down
on the object's top, its props beside the edge (campaign 2026-12-05 flights 21 and 39: 0.10 m from a desk's
top). The camera looks ahead and down, so what is under the vehicle now was seen on the way there; the obstacle
map carries it (eq. 14) and holds it while it is within reach (``perception.obstacle_map``, near field).

:func:`object_below` finds the highest map point under the vehicle's footprint that is not the floor: within
``footprint_radius_m`` horizontally, below the vehicle, and more than the reference's ``floor_margin_m`` above
the take-off floor. A commanded landing (a ground station's LAND) over one is refused (:mod:`companion.gcs_commands`). A
failsafe landing (:mod:`companion.modes`) first moves clear: :func:`clearing_velocity` points away from the
object (from the centroid of its points around the vehicle), and the reference pipeline flies it like a
script's command (no motion toward unseen sectors, the safe distance, the closing-speed law).
With the height above the floor unknown, the floor cannot be told from an object and nothing is reported.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from companion.obstacle_points import finite_rows


@dataclass(frozen=True)
class LandingSpotParams:
    """``enabled``: refuse commanded landings over an object; ``footprint_radius_m``: the vehicle's reach (arm +
    prop, MK-Quadro ~0.3 m) plus the spacing of the map's samples of an object's top (one per image sector:
    a failsafe landing that moved 0.25 m off a desk's sample at a 0.4 m footprint came down on the desk)."""

    enabled: bool = True
    footprint_radius_m: float = 0.6   # arm + prop (0.3 m) + the spacing of the map's samples of a top (~0.3 m)
    clearing_speed_m_s: float = 0.25   # a failsafe landing moves clear of an object below at this speed

    def __post_init__(self) -> None:
        if not self.footprint_radius_m > 0.0:
            raise ValueError(f"footprint_radius_m must be > 0, got {self.footprint_radius_m}")
        if not 0.0 < self.clearing_speed_m_s <= 1.0:
            raise ValueError(f"clearing_speed_m_s must be in (0, 1] m/s, got {self.clearing_speed_m_s}")


@dataclass(frozen=True)
class ObjectBelow:
    """The highest non-floor point under the footprint: its height above the take-off floor and horizontal
    offset from the vehicle (m)."""

    top_height_m: float
    offset_m: float

    def refusal(self) -> str:
        """The STATUSTEXT body of a refused landing (MAVLink's 50 characters after "companion: ")."""
        return f"land refused: object below, {self.top_height_m:.2f} m tall"


def _objects_below(points_h_m: ArrayLike | None, height_m: float | None, floor_margin_m: float
                   ) -> tuple[NDArray[np.float64], NDArray[np.float64]] | None:
    """The finite map points below the vehicle that are not the floor, and their heights above it."""
    if points_h_m is None or height_m is None or not math.isfinite(height_m):
        return None
    p = finite_rows(points_h_m)
    above_floor_m = height_m - p[:, 2]
    keep = (p[:, 2] > 0.0) & (above_floor_m > floor_margin_m)
    return p[keep], above_floor_m[keep]


def clearing_velocity(points_h_m: ArrayLike | None, height_m: float | None, params: LandingSpotParams,
                      floor_margin_m: float, fallback_yaw_rad: float) -> NDArray[np.float64]:
    """A horizontal velocity in H away from the object below: from the centroid of the object points within
    ``footprint_radius_m + 0.5`` m toward the vehicle, at ``clearing_speed_m_s``; over the middle of a wide
    object (the centroid under the vehicle) along ``fallback_yaw_rad`` (the camera's axis: the way it sees)."""
    below = _objects_below(points_h_m, height_m, floor_margin_m)
    direction = np.array([math.cos(fallback_yaw_rad), math.sin(fallback_yaw_rad)])
    if below is not None:
        p = below[0]
        near = p[:, 0] ** 2 + p[:, 1] ** 2 <= (params.footprint_radius_m + 0.5) ** 2
        if near.any():
            centroid = p[near, :2].mean(axis=0)
            r = float(np.hypot(*centroid))
            if r > 0.05:
                direction = -centroid / r
    return np.array([*(params.clearing_speed_m_s * direction), 0.0])


def object_below(points_h_m: ArrayLike | None, height_m: float | None, params: LandingSpotParams,
                 floor_margin_m: float) -> ObjectBelow | None:
    """The highest map point (H, vehicle at the origin, z down) under the footprint that is not the floor
    (higher than ``floor_margin_m`` above the take-off floor, ``height_m`` below the vehicle); None if there is
    none, or the check is off, or the height above the floor is unknown."""
    below = _objects_below(points_h_m, height_m, floor_margin_m) if params.enabled else None
    if below is None:
        return None
    p, above_floor_m = below
    r2 = p[:, 0] ** 2 + p[:, 1] ** 2
    under = r2 <= params.footprint_radius_m**2
    if not under.any():
        return None
    i = int(np.argmax(np.where(under, above_floor_m, -np.inf)))
    return ObjectBelow(float(above_floor_m[i]), float(math.sqrt(r2[i])))

"""Is there something under the vehicle to land on other than the floor? (pure; issue 14)

The autopilot's LAND descends vertically wherever the vehicle is: over a desk or a box it sets the vehicle down
on the object's top, its props beside the edge (campaign 2026-12-05 flights 21 and 39: 0.10 m from a desk's
top). The camera looks ahead and down, so what is under the vehicle now was seen on the way there: the obstacle
map carries it (eq. 14) for a while, and :class:`BelowMemory` keeps it for the rest of the flight.

:func:`object_below` finds the highest point under the vehicle's footprint that is not the floor: within
``footprint_radius_m`` horizontally, below the vehicle, and higher above the take-off floor than ``min_top_m``
(and the reference's ``floor_margin_m``). A commanded landing (a ground station's LAND) over one is refused
(:mod:`companion.gcs_commands`). A failsafe landing (:mod:`companion.modes`) first moves clear:
:func:`clearing_azimuth_rad` picks a seen way with free space, away from the object if it can, and
the reference pipeline flies it like a script's command (no motion toward unseen sectors, the safe distance,
the closing-speed law). With the height above the floor unknown, the floor cannot be told from an object and
nothing is reported.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from companion.avoidance import remove_toward_unknown, sector_index
from companion.obstacle_points import finite_rows


@dataclass(frozen=True)
class LandingSpotParams:
    """``enabled``: refuse commanded landings over an object; ``footprint_radius_m``: the vehicle's reach (arm +
    prop, MK-Quadro ~0.3 m) plus a margin, less than the safe distance (at 0.6 m a box-side wall the vehicle
    rested beside counted as "below" and the failsafe never found a clear spot). The map samples a top once per
    image sector; :class:`BelowMemory` gathers the samples of every frame."""

    enabled: bool = True
    footprint_radius_m: float = 0.4   # arm + prop (0.3 m) + margin; under the safe distance, so a wall the
                                       # vehicle rests beside (0.45 m) is not "below" it
    clearing_speed_m_s: float = 0.25   # a failsafe landing moves clear of an object below at this speed
    min_top_m: float = 0.25            # lower tops are landed on (the gear takes them; the floor's samples, with
                                       # the height's error, must never read as an object)
    clear_margin_m: float = 0.15       # once a failsafe landing moves clear, the spot counts as clear only with
                                       # nothing within footprint + this: the map's tops can read a few cm
                                       # optimistic, and a landing that stopped just past the footprint came
                                       # down 0.33 m from the box (campaign 9, flight 2)

    def __post_init__(self) -> None:
        if not self.footprint_radius_m > 0.0:
            raise ValueError(f"footprint_radius_m must be > 0, got {self.footprint_radius_m}")
        if not 0.0 < self.clearing_speed_m_s <= 1.0:
            raise ValueError(f"clearing_speed_m_s must be in (0, 1] m/s, got {self.clearing_speed_m_s}")
        if not self.min_top_m >= 0.0:
            raise ValueError(f"min_top_m must be >= 0, got {self.min_top_m}")
        if not 0.0 <= self.clear_margin_m <= 1.0:
            raise ValueError(f"clear_margin_m must be in [0, 1] m, got {self.clear_margin_m}")


@dataclass(frozen=True)
class ObjectBelow:
    """The highest non-floor point under the footprint: its height above the take-off floor and horizontal
    offset from the vehicle (m)."""

    top_height_m: float
    offset_m: float

    def refusal(self) -> str:
        """The STATUSTEXT body of a refused landing (MAVLink's 50 characters after "companion: ")."""
        return f"land refused: object below, {self.top_height_m:.2f} m tall"


#: a candidate top with a surface point within this horizontal distance at the vehicle's own level belongs to a wall,
#: a column or a box side *beside* the vehicle, not to an object *below* it (issue 30: MAVSDK's LAND was refused
#: 0.5 m from a wall, its lower part read as a top under the footprint)
BESIDE_RADIUS_M = 0.15
LEVEL_BAND_M = (-0.5, 0.10)   # "the vehicle's level": from 0.5 m above the centre of mass to 0.1 m below it (H, z down)


def _beside(candidates: NDArray[np.float64], context: NDArray[np.float64], within_m: float) -> NDArray[np.bool_]:
    """Which candidates (N x 3, H) lie under a surface that reaches up to the vehicle's level (``context`` M x 3):
    a wall or column the vehicle rests beside, whose lower part a drift margin or a footprint can put "below" it. A
    top of an object below the vehicle has nothing at the vehicle's level above it (else the vehicle would be in it).
    Only context within ``within_m`` (+ the radius) of the vehicle counts, which keeps the per-frame tree small."""
    if not candidates.shape[0] or not context.shape[0]:
        return np.zeros(candidates.shape[0], dtype=bool)
    lo, hi = LEVEL_BAND_M
    z = context[:, 2]
    near = (z >= lo) & (z <= hi)
    if math.isfinite(within_m):
        reach = within_m + BESIDE_RADIUS_M
        near &= context[:, 0] ** 2 + context[:, 1] ** 2 <= reach * reach
    level = context[near]
    if not level.shape[0]:
        return np.zeros(candidates.shape[0], dtype=bool)
    d, _ = cKDTree(level[:, :2]).query(candidates[:, :2], distance_upper_bound=BESIDE_RADIUS_M)
    return np.isfinite(d)


def _objects_below(points_h_m: ArrayLike | None, height_m: float | None, floor_margin_m: float,
                   within_m: float = math.inf, context_h_m: ArrayLike | None = None,
                   ) -> tuple[NDArray[np.float64], NDArray[np.float64]] | None:
    """The finite map points below the vehicle that are not the floor (and within ``within_m`` of it
    horizontally), and their heights above the floor, less those beside the vehicle (:func:`_beside`, against
    ``context_h_m``, default the points themselves). One mask over the map's columns, one gather: run on every
    frame over up to 20,000 particles (benchmarks/bench_safety_map.py)."""
    if points_h_m is None or height_m is None or not math.isfinite(height_m):
        return None
    p = finite_rows(points_h_m)
    z = p[:, 2]
    keep = (z > 0.0) & (z < height_m - floor_margin_m)
    if math.isfinite(within_m):
        x, y = p[:, 0], p[:, 1]
        keep &= x * x + y * y <= within_m * within_m
    q = p.take(np.flatnonzero(keep), axis=0)
    if q.shape[0]:
        q = q[~_beside(q, p if context_h_m is None else finite_rows(context_h_m), within_m)]
    return q, height_m - q[:, 2]


CLEARING_CANDIDATES = 12      # directions tried for the way off, every 30 deg
CLEARING_LOOKAHEAD_M = 3.0    # free space counted up to this far along a direction


def clearing_azimuth_rad(points_h_m: ArrayLike | None, height_m: float | None, params: LandingSpotParams,
                         floor_margin_m: float, fallback_yaw_rad: float, sectors_m: ArrayLike | None = None,
                         guard_rad: float = 0.0, sector_offset_rad: float = 0.0,
                         room: Callable[[float], bool] | None = None) -> float | None:
    """The way off the object below, an azimuth in H: of twelve directions, those the map has looked at (no
    sector of ``sectors_m`` within ``guard_rad`` unknown: the reference would not fly the others), the one with
    the most free space ahead (up to 3 m, from the sectors) plus half a metre for pointing straight away from
    the object (from the centroid of its points within ``footprint_radius_m + 0.5`` m toward the vehicle).
    ``fallback_yaw_rad`` (the camera's axis: the way it sees) when no sectors are known. Chosen once per
    clearing (the daemon keeps it in the world): re-chosen every frame, the way off a desk flipped between
    straight back and the camera's axis and went nowhere (a re-flown campaign flight). With ``room`` (a predicate
    on an azimuth in H: :func:`room_to_clear`) only the directions it allows are taken; None if none is. A direction
    along which the footprint does not clear the object within the look-ahead is no way off (campaign 20261216's
    flight 13: the one way with room led along a box that filled a corridor's end; taken, it kept the narrow rule
    from being asked, and the landing came down the box's side at 0.272 m after 30 s)."""
    away: NDArray[np.float64] | None = None
    tops = _objects_below(points_h_m, height_m, max(floor_margin_m, params.min_top_m),
                          within_m=CLEARING_LOOKAHEAD_M + params.footprint_radius_m)
    tops_xy = np.zeros((0, 2)) if tops is None else tops[0][:, :2]
    if tops is not None:
        # the object's own points: those of the tops within reach of the footprint
        p = tops_xy[np.hypot(tops_xy[:, 0], tops_xy[:, 1]) <= params.footprint_radius_m + 0.5]
        if p.shape[0]:
            centroid = p[:, :2].mean(axis=0)
            r = float(np.hypot(*centroid))
            if r > 0.05:
                away = -centroid / r
    if sectors_m is None:
        az0 = fallback_yaw_rad if away is None else math.atan2(away[1], away[0])
        return az0 if room is None or room(az0) else None
    s = np.asarray(sectors_m, dtype=float).ravel()
    n = s.size
    best: float | None = fallback_yaw_rad if room is None else None
    best_score = -math.inf
    for k in range(CLEARING_CANDIDATES):
        az = fallback_yaw_rad + k * 2.0 * math.pi / CLEARING_CANDIDATES
        u = np.array([math.cos(az), math.sin(az), 0.0])
        if n == 0 or remove_toward_unknown(u, s, guard_rad, sector_offset_rad)[1]:
            continue
        if room is not None and not room(az):
            continue
        to_clear_m = distance_to_clear_m(tops_xy, az, params.footprint_radius_m)
        if to_clear_m > CLEARING_LOOKAHEAD_M:   # along the object as far as the look-ahead: no way off it
            continue
        width = 2.0 * math.pi / n
        steps = int(math.ceil(guard_rad / width))
        free = min(float(s[sector_index(az + j * width, n, sector_offset_rad)]) for j in range(-steps, steps + 1))
        score = min(free, CLEARING_LOOKAHEAD_M) + (0.5 * float(u[:2] @ away) if away is not None else 0.0) \
            - to_clear_m
        if score > best_score:
            best, best_score = az, score
    return best


def distance_to_clear_m(tops_xy_m: NDArray[np.float64], azimuth_rad: float, footprint_radius_m: float,
                        step_m: float = 0.1) -> float:
    """How far along ``azimuth_rad`` (H) the vehicle must move until no top of ``tops_xy_m`` (N x 2, H) is within
    its footprint: the way off one box should not lead over the next (campaign 7, flight 8, re-flown: the way
    off a box led 2.5 m on over another and the landing came down on its edge). ``CLEARING_LOOKAHEAD_M`` + 1 if
    there is no clear spot within the look-ahead."""
    if not tops_xy_m.shape[0]:
        return 0.0
    u = np.array([math.cos(azimuth_rad), math.sin(azimuth_rad)])
    along = np.arange(0.0, CLEARING_LOOKAHEAD_M + 1e-9, step_m)
    d2 = ((tops_xy_m[None, :, :] - along[:, None, None] * u[None, None, :]) ** 2).sum(axis=2)
    clear = ~(d2 <= footprint_radius_m**2).any(axis=1)
    return float(along[int(np.argmax(clear))]) if clear.any() else CLEARING_LOOKAHEAD_M + 1.0


ROOM_LATERAL_MARGIN_M = 0.15   # a clearing move passes nothing closer than min_distance_m + this to its side
NARROW_STOP_M = 0.4            # a narrow way off is free this far past where the footprint clears: the move goes on
                               # for land_clear_hold_s (1 s at 0.25 m/s) after the spot reads clear, then stops


def tops_xy_m(points_h_m: ArrayLike | None, height_m: float | None, params: LandingSpotParams,
              floor_margin_m: float) -> NDArray[np.float64]:
    """The tops of the objects below the vehicle's level within the clearing's look-ahead (N x 2, H), as
    :func:`clearing_azimuth_rad` sees them."""
    tops = _objects_below(points_h_m, height_m, max(floor_margin_m, params.min_top_m),
                          within_m=CLEARING_LOOKAHEAD_M + params.footprint_radius_m)
    return np.zeros((0, 2)) if tops is None else tops[0][:, :2]


def narrow_reach_m(tops_xy: NDArray[np.float64], azimuth_rad: float, params: LandingSpotParams) -> float:
    """How far a narrow way off (:func:`room_to_clear` with no lateral margin) must be free along ``azimuth_rad``:
    to where the footprint widened by ``clear_margin_m`` holds no top, and NARROW_STOP_M on."""
    return distance_to_clear_m(tops_xy, azimuth_rad, params.footprint_radius_m + params.clear_margin_m) + NARROW_STOP_M


def room_to_clear(band_points_h_m: ArrayLike, azimuth_rad: float, reach_m: float, min_distance_m: float,
                  lateral_margin_m: float = ROOM_LATERAL_MARGIN_M) -> bool:
    """Whether a failsafe landing may move clear along ``azimuth_rad`` (H): no obstacle point of the avoidance's
    height band (N x 3 in H, vehicle at the origin) in the path the move sweeps (ahead, within ``reach_m`` along
    the way and ``min_distance_m + lateral_margin_m`` to either side of it), and none anywhere nearer than
    ``min_distance_m`` (inside the safe distance the camera's blind zone can hide the obstacle: campaign 6's
    flight 6 moved from 0.41 m of one to 0.19 m). What lies behind the way off does not count: a vehicle that an
    operator left resting at the safe distance from a wall, over the edge of a box, landed beside the box at
    0.27 m of it when any point within reach counted (campaign 7, flight 8). Nor do walls the move runs past
    beyond the margin: in a 1.7 m corridor a cone of 100 deg either side of the way found every way blocked by
    the walls alongside, and the failsafe landed on the box (campaign 9, flight 2, re-flown: 0.14-0.29 m)."""
    p = finite_rows(band_points_h_m)
    if not p.shape[0]:
        return True
    r = np.hypot(p[:, 0], p[:, 1])
    if bool((r < min_distance_m).any()):
        return False
    u = np.array([math.cos(azimuth_rad), math.sin(azimuth_rad)])
    along = p[:, :2] @ u
    beside = np.abs(p[:, 0] * u[1] - p[:, 1] * u[0])
    in_path = (along > 0.0) & (along <= reach_m) & (beside < min_distance_m + lateral_margin_m)
    return not bool(in_path.any())


SURVEY_TURN_RAD = math.radians(300.0)   # a full turn less the camera's width: every way has been looked at
SURVEY_YAW_RATE_RAD_S = 0.7


class ClearingSurvey:
    """Before a failsafe landing picks its way off an object, the vehicle turns on the spot (about 7 s) so that
    the camera, which looks one way, has looked every way: in HOLD nothing pan-scans, and the ways the map had
    not looked at (behind the camera, often the open room) could not be chosen, so a vehicle over a box by a
    wall could only slide along the wall, had no room, and landed on the box (campaign 7, flight 8, re-flown)."""

    def __init__(self, turn_rad: float = SURVEY_TURN_RAD) -> None:
        self.turn_rad = turn_rad
        self.turned_rad = 0.0
        self._last_yaw_rad: float | None = None

    @property
    def done(self) -> bool:
        return self.turned_rad >= self.turn_rad

    def observe(self, yaw_rad: float) -> None:
        """The vehicle's heading now (any frame fixed to the world); counts the turn made since the last call."""
        if not math.isfinite(yaw_rad):
            return
        if self._last_yaw_rad is not None:
            self.turned_rad += abs((yaw_rad - self._last_yaw_rad + math.pi) % (2.0 * math.pi) - math.pi)
        self._last_yaw_rad = yaw_rad


CLEARING_LOOK_RAD = math.radians(20.0)   # the camera this close to the way off: move
CLEARING_YAW_GAIN_PER_S = 1.0
CLEARING_MAX_YAW_RATE_RAD_S = 0.5


def clearing_command(azimuth_rad: float, camera_yaw_rad: float, params: LandingSpotParams
                     ) -> tuple[NDArray[np.float64], float]:
    """The clearing command in H (velocity, yaw rate) along ``azimuth_rad``: turn the camera (at
    ``camera_yaw_rad`` in H) toward it, and move at ``clearing_speed_m_s`` once it looks within 20 deg of it."""
    error = (azimuth_rad - camera_yaw_rad + math.pi) % (2.0 * math.pi) - math.pi
    yaw_rate = max(-CLEARING_MAX_YAW_RATE_RAD_S, min(CLEARING_MAX_YAW_RATE_RAD_S, CLEARING_YAW_GAIN_PER_S * error))
    if abs(error) > CLEARING_LOOK_RAD:
        return np.zeros(3), yaw_rate
    return np.array([params.clearing_speed_m_s * math.cos(azimuth_rad),
                     params.clearing_speed_m_s * math.sin(azimuth_rad), 0.0]), yaw_rate


def object_below(points_h_m: ArrayLike | None, height_m: float | None, params: LandingSpotParams,
                 floor_margin_m: float, extra_radius_m: float = 0.0,
                 context_h_m: ArrayLike | None = None) -> ObjectBelow | None:
    """The highest point (H, vehicle at the origin, z down) under the footprint (widened by ``extra_radius_m``)
    that is not the floor (higher than ``floor_margin_m`` and ``min_top_m`` above the take-off floor, ``height_m``
    below the vehicle); None if there is none, or the check is off, or the height above the floor is unknown. A wall,
    a column or a box side beside the vehicle (a surface that reaches its level, in ``context_h_m`` — the map —
    or in ``points_h_m``) is never "below" it."""
    below = _objects_below(points_h_m, height_m, max(floor_margin_m, params.min_top_m),
                           within_m=params.footprint_radius_m + max(0.0, extra_radius_m),
                           context_h_m=context_h_m) if params.enabled else None
    if below is None or not below[1].size:
        return None
    p, above_floor_m = below
    i = int(np.argmax(above_floor_m))
    return ObjectBelow(float(above_floor_m[i]), float(math.hypot(p[i, 0], p[i, 1])))


class BelowMemory:
    """The tops of objects seen around and under the vehicle, kept in the odometry's world frame until it lands.

    The obstacle map forgets what is under the vehicle (the camera never looks there again; its particles age
    out, within 20 s near the vehicle), but a vehicle may hover over a desk for longer before it is asked to
    land: a re-flown campaign flight whose refused landing was followed by a failsafe landing came down on the
    desk the map had forgotten. Each frame :meth:`observe` keeps the non-floor points below the vehicle within
    ``footprint_radius_m + 0.5`` m, thinned to one per ``grid_m`` cell with the highest top; :meth:`points_h`
    gives them back in H for :func:`object_below` and :func:`clearing_azimuth_rad`. In the odometry's frame they
    drift with the odometry (centimetres over a flight), not with the map's noise."""

    def __init__(self, params: LandingSpotParams, grid_m: float = 0.1, max_cells: int = 2000) -> None:
        self.params, self.grid_m, self.max_cells = params, grid_m, max_cells
        self._tops: dict[tuple[int, int], float] = {}   # world cell -> highest top above the floor (m)

    def __len__(self) -> int:
        return len(self._tops)

    def clear(self) -> None:
        self._tops.clear()

    def observe(self, points_h_m: ArrayLike | None, height_m: float | None, floor_margin_m: float,
                position_w_m: ArrayLike | None, yaw_rad: float) -> None:
        """Keep the objects below the vehicle at ``position_w_m`` (the odometry's world, NED) heading ``yaw_rad``."""
        if not self.params.enabled or position_w_m is None or not math.isfinite(yaw_rad):
            return
        pos = np.asarray(position_w_m, dtype=float).ravel()
        if pos.size < 2 or not np.all(np.isfinite(pos[:2])):
            return
        below = _objects_below(points_h_m, height_m, max(floor_margin_m, self.params.min_top_m),
                               within_m=self.params.footprint_radius_m + 0.5)
        if below is None or not below[1].size:
            return
        p, t = below
        c, s = math.cos(yaw_rad), math.sin(yaw_rad)
        x = pos[0] + c * p[:, 0] - s * p[:, 1]
        y = pos[1] + s * p[:, 0] + c * p[:, 1]
        ix = np.floor(x / self.grid_m).astype(np.int64)
        iy = np.floor(y / self.grid_m).astype(np.int64)
        # the highest top per cell first (a frame holds thousands of points over a few hundred cells): sorted by
        # cell, then top, the last of each cell's run is its highest
        order = np.lexsort((t, iy, ix))
        ix, iy, t = ix[order], iy[order], t[order]
        last = np.ones(ix.size, dtype=bool)
        last[:-1] = (ix[1:] != ix[:-1]) | (iy[1:] != iy[:-1])
        for i, j, h in zip(ix[last].tolist(), iy[last].tolist(), t[last].tolist(), strict=True):
            if h > self._tops.get((i, j), -math.inf):
                self._tops[(i, j)] = h
        while len(self._tops) > self.max_cells:   # the oldest cells first (dicts keep insertion order)
            del self._tops[next(iter(self._tops))]

    def points_h(self, position_w_m: ArrayLike | None, yaw_rad: float, height_m: float | None) -> NDArray[np.float64]:
        """The remembered tops as points in H (vehicle at ``position_w_m``, heading ``yaw_rad``, ``height_m`` above
        the floor), N x 3; none if the pose or the height is unknown."""
        if not self._tops or position_w_m is None or height_m is None or not math.isfinite(height_m) \
                or not math.isfinite(yaw_rad):
            return np.zeros((0, 3))
        pos = np.asarray(position_w_m, dtype=float).ravel()
        if pos.size < 2 or not np.all(np.isfinite(pos[:2])):
            return np.zeros((0, 3))
        cells = np.array(list(self._tops.keys()), dtype=float)
        tops = np.array(list(self._tops.values()))
        dx = (cells[:, 0] + 0.5) * self.grid_m - pos[0]
        dy = (cells[:, 1] + 0.5) * self.grid_m - pos[1]
        c, s = math.cos(yaw_rad), math.sin(yaw_rad)
        return np.column_stack([c * dx + s * dy, -s * dx + c * dy, height_m - tops])

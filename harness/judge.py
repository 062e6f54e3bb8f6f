"""The one judge of a flight's safety and mobility, from the SITL's truth and the scenario's geometry (pure).

Tests, the demo's report, campaigns and the falsification search all judge with this module (issue 29: one
judge, no blind spot). Clearance is the distance from the vehicle's centre of mass (as paper 000's Fig. 8) to
every surface that is not the floor: the walls' and ceiling's inner faces and every object (yawed boxes, upright
cylinders), over the **whole** flight, take-off and touchdown included. Touching the floor (or a rug, which is
floor) is landing; touching the top or the side of a box on the way down is not.

Mobility is judged beside it (a vehicle that never moved is trivially safe): how far from the start the vehicle
went, how high it flew and how long its path was.

Geometry: the truth's LOCAL_POSITION_NED is relative to the start position (arena NED, not rotated), so the arena
position is ``start + p_local``; the start is on the floor, with the centre of mass ``rest_height_m`` above it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from quadlink.safety import CLEARANCE_BOUND_M
from sim_sitl.config import PhysicsConfig, ScenarioConfig, load_scenario
from sim_sitl.scene import build_scene

Array = NDArray[np.float64]



# ---------------------------------------------------------------- geometry
def box_distance_m(p_ned_m: Array, centre_ned_m: Array, size_m: Array, yaw_rad: float) -> float:
    """Distance from a point to a solid box turned by ``yaw_rad`` about the down axis (0 inside)."""
    d = np.asarray(p_ned_m, dtype=float) - np.asarray(centre_ned_m, dtype=float)
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    local = np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1], d[2]])   # Rz(yaw)^T d
    q = np.abs(local) - np.asarray(size_m, dtype=float) / 2.0
    return float(np.linalg.norm(np.maximum(q, 0.0)))


def cylinder_distance_m(p_ned_m: Array, centre_ned_m: Array, radius_m: float, height_m: float) -> float:
    """Distance from a point to a solid upright cylinder (0 inside)."""
    d = np.asarray(p_ned_m, dtype=float) - np.asarray(centre_ned_m, dtype=float)
    radial = max(math.hypot(d[0], d[1]) - radius_m, 0.0)
    axial = max(abs(d[2]) - height_m / 2.0, 0.0)
    return math.hypot(radial, axial)


@dataclass(frozen=True)
class Clearance:
    """True distances from the centre of mass (m) to the walls, the objects, the ceiling and the floor (rugs
    included); ``nearest_name`` names the nearest non-floor surface."""

    wall_m: float
    object_m: float
    ceiling_m: float
    floor_m: float
    nearest_name: str

    @property
    def surface_m(self) -> float:
        """The judged clearance: the nearest non-floor surface."""
        return min(self.wall_m, self.object_m, self.ceiling_m)


class ArenaGeometry:
    """A scenario's bodies as plain geometry (the same bodies :func:`sim_sitl.scene.build_scene` gives pybullet)."""

    def __init__(self, scenario: ScenarioConfig | str) -> None:
        self.scenario = load_scenario(scenario) if isinstance(scenario, str) else scenario
        self.scene = build_scene(self.scenario)
        # the scenario's own objects (partitions, blocks and stubs marked "wall" among them) come after the room's
        # slabs, whose faces are the planes of clearance() below
        self.objects = self.scene.bodies[len(self.scene.bodies) - len(self.scenario.objects):]
        self.start_ned_m = np.array([*self.scenario.start.position_m[:2], 0.0])
        self.room = self.scenario.room

    def clearance(self, p_arena_ned_m: Array) -> Clearance:
        p = np.asarray(p_arena_ned_m, dtype=float)
        nx, ny = self.room.size_m
        wall = min(p[0] + nx / 2, nx / 2 - p[0], p[1] + ny / 2, ny / 2 - p[1]) if self.room.walls else math.inf
        ceiling = p[2] + self.room.height_m if self.room.ceiling else math.inf
        floor = -p[2]
        best, name = math.inf, "wall"
        for b in self.objects:
            if b.kind == "box":
                d = box_distance_m(p, np.array(b.centre_ned_m), np.array(b.size_m), b.yaw_rad)
            else:
                d = cylinder_distance_m(p, np.array(b.centre_ned_m), b.radius_m, b.size_m[2])
            if b.surface == "floor":   # a rug: floor, landing on it is landing
                floor = min(floor, d)
            elif d < best:
                best, name = d, b.name
        nearest = min((wall, "wall"), (best, name), (ceiling, "ceiling"))[1]
        return Clearance(wall, best, ceiling, floor, nearest)

    def arena_position(self, p_local_ned_m: Array, rest_height_m: float) -> Array:
        """Arena NED of a truth position (local NED from the start, where the centre of mass rests
        ``rest_height_m`` above the floor)."""
        return self.start_ned_m + np.asarray(p_local_ned_m, dtype=float) - np.array([0.0, 0.0, rest_height_m])


# ---------------------------------------------------------------- the verdict
@dataclass(frozen=True)
class Judgement:
    """A flight judged on its truth: clearance over the whole flight and how far the vehicle went."""

    min_clearance_m: float       # nearest non-floor surface, whole flight (nan: no truth)
    t_min_s: float               # when
    nearest_surface: str         # "wall", "ceiling" or the object's name
    min_wall_m: float
    min_object_m: float
    min_ceiling_m: float
    max_height_m: float          # centre of mass above the floor
    max_excursion_m: float       # the farthest horizontal distance from the start
    path_length_m: float         # horizontal path length
    samples: int

    @property
    def safe(self) -> bool:
        return self.min_clearance_m >= CLEARANCE_BOUND_M

    def summary(self) -> str:
        return (f"min clearance {self.min_clearance_m:.3f} m ({self.nearest_surface}) at t={self.t_min_s:.1f} s; "
                f"walls {self.min_wall_m:.3f} objects {self.min_object_m:.3f} ceiling {self.min_ceiling_m:.3f}; "
                f"moved {self.max_excursion_m:.2f} m from the start (path {self.path_length_m:.1f} m), "
                f"up to {self.max_height_m:.2f} m")


def judge(t_s: Array, p_local_ned_m: Array, geometry: ArenaGeometry,
          rest_height_m: float = PhysicsConfig().body_size_m[2] / 2) -> Judgement:
    """Judge a flight from its truth positions (``t_s`` N, ``p_local_ned_m`` N x 3, local NED from the start)."""
    t = np.asarray(t_s, dtype=float).reshape(-1)
    P = np.asarray(p_local_ned_m, dtype=float).reshape(-1, 3)
    if t.size == 0:
        nan = math.nan
        return Judgement(nan, nan, "", nan, nan, nan, nan, nan, nan, 0)
    arena = geometry.arena_position(P, rest_height_m)
    c = [geometry.clearance(p) for p in arena]
    k = int(np.argmin([x.surface_m for x in c]))
    steps = np.linalg.norm(np.diff(P[:, :2], axis=0), axis=1) if len(P) > 1 else np.zeros(0)
    return Judgement(
        min_clearance_m=c[k].surface_m, t_min_s=float(t[k]), nearest_surface=c[k].nearest_name,
        min_wall_m=min(x.wall_m for x in c), min_object_m=min(x.object_m for x in c),
        min_ceiling_m=min(x.ceiling_m for x in c), max_height_m=float(np.max(-arena[:, 2])),
        max_excursion_m=float(np.max(np.linalg.norm(P[:, :2] - P[0, :2], axis=1))),
        path_length_m=float(np.sum(steps)), samples=int(t.size))

"""Procedural arenas for flight campaigns (issue 15): rooms, corridors, corners, alcoves, low ceilings.

Pure: :func:`generate_scenario` takes a ``numpy.random.Generator`` and returns a
:class:`~sim_sitl.config.ScenarioConfig` (the structure of ``configs/scenarios/*.yaml``, arena frame NED,
origin on the floor at the centre of the room) plus the plain-data record of every draw it made.
:func:`scenario_to_dict` gives the YAML form that ``quadlink sitl --scenario PATH`` loads.

The geometry helpers (:func:`nearest_obstacle_2d`, :func:`clearance_2d`) work on the horizontal
footprints of the walls and of the objects that reach into the flight band, so the campaign can place a
start pose in free space and aim an operator at the nearest obstacle.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from quadlink.config import to_dict
from sim_sitl.config import RoomConfig, ScenarioConfig, SceneObject, StartPose, load_scenario

LAYOUTS = ("room", "corridor", "corner", "alcove", "low-ceiling")
FIXED_ARENAS = ("paper-arena", "office")
#: textured surfaces the RGB-D odometry can track; ``plain`` is drawn rarely (a hard case, not the norm)
TEXTURED = ("carpet", "wood", "concrete", "noise", "checker")
ROOM_SIZE_RANGE_M = (4.0, 12.0)
MAX_COLUMNS = 5
MAX_BOXES = 5
START_CLEARANCE_M = 1.0  # free radius around the start (take-off needs room; the start is not a test)
#: heights (m above the floor) the vehicle flies through: an object counts as an obstacle for the
#: operator generator only if it spans part of this band
FLIGHT_BAND_M = (0.6, 1.6)
#: the materials an Xtion does not see (``sim_sitl/xtion.py``): a procedural object gets one of them with the
#: probability ``hazard_material_p`` (0 by default: the arenas of earlier campaigns are unchanged)
HAZARD_MATERIALS = ("dark", "specular", "glass")


def _color(rng: np.random.Generator) -> tuple[float, float, float]:
    c = rng.uniform(0.35, 0.9, 3)
    return (round(float(c[0]), 3), round(float(c[1]), 3), round(float(c[2]), 3))


def _texture(rng: np.random.Generator, plain_p: float = 0.05) -> str:
    if rng.random() < plain_p:
        return "plain"
    return str(rng.choice(TEXTURED))


def _box(name: str, x: float, y: float, size: tuple[float, float, float], yaw_deg: float, z_top_m: float | None,
         rng: np.random.Generator, surface: str = "object") -> SceneObject:
    """A box standing on the floor (``z_top_m`` None) or hanging with its top at the ceiling height."""
    h = size[2]
    z = -h / 2 if z_top_m is None else -(z_top_m - h / 2)
    return SceneObject(kind="box", name=name, position_m=(round(x, 3), round(y, 3), round(z, 3)),
                       size_m=tuple(round(s, 3) for s in size), yaw_deg=round(yaw_deg, 2),  # type: ignore[arg-type]
                       texture=_texture(rng), color=_color(rng), surface=surface)  # type: ignore[arg-type]


@dataclass(frozen=True)
class Footprint:
    """An object's horizontal footprint (arena north/east) and vertical extent (up from the floor)."""

    kind: str  # "box" | "cylinder"
    centre_m: tuple[float, float]
    half_m: tuple[float, float]  # box half extents along its own axes
    yaw_rad: float
    radius_m: float
    bottom_up_m: float
    top_up_m: float
    name: str


def footprints(scenario: ScenarioConfig) -> list[Footprint]:
    out = []
    for o in scenario.objects:
        if o.surface == "floor":
            continue
        if o.kind == "box":
            h = o.size_m[2]
            half = (o.size_m[0] / 2, o.size_m[1] / 2)
            r = 0.0
        else:
            h = o.height_m
            half = (o.radius_m, o.radius_m)
            r = o.radius_m
        centre_up = -o.position_m[2]
        out.append(Footprint(o.kind, (o.position_m[0], o.position_m[1]), half, math.radians(o.yaw_deg), r,
                             centre_up - h / 2, centre_up + h / 2, o.name))
    return out


def _closest_point(fp: Footprint, q: np.ndarray) -> np.ndarray:
    c = np.asarray(fp.centre_m)
    if fp.kind == "cylinder":
        d = q - c
        n = float(np.linalg.norm(d))
        return c + (d / n * fp.radius_m if n > 1e-9 else np.array([fp.radius_m, 0.0]))
    cy, sy = math.cos(fp.yaw_rad), math.sin(fp.yaw_rad)
    R = np.array([[cy, -sy], [sy, cy]])  # box axes -> arena (yaw about down: north toward east)
    local = R.T @ (q - c)
    clamped = np.clip(local, -np.asarray(fp.half_m), np.asarray(fp.half_m))
    return c + R @ clamped


def nearest_obstacle_2d(scenario: ScenarioConfig, xy_m: tuple[float, float],
                        band_m: tuple[float, float] = FLIGHT_BAND_M) -> tuple[float, tuple[float, float], str]:
    """Horizontal distance from ``xy_m`` to the nearest wall or object spanning ``band_m``.

    Returns (distance m, nearest point (north, east) m, name). Inside a footprint the distance is 0.
    """
    q = np.asarray(xy_m, dtype=float)
    nx, ny = scenario.room.size_m
    best: tuple[float, tuple[float, float], str] = (math.inf, (math.nan, math.nan), "")
    if scenario.room.walls:
        for point, name in (((nx / 2, q[1]), "wall-north"), ((-nx / 2, q[1]), "wall-south"),
                            ((q[0], ny / 2), "wall-east"), ((q[0], -ny / 2), "wall-west")):
            d = float(np.linalg.norm(q - np.asarray(point)))
            if d < best[0]:
                best = (d, (float(point[0]), float(point[1])), name)
    for fp in footprints(scenario):
        if fp.top_up_m < band_m[0] or fp.bottom_up_m > band_m[1]:
            continue
        p = _closest_point(fp, q)
        d = float(np.linalg.norm(q - p))
        if d < best[0]:
            best = (d, (float(p[0]), float(p[1])), fp.name)
    return best


def clearance_2d(scenario: ScenarioConfig, xy_m: tuple[float, float]) -> float:
    """Horizontal distance to the nearest wall or object of any height (the start must be clear of all)."""
    return nearest_obstacle_2d(scenario, xy_m, band_m=(-math.inf, math.inf))[0]


def draw_start(scenario: ScenarioConfig, rng: np.random.Generator, clearance_m: float = START_CLEARANCE_M,
               tries: int = 200) -> StartPose:
    """A start position at least ``clearance_m`` from every wall and object (relaxed to 0.5 m in a crowded
    room), with a uniform heading; the scenario's own start if even that fails."""
    nx, ny = scenario.room.size_m
    for clear_m in (clearance_m, 0.8 * clearance_m, 0.6 * clearance_m, 0.5 * clearance_m):
        for _ in range(tries):
            x = float(rng.uniform(-nx / 2 + clear_m, nx / 2 - clear_m))
            y = float(rng.uniform(-ny / 2 + clear_m, ny / 2 - clear_m))
            if clearance_2d(scenario, (x, y)) >= clear_m:
                return StartPose(position_m=(round(x, 3), round(y, 3)),
                                 yaw_deg=round(float(rng.uniform(-180.0, 180.0)), 2))
    return scenario.start


def _scatter(rng: np.random.Generator, room: RoomConfig, n_columns: int, n_boxes: int,
             keep_clear: list[tuple[float, float]], existing: list[SceneObject]) -> list[SceneObject]:
    """Columns (full height) and boxes (0.3-1.8 m) placed away from the keep-clear points and each other."""
    nx, ny = room.size_m
    objects: list[SceneObject] = []
    for i in range(n_columns + n_boxes):
        column = i < n_columns
        for _ in range(100):
            x = float(rng.uniform(-nx / 2 + 0.5, nx / 2 - 0.5))
            y = float(rng.uniform(-ny / 2 + 0.5, ny / 2 - 0.5))
            if any(math.hypot(x - a, y - b) < START_CLEARANCE_M + 0.6 for a, b in keep_clear):
                continue
            probe = ScenarioConfig(room=dataclasses.replace(room, walls=False), objects=tuple(existing + objects))
            if clearance_2d(probe, (x, y)) < 1.0:
                continue
            break
        else:
            continue
        if column:
            r = float(rng.uniform(0.1, 0.35))
            objects.append(SceneObject(kind="cylinder", name=f"column-{i}", position_m=(round(x, 3), round(y, 3),
                                       round(-room.height_m / 2, 3)), radius_m=round(r, 3),
                                       height_m=room.height_m, texture=_texture(rng), color=_color(rng)))
        else:
            size = (float(rng.uniform(0.3, 1.2)), float(rng.uniform(0.3, 1.2)), float(rng.uniform(0.3, 1.8)))
            objects.append(_box(f"box-{i - n_columns}", x, y, size, float(rng.uniform(-90, 90)), None, rng))
    return objects


def draw_hazard_materials(rng: np.random.Generator, objects: list[SceneObject], p: float,
                          materials: tuple[str, ...] = HAZARD_MATERIALS) -> list[SceneObject]:
    """Each object dark, specular or glass with probability ``p`` (else as it was), from a child stream of ``rng``
    (``Generator.spawn``: the parent's draws are untouched, so the geometry of a seed does not depend on ``p``).
    Two draws per object whatever ``p``: an object hazardous at some ``p`` stays so at any larger one."""
    if p <= 0:
        return objects
    child = rng.spawn(1)[0]
    u = child.random(len(objects))
    kind = child.integers(0, len(materials), len(objects))
    return [dataclasses.replace(o, material=materials[int(k)]) if ui < p else o  # type: ignore[arg-type]
            for o, ui, k in zip(objects, u, kind, strict=True)]


def generate_procedural(rng: np.random.Generator, name: str, layout: str | None = None,
                        hazard_material_p: float = 0.0, hazard_materials: tuple[str, ...] = HAZARD_MATERIALS,
                        ) -> tuple[ScenarioConfig, str]:
    """One procedural arena and its layout; ``layout`` (one of :data:`LAYOUTS`) is drawn when None; each object is
    dark, specular or glass with probability ``hazard_material_p`` (:func:`draw_hazard_materials`)."""
    layout = layout or str(rng.choice(LAYOUTS))
    if layout not in LAYOUTS:
        raise ValueError(f"unknown layout {layout!r} (known: {', '.join(LAYOUTS)})")
    lo, hi = ROOM_SIZE_RANGE_M
    height = float(rng.uniform(2.6, 3.2))
    if layout == "corridor":  # a long room with a partition leaving a corridor 1.4-2.4 m wide
        size = (float(rng.uniform(8.0, hi)), float(rng.uniform(lo, 6.0)))
    else:
        size = (float(rng.uniform(lo, hi)), float(rng.uniform(lo, hi)))
    if layout == "low-ceiling":
        height = float(rng.uniform(2.0, 2.4))
    room = RoomConfig(size_m=(round(size[0], 3), round(size[1], 3)), height_m=round(height, 3),
                      floor_texture=_texture(rng, 0.0), wall_texture=_texture(rng),
                      ceiling_texture=_texture(rng, 0.5))
    nx, ny = room.size_m
    h = room.height_m
    objects: list[SceneObject] = []
    start_xy = (round(-nx / 2 + 1.2, 3), 0.0)
    if layout == "corridor":
        width = float(rng.uniform(1.4, 2.4))
        # a wall-high partition along the room; the corridor is the strip y in [-ny/2, -ny/2 + width]
        part_y0 = -ny / 2 + width
        objects.append(_box("partition", 0.0, (part_y0 + ny / 2) / 2, (nx - 2.5, ny / 2 - part_y0, h), 0.0, None,
                            rng, surface="wall"))
        start_xy = (round(-nx / 2 + 1.1, 3), round(-ny / 2 + width / 2, 3))
    elif layout == "corner":  # an L-shaped room: one quadrant filled, giving an inside corner
        qx, qy = float(rng.uniform(0.3, 0.5)) * nx, float(rng.uniform(0.3, 0.5)) * ny
        sx, sy = rng.choice([-1.0, 1.0], 2)
        objects.append(_box("corner-block", float(sx) * (nx / 2 - qx / 2), float(sy) * (ny / 2 - qy / 2),
                            (qx, qy, h), 0.0, None, rng, surface="wall"))
        start_xy = (round(-float(sx) * (nx / 2 - 1.2), 3), round(-float(sy) * (ny / 2 - 1.2), 3))
    elif layout == "alcove":  # two wall stubs out of the north wall making a niche 0.8-1.6 m wide
        width = float(rng.uniform(0.8, 1.6))
        depth = float(rng.uniform(0.6, 1.2))
        y0 = float(rng.uniform(-ny / 2 + 1.0, ny / 2 - 1.0 - width))
        for k, y in enumerate((y0 - 0.1, y0 + width + 0.1)):
            objects.append(_box(f"alcove-stub-{k}", nx / 2 - depth / 2, y, (depth, 0.2, h), 0.0, None, rng,
                                surface="wall"))
    elif layout == "low-ceiling":  # plus a soffit hanging into the flight band over part of the room
        drop = float(rng.uniform(0.3, 0.7))
        sx = float(rng.uniform(1.0, nx / 2))
        objects.append(_box("soffit", float(rng.uniform(0.0, nx / 4)), float(rng.uniform(-ny / 4, ny / 4)),
                            (sx, float(rng.uniform(1.0, ny / 2)), drop), 0.0, h, rng, surface="object"))
    n_columns = int(rng.integers(0, MAX_COLUMNS + 1))
    n_boxes = int(rng.integers(0, MAX_BOXES + 1))
    objects += _scatter(rng, room, n_columns, n_boxes, [start_xy], objects)
    objects = draw_hazard_materials(rng, objects, hazard_material_p, hazard_materials)
    scenario = ScenarioConfig(name=name, description=f"procedural {layout} {nx:.1f} x {ny:.1f} m, {h:.2f} m high, "
                              f"{n_columns} columns, {n_boxes} boxes", room=room,
                              start=StartPose(position_m=start_xy, yaw_deg=0.0), objects=tuple(objects))
    return scenario, layout


@dataclass(frozen=True)
class ArenaDraw:
    scenario: ScenarioConfig
    record: dict[str, Any]  # every draw, plain data (goes into the flight's draws.json)


def generate_scenario(rng: np.random.Generator, name: str, fixed_share: float = 0.2,
                      hazard_material_p: float = 0.0, hazard_materials: tuple[str, ...] = HAZARD_MATERIALS,
                      ) -> ArenaDraw:
    """An arena for one flight: a fixed member (paper-arena, office) with probability ``fixed_share``, else a
    procedural one (its objects dark, specular or glass with probability ``hazard_material_p``); in both cases
    the start pose is drawn in free space."""
    if rng.random() < fixed_share:
        base_name = str(rng.choice(FIXED_ARENAS))
        base = dataclasses.replace(load_scenario(base_name), name=name)
        layout = f"fixed:{base_name}"
    else:
        base, layout = generate_procedural(rng, name, hazard_material_p=hazard_material_p,
                                           hazard_materials=hazard_materials)
    start = draw_start(base, rng)
    scenario = dataclasses.replace(base, start=start)
    record = {"layout": layout, "room_size_m": list(scenario.room.size_m),
              "room_height_m": scenario.room.height_m, "objects": len(scenario.objects),
              "start": {"position_m": list(start.position_m), "yaw_deg": start.yaw_deg},
              "start_clearance_m": clearance_2d(scenario, start.position_m)}
    if hazard_material_p > 0:
        record["hazard_materials"] = {o.name: o.material for o in scenario.objects if o.material != "matte"}
    return ArenaDraw(scenario, record)


def scenario_to_dict(scenario: ScenarioConfig) -> dict[str, Any]:
    """The YAML form (``configs/scenarios/*.yaml``) of a scenario."""
    data: dict[str, Any] = to_dict(scenario)
    return data


OVERHEAD_MIN_BOTTOM_M = 0.5   # an object reaching the ceiling with its underside this high hangs from it (a soffit)
CEILING_TOUCH_M = 0.05        # ... "reaching": its top within this of the ceiling (a desk's top is not overhead)


def lowest_overhead_m(scenario: ScenarioConfig) -> float:
    """The lowest overhead above the floor: the ceiling, or the underside of anything hanging from it."""
    h = scenario.room.height_m
    hanging = [fp.bottom_up_m for fp in footprints(scenario)
               if fp.bottom_up_m >= OVERHEAD_MIN_BOTTOM_M and fp.top_up_m >= h - CEILING_TOUCH_M]
    return float(min([h, *hanging]))

"""The static scene of a scenario as plain data (pure): the bodies both renderers and the physics build.

``build_scene`` turns a :class:`ScenarioConfig` into the room's slabs (floor, ceiling, walls: boxes
``SLAB_M`` thick outside the room's interior) followed by the scenario's objects, all in the arena frame
(NED, origin on the floor at the centre). ``world.py`` makes pybullet bodies of them; ``raster.py``
draws them. ``scene_textures`` generates every body's procedural texture once, in body order, so both
renderers (and the random stream) see the same images.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from sim_sitl.config import MATERIALS, RoomConfig, ScenarioConfig
from sim_sitl.textures import make_texture

SLAB_M = 0.2  # thickness of the floor, ceiling and wall slabs
TEXEL_M = 0.01  # target texture resolution on large boxes (textures 256..1024 px)
CYLINDER_TEXTURE_PX = 256

SURFACE_FLOOR = "floor"
SURFACE_CEILING = "ceiling"
SURFACE_WALL = "wall"
SURFACE_OBJECT = "object"

TextureKey = tuple[str, tuple[float, float, float], int]  # (kind, colour, size_px)

#: per-pixel material codes the renderers give the camera model: the index in ``MATERIALS`` (matte = 0)
MATERIAL_CODE: dict[str, int] = {m: i for i, m in enumerate(MATERIALS)}


@dataclass(frozen=True)
class SceneBody:
    """A static vertical prism: a box turned by ``yaw_rad`` about the down axis, or an upright cylinder.

    ``size_m`` is the box's full extent along its own (north, east, down) axes; a cylinder uses
    ``radius_m`` and ``size_m[2]`` as its height. The texture spans each face of a box and wraps once
    around a cylinder.
    """

    kind: str  # "box" | "cylinder"
    name: str
    centre_ned_m: tuple[float, float, float]
    size_m: tuple[float, float, float]
    yaw_rad: float
    texture: str
    color: tuple[float, float, float]
    surface: str
    texture_px: int
    radius_m: float = 0.0
    material: str = "matte"  # ``sim_sitl.config.MATERIALS``; the room's slabs are matte

    @property
    def texture_key(self) -> TextureKey:
        return (self.texture, (float(self.color[0]), float(self.color[1]), float(self.color[2])), self.texture_px)

    @property
    def height_m(self) -> float:
        return self.size_m[2]


@dataclass(frozen=True)
class Scene:
    room: RoomConfig
    bodies: tuple[SceneBody, ...]  # the room's slabs first, then the scenario's objects

    @property
    def closed_room(self) -> bool:
        """Walls and ceiling present: from inside, only the slabs' inner faces can be seen."""
        return self.room.walls and self.room.ceiling

    def interior_bounds_ned_m(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Corners (min, max) of the room's interior box, NED."""
        nx, ny = self.room.size_m
        return np.array([-nx / 2, -ny / 2, -self.room.height_m]), np.array([nx / 2, ny / 2, 0.0])


def box_texture_px(size_m: tuple[float, float, float]) -> int:
    """Texture size for a box: about ``TEXEL_M`` per texel on its largest face, 256..1024 px."""
    return int(min(1024, max(256, 2 ** math.ceil(math.log2(max(size_m) / TEXEL_M)))))


def _box(name: str, centre: tuple[float, float, float], size: tuple[float, float, float], yaw_rad: float,
         texture: str, color: tuple[float, float, float], surface: str, material: str = "matte") -> SceneBody:
    return SceneBody("box", name, centre, size, yaw_rad, texture, color, surface, box_texture_px(size),
                     material=material)


def build_scene(scenario: ScenarioConfig) -> Scene:
    room = scenario.room
    nx, ny = room.size_m
    h = room.height_m
    t = SLAB_M
    white = (0.85, 0.85, 0.85)
    bodies = [_box("floor", (0.0, 0.0, t / 2), (nx + 2 * t, ny + 2 * t, t), 0.0, room.floor_texture,
                   (0.55, 0.35, 0.3), SURFACE_FLOOR)]
    if room.ceiling:
        bodies.append(_box("ceiling", (0.0, 0.0, -h - t / 2), (nx + 2 * t, ny + 2 * t, t), 0.0, room.ceiling_texture,
                           white, SURFACE_CEILING))
    if room.walls:
        for sx in (-1.0, 1.0):
            bodies.append(_box(f"wall-{'south' if sx < 0 else 'north'}", (sx * (nx / 2 + t / 2), 0.0, -h / 2),
                               (t, ny + 2 * t, h), 0.0, room.wall_texture, (0.75, 0.75, 0.7), SURFACE_WALL))
        for sy in (-1.0, 1.0):
            bodies.append(_box(f"wall-{'west' if sy < 0 else 'east'}", (0.0, sy * (ny / 2 + t / 2), -h / 2),
                               (nx, t, h), 0.0, room.wall_texture, (0.7, 0.72, 0.78), SURFACE_WALL))
    for obj in scenario.objects:
        centre = (float(obj.position_m[0]), float(obj.position_m[1]), float(obj.position_m[2]))
        if obj.kind == "box":
            bodies.append(_box(obj.name, centre, obj.size_m, math.radians(obj.yaw_deg), obj.texture, obj.color,
                               obj.surface, obj.material))
        else:
            d = 2.0 * obj.radius_m
            bodies.append(SceneBody("cylinder", obj.name, centre, (d, d, obj.height_m), 0.0, obj.texture, obj.color,
                                    obj.surface, CYLINDER_TEXTURE_PX, obj.radius_m, obj.material))
    return Scene(room, tuple(bodies))


def scene_textures(scene: Scene, rng: np.random.Generator) -> dict[TextureKey, NDArray[np.uint8]]:
    """Every body's RGB8 texture, generated in body order (one draw per distinct key)."""
    out: dict[TextureKey, NDArray[np.uint8]] = {}
    for body in scene.bodies:
        key = body.texture_key
        if key not in out:
            out[key] = make_texture(body.texture, rng, body.color, body.texture_px)
    return out

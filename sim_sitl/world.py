"""The pybullet side of the SITL: scene, rigid body, rotor forces, distance queries (one client each).

pybullet works in a z-up world; this module is the one place that converts. The pybullet world is
the arena's NWU (x north, y west, z up) and the vehicle's pybullet body frame is FLU, so with
``D = diag(1, -1, -1)`` (a rotation by pi about x): ``p_ned = D p_pb``, ``R_ned_frd = D R_pb_flu D``.
Everything that leaves this module is NED / FRD.
"""

from __future__ import annotations

import logging
import math
import tempfile
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pybullet as p
from numpy.typing import NDArray

from quadlink.frames import GRAVITY_M_S2, R_NED_NWU, Rz
from quadlink.vehicle import VehicleConfig
from sim_sitl.config import ScenarioConfig, SitlConfig
from sim_sitl.motors import body_wrench, motor_lag, rotor_layout
from sim_sitl.scene import (
    SURFACE_CEILING,
    SURFACE_FLOOR,
    SURFACE_OBJECT,
    SURFACE_WALL,
    TextureKey,
    build_scene,
    scene_textures,
)

log = logging.getLogger(__name__)

D = R_NED_NWU  # NED <-> pybullet NWU, and (the same matrix) FRD <-> FLU
_D_SANDWICH = np.outer(np.diag(D), np.diag(D))  # elementwise form of D @ R @ D

__all__ = ["D", "SURFACE_CEILING", "SURFACE_FLOOR", "SURFACE_OBJECT", "SURFACE_WALL", "RigidState", "World"]


@dataclass(frozen=True)
class RigidState:
    """True state of the vehicle in the arena frame (NED, origin at the centre of the floor)."""

    t_s: float
    p_ned_m: NDArray[np.float64]
    v_ned_m_s: NDArray[np.float64]
    R_ned_q: NDArray[np.float64]  # body FRD -> NED
    omega_q_rad_s: NDArray[np.float64]  # body rates, FRD
    a_ned_m_s2: NDArray[np.float64]  # kinematic acceleration over the last step
    motor_thrust_n: NDArray[np.float64]


def _quat_xyzw_from_R(R: NDArray[np.float64]) -> list[float]:
    from quadlink.frames import quat_wxyz_from_R

    w, x, y, z = quat_wxyz_from_R(R)
    return [float(x), float(y), float(z), float(w)]


class World:
    """A pybullet ``DIRECT`` client holding one arena and one quadrotor. Not thread-safe: one owner."""

    def __init__(self, vehicle: VehicleConfig, cfg: SitlConfig, scenario: ScenarioConfig,
                 rng: np.random.Generator, texture_dir: str | Path | None = None) -> None:
        self.vehicle = vehicle
        self.cfg = cfg
        self.scenario = scenario
        self.client = p.connect(p.DIRECT)
        self.dt_s = 1.0 / cfg.physics.rate_hz
        self.layout = rotor_layout(vehicle)
        self._tmp = tempfile.TemporaryDirectory(prefix="quadlink-sitl-tex-") if texture_dir is None else None
        self._texture_dir = Path(self._tmp.name if self._tmp else texture_dir)  # type: ignore[arg-type]
        self._rng = rng
        self.scene = build_scene(scenario)
        self._texture_ids: dict[TextureKey, int] = {}
        self._texture_images: dict[TextureKey, NDArray[np.uint8]] | None = None
        self.surfaces: dict[int, str] = {}
        self.materials: dict[int, str] = {}  # pybullet body id -> material (the camera's segmentation)
        self._pending_textures: list[tuple[int, TextureKey]] = []
        p.setGravity(0.0, 0.0, -GRAVITY_M_S2, physicsClientId=self.client)
        p.setTimeStep(self.dt_s, physicsClientId=self.client)
        p.setPhysicsEngineParameter(numSolverIterations=20, physicsClientId=self.client)
        self._build_scene()
        self._query_shape = p.createCollisionShape(p.GEOM_SPHERE, radius=1e-3, physicsClientId=self.client)
        self._build_vehicle()
        self.t_s = 0.0
        self.motor_thrust_n = np.zeros(4)
        self.external_force_ned_n = np.zeros(3)  # a push at the centre of mass (sim_sitl/disturbance.py), NED
        self._state = self._read_state(None)
        self._settle(0.5)

    # ------------------------------------------------------------------ scene
    def _texture(self, key: TextureKey) -> int:
        if key not in self._texture_ids:
            img = self.scene_textures()[key]
            path = self._texture_dir / f"tex{len(self._texture_ids)}_{key[0]}.bmp"  # uncompressed: fast to load
            cv2.imwrite(str(path), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
            self._texture_ids[key] = p.loadTexture(str(path), physicsClientId=self.client)
        return self._texture_ids[key]

    def _build_scene(self) -> None:
        """One static pybullet body per ``scene.bodies`` entry (textures come later: ``load_textures``)."""
        for b in self.scene.bodies:
            centre = (D @ np.asarray(b.centre_ned_m)).tolist()
            # glass: fully transparent (the tiny renderer skips it; without a visual shape it would draw the
            # collision shape): the camera sees through it, the vehicle does not pass
            glass = b.material == "glass"
            if b.kind == "box":
                half = [s / 2.0 for s in b.size_m]
                cs = p.createCollisionShape(p.GEOM_BOX, halfExtents=half, physicsClientId=self.client)
                vs = p.createVisualShape(p.GEOM_BOX, halfExtents=half, physicsClientId=self.client)
                body = p.createMultiBody(0.0, cs, vs, centre, p.getQuaternionFromEuler([0.0, 0.0, -b.yaw_rad]),
                                         physicsClientId=self.client)
            else:
                cs = p.createCollisionShape(p.GEOM_CYLINDER, radius=b.radius_m, height=b.height_m,
                                            physicsClientId=self.client)
                vs = p.createVisualShape(p.GEOM_CYLINDER, radius=b.radius_m, length=b.height_m,
                                         physicsClientId=self.client)
                body = p.createMultiBody(0.0, cs, vs, centre, physicsClientId=self.client)
            p.changeVisualShape(body, -1, rgbaColor=[*b.color, 0.0 if glass else 1.0], physicsClientId=self.client)
            if not glass:
                self._pending_textures.append((body, b.texture_key))
            p.changeDynamics(body, -1, lateralFriction=self.cfg.physics.ground_friction, physicsClientId=self.client)
            self.surfaces[body] = b.surface
            self.materials[body] = b.material

    def _build_vehicle(self) -> None:
        size = self.cfg.physics.body_size_m
        cs = p.createCollisionShape(p.GEOM_BOX, halfExtents=[s / 2 for s in size], physicsClientId=self.client)
        start = self.scenario.start
        # rest on whatever is below the start point (floor, or a rug lying on it)
        hits = p.rayTestBatch([
            [start.position_m[0] + dx, -(start.position_m[1] + dy), self.scenario.room.height_m - 0.01]
            for dx in (-size[0] / 2, size[0] / 2) for dy in (-size[1] / 2, size[1] / 2)],
            [[start.position_m[0] + dx, -(start.position_m[1] + dy), -1.0]
             for dx in (-size[0] / 2, size[0] / 2) for dy in (-size[1] / 2, size[1] / 2)],
            physicsClientId=self.client)
        support_up_m = max((h[3][2] for h in hits if h[0] >= 0), default=0.0)
        self.start_p_ned_m = np.array([start.position_m[0], start.position_m[1], -support_up_m - size[2] / 2.0 - 1e-3])
        R0 = Rz(math.radians(start.yaw_deg))
        self.body = p.createMultiBody(self.vehicle.mass_kg, cs, -1, (D @ self.start_p_ned_m).tolist(),
                                      _quat_xyzw_from_R(D @ R0 @ D), physicsClientId=self.client)
        p.changeDynamics(self.body, -1, localInertiaDiagonal=list(self.vehicle.inertia_kg_m2), linearDamping=0.0,
                         angularDamping=0.0, lateralFriction=self.cfg.physics.ground_friction,
                         physicsClientId=self.client)

    def scene_textures(self) -> dict[TextureKey, NDArray[np.uint8]]:
        """The bodies' procedural textures, generated on first use from the world's generator (they take a
        moment: only a camera needs them). Both renderers use these images."""
        if self._texture_images is None:
            self._texture_images = scene_textures(self.scene, self._rng)
        return self._texture_images

    def load_textures(self) -> None:
        """Apply the procedural textures to the pybullet bodies (for pybullet's renderer)."""
        for body, key in self._pending_textures:
            p.changeVisualShape(body, -1, textureUniqueId=self._texture(key), rgbaColor=[1, 1, 1, 1],
                                physicsClientId=self.client)
        self._pending_textures = []

    # ------------------------------------------------------------------ dynamics
    def _read_state(self, v_prev_ned: NDArray[np.float64] | None) -> RigidState:
        """The body's state; the acceleration is the velocity change since ``v_prev_ned`` over one step."""
        pos, quat = p.getBasePositionAndOrientation(self.body, physicsClientId=self.client)
        lin, ang = p.getBaseVelocity(self.body, physicsClientId=self.client)
        R_ned_q = np.array(p.getMatrixFromQuaternion(quat)).reshape(3, 3) * _D_SANDWICH  # = D R_pb D
        v_ned = np.array((lin[0], -lin[1], -lin[2]))
        omega_q = R_ned_q.T @ np.array((ang[0], -ang[1], -ang[2]))
        a_ned = np.zeros(3) if v_prev_ned is None else (v_ned - v_prev_ned) / self.dt_s
        return RigidState(self.t_s, np.array((pos[0], -pos[1], -pos[2])), v_ned, R_ned_q, omega_q, a_ned,
                          self.motor_thrust_n.copy())

    def _settle(self, seconds: float) -> None:
        """Let the vehicle come to rest on its support before time starts (the board boots on the ground)."""
        for _ in range(round(seconds / self.dt_s)):
            self.step(np.zeros(4))
        self.t_s = 0.0
        self._state = self._read_state(None)
        self.start_p_ned_m = self._state.p_ned_m.copy()

    @property
    def state(self) -> RigidState:
        return self._state

    def step(self, motor_cmd_n: NDArray[np.float64]) -> RigidState:
        """Advance one physics step with the given per-motor thrust commands (N)."""
        m = self.vehicle.motor
        self.motor_thrust_n = motor_lag(self.motor_thrust_n, np.asarray(motor_cmd_n, dtype=float),
                                        m.time_constant_s, self.dt_s)
        thrust_n, torque_q = body_wrench(self.layout, self.motor_thrust_n)
        s = self._state
        R = s.R_ned_q
        v_q = R.T @ s.v_ned_m_s
        drag_q = -np.asarray(self.vehicle.linear_drag_n_s_m) * v_q
        drag_q[:2] -= self.cfg.physics.rotor_drag_n_s_m_per_n * thrust_n * v_q[:2]  # rotor (induced) drag
        force_ned = R @ (np.array([0.0, 0.0, -thrust_n]) + drag_q) + self.external_force_ned_n
        torque_ned = R @ torque_q
        pos_pb = (D @ s.p_ned_m).tolist()
        p.applyExternalForce(self.body, -1, (D @ force_ned).tolist(), pos_pb, p.WORLD_FRAME,
                             physicsClientId=self.client)
        p.applyExternalTorque(self.body, -1, (D @ torque_ned).tolist(), p.WORLD_FRAME, physicsClientId=self.client)
        p.stepSimulation(physicsClientId=self.client)
        self.t_s += self.dt_s
        self._state = self._read_state(s.v_ned_m_s)
        return self._state

    def reset_pose(self, p_ned_m: NDArray[np.float64], R_ned_q: NDArray[np.float64],
                   v_ned_m_s: NDArray[np.float64] | None = None) -> None:
        """Place the vehicle (tests and scripted starts)."""
        v = np.zeros(3) if v_ned_m_s is None else np.asarray(v_ned_m_s, dtype=float)
        p.resetBasePositionAndOrientation(self.body, (D @ p_ned_m).tolist(), _quat_xyzw_from_R(D @ R_ned_q @ D),
                                          physicsClientId=self.client)
        p.resetBaseVelocity(self.body, (D @ v).tolist(), [0.0, 0.0, 0.0], physicsClientId=self.client)
        self._state = self._read_state(None)

    # ------------------------------------------------------------------ queries
    def nearest_distances(self, p_ned_m: NDArray[np.float64], max_distance_m: float = 20.0) -> tuple[float, float]:
        """Distance from a point to the nearest surface of any kind, and excluding floor and ceiling.

        ``inf`` where nothing lies within ``max_distance_m``.
        """
        pos = (D @ p_ned_m).tolist()
        any_m = other_m = math.inf
        for body, surface in self.surfaces.items():
            pts = p.getClosestPoints(bodyA=-1, bodyB=body, distance=max_distance_m, collisionShapeA=self._query_shape,
                                     collisionShapePositionA=pos, physicsClientId=self.client)
            if not pts:
                continue
            d = max(0.0, min(pt[8] for pt in pts) + 1e-3)  # the query sphere's radius
            any_m = min(any_m, d)
            if surface not in (SURFACE_FLOOR, SURFACE_CEILING):
                other_m = min(other_m, d)
        return any_m, other_m

    def close(self) -> None:
        if self.client >= 0:
            try:
                p.disconnect(physicsClientId=self.client)
            except p.error:
                pass
            self.client = -1
        if self._tmp is not None:
            self._tmp.cleanup()
            self._tmp = None

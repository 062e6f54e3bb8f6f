"""The falsification search's flight space (issue 31), pure but for :func:`write_flight`.

A point is a :class:`FlightParams`: typed, bounded, named parameters with units. :func:`build_flight` maps it,
deterministically, to a flight the campaign runner flies: an arena built *relative to the take-off pose and the
push* (one obstacle of a given kind at a given distance and bearing from the camera's axis), an operator session
(one push in a direction relative to the camera's axis, with its speed, timing, turn and climb rates), the
vehicle and sensor errors (camera mount, IMU bias spreads, mass, the SITL's seed), and the companion's
calibration (the room height it is told, the pan-scan on or off). The same point gives the same files, byte for
byte, and a deterministic lock-step flight of those files re-flies bit for bit.

Frames: the arena is NED with its origin on the floor at the room's centre; the vehicle takes off there facing
north (yaw 0), so its camera looks along ``MOTION_OFFSET_RAD`` (45 deg right of the heading, where the haptic
operator's handle moves it). Bearings are measured from that axis, clockwise seen from above (NED yaw sense).

Not in the space: link delay and loss, glass. The deterministic lock-step has no impaired link (a netem link is on the
wall clock, so a flight through it cannot re-fly bit for bit); see docs/falsification.md.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, Literal, get_args

import numpy as np
import yaml

from harness.campaign.draws import (
    CAMERA_TILT_DEG,
    IMU_BIAS_SCALE,
    MASS_SPREAD,
    ROOM_HEIGHT_ENTRY_ERROR_M,
    FlightFiles,
    mount_turned,
    write_sitl_files,
)
from harness.campaign.sessions import (
    FULL_DEFLECTION_N,
    LANDING_S,
    MAX_SPEED_M_S,
    MAX_YAW_RATE_RAD_S,
    MOTION_OFFSET_RAD,
    TAKEOFF_S,
)
from harness.demo.cli import write_companion_config
from quadlink import CONFIG_DIR
from quadlink.errors import ConfigError
from sim_sitl.config import CameraNoiseConfig, ImuNoiseConfig, RoomConfig, ScenarioConfig, SceneObject, StartPose
from sim_sitl.scenario_gen import clearance_2d

ObstacleKind = Literal["wall", "corner", "doorway", "pole", "box", "column"]
ObstacleMaterial = Literal["matte", "dark", "specular"]
PushDirection = Literal["along", "diagonal", "across", "against"]
OperatorKind = Literal["haptic", "offboard"]

#: push direction -> angle from the camera's axis (rad, clockwise seen from above)
PUSH_ANGLE_RAD = {"along": 0.0, "diagonal": math.pi / 4, "across": math.pi / 2, "against": math.pi}
#: the haptic device moves the vehicle along the camera's axis only (paper 000 eq. 2: x is speed along alpha,
#: y is yaw rate); a push at an angle to it is flown by the offboard client's body-frame velocity
HAPTIC_DIRECTIONS = ("along", "against")
ROOM_SIZE_M = (10.0, 10.0)
SLAB_THICKNESS_M = 0.2
MIN_START_CLEARANCE_M = 0.5  # the take-off needs this much room around the body (0.36 m wide)
CLIMB_MAX_M_S = 0.4  # full deflection of the handle's z (configs/companion.yaml reference.k_climb_m_s)
HANDLE_GAIN = 1.1  # a little more force than the fraction: the handle sits where spring and push balance


def _p(low: float | None = None, high: float | None = None, unit: str = "", doc: str = "") -> Any:
    return field(metadata={"low": low, "high": high, "unit": unit, "doc": doc})


@dataclass(frozen=True)
class FlightParams:
    """One point of the flight space. Floats are bounded by ``[low, high]`` (field metadata, with the unit)."""

    # arena, relative to the take-off pose and the camera's axis
    obstacle_kind: ObstacleKind = _p(doc="wall | corner (inside, two walls) | doorway (a gap in a wall) | "
                                         "pole (thin) | box (standing) | column (thick)")
    obstacle_distance_m: float = _p(0.6, 3.0, "m", "take-off point to the obstacle's nearest surface, horizontal "
                                                   "(doorway: to the wall's plane; corner: to each leg)")
    obstacle_bearing_deg: float = _p(-180.0, 180.0, "deg", "obstacle (corner: its vertex; doorway: the gap's centre) "
                                                           "from the camera's axis, clockwise from above")
    obstacle_size: float = _p(0.0, 1.0, "1", "size within the kind's range (SIZE_RANGES_M)")
    room_height_m: float = _p(2.0, 3.2, "m", "floor to ceiling")
    # operator
    operator: OperatorKind = _p(doc="haptic (MANUAL_CONTROL) | offboard (SET_POSITION_TARGET_LOCAL_NED); "
                                    "diagonal and across pushes always fly offboard")
    push_direction: PushDirection = _p(doc="the push's direction from the camera's axis: along 0, diagonal 45, "
                                           "across 90, against 180 deg")
    push_speed_fraction: float = _p(0.3, 1.0, "1", "of full deflection (0.6 m/s)")
    push_start_s: float = _p(0.0, 4.0, "s", "after the take-off phase (10 s)")
    push_duration_s: float = _p(1.0, 8.0, "s", "cut to what the flight's duration leaves")
    push_yaw_rate_rad_s: float = _p(-0.6, 0.6, "rad/s", "turn rate commanded while pushing")
    push_climb_m_s: float = _p(-0.2, 0.4, "m/s", "climb (up positive) commanded while pushing")
    pan_scan: bool = _p(doc="the companion's pan-scan (eq. 4) on or off")
    # sensors, calibration, vehicle: the campaign's ranges (harness/campaign/draws.py), so that a finding lies
    # within the conditions the safety claim is made for
    camera_roll_error_deg: float = _p(-CAMERA_TILT_DEG, CAMERA_TILT_DEG, "deg", "true mount turned about body x")
    camera_pitch_error_deg: float = _p(-CAMERA_TILT_DEG, CAMERA_TILT_DEG, "deg", "... about y")
    camera_yaw_error_deg: float = _p(-CAMERA_TILT_DEG, CAMERA_TILT_DEG, "deg", "... about z")
    accel_bias_scale: float = _p(*IMU_BIAS_SCALE, "1", "x the nominal accelerometer bias sigma at power-up")
    gyro_bias_scale: float = _p(*IMU_BIAS_SCALE, "1", "x the nominal gyro bias sigma at power-up")
    room_height_entered: bool = _p(doc="the operator entered the room's height into the companion (else only "
                                       "its altitude fence holds)")
    room_height_error_m: float = _p(-ROOM_HEIGHT_ENTRY_ERROR_M, ROOM_HEIGHT_ENTRY_ERROR_M, "m",
                                    "the entered height minus the true one (when entered)")
    mass_scale: float = _p(1 - MASS_SPREAD, 1 + MASS_SPREAD, "1", "x the nominal mass (the companion keeps its "
                                                                  "nominal model)")
    sitl_seed: int = _p(0, 9999, "", "the SITL's own seed (noise and the biases' draws)")
    # last, so that the draws of the fields above are those of the searches before it
    obstacle_material: ObstacleMaterial = _p(doc="matte | dark (absorbs the Xtion's pattern: no depth return) | "
                                                 "specular (mirrors it away); the campaigns' hazards, not glass")

    def __post_init__(self) -> None:
        check(self)


#: obstacle_size 0..1 -> the kind's dimension: pole/column radius, box edge, doorway gap, wall/corner leg length
SIZE_RANGES_M: dict[str, tuple[float, float]] = {
    "pole": (0.02, 0.06), "column": (0.12, 0.4), "box": (0.4, 1.2), "doorway": (0.7, 1.6), "wall": (2.0, 6.0),
    "corner": (1.5, 4.0)}


def param_fields() -> list[dataclasses.Field[Any]]:
    return list(fields(FlightParams))


def choices(f: dataclasses.Field[Any]) -> tuple[Any, ...] | None:
    """The values of a categorical parameter (None for a numeric one)."""
    tp = {"obstacle_kind": ObstacleKind, "operator": OperatorKind, "push_direction": PushDirection,
          "obstacle_material": ObstacleMaterial}.get(f.name)
    if tp is not None:
        return get_args(tp)
    if f.name in ("pan_scan", "room_height_entered"):
        return (True, False)
    return None


def check(params: FlightParams) -> None:
    """Raise :class:`ConfigError` naming the first parameter out of its bounds or choices."""
    for f in param_fields():
        v = getattr(params, f.name)
        opts = choices(f)
        if opts is not None:
            if v not in opts:
                raise ConfigError(f"falsify parameter {f.name}={v!r}: not one of {', '.join(map(str, opts))}")
            continue
        lo, hi = f.metadata["low"], f.metadata["high"]
        if f.name == "sitl_seed":
            if not isinstance(v, int) or isinstance(v, bool):
                raise ConfigError(f"falsify parameter {f.name}={v!r}: not an integer")
        if not (isinstance(v, (int, float)) and math.isfinite(v) and lo <= v <= hi):
            raise ConfigError(f"falsify parameter {f.name}={v!r}: outside [{lo}, {hi}] {f.metadata['unit']}")


#: parameters added to the space since its first searches, and the value the flights before them had
ADDED_SINCE: dict[str, Any] = {"obstacle_material": "matte"}


def params_from_dict(data: dict[str, Any]) -> FlightParams:
    """A point from plain data (an Optuna trial's ``params``, params.json); unknown or missing names are errors,
    but for a parameter added since (:data:`ADDED_SINCE`), which an older study's trials lack."""
    names = {f.name for f in param_fields()}
    data = {**{k: v for k, v in ADDED_SINCE.items() if k not in data}, **data}
    unknown, missing = set(data) - names, names - set(data)
    if unknown or missing:
        raise ConfigError(f"falsify parameters: unknown {sorted(unknown)}, missing {sorted(missing)}")
    return FlightParams(**data)


def distributions() -> dict[str, Any]:
    """The space as Optuna distributions, by parameter name (what :func:`suggest` asks a trial for)."""
    from optuna.distributions import CategoricalDistribution, FloatDistribution, IntDistribution

    out: dict[str, Any] = {}
    for f in param_fields():
        opts = choices(f)
        if opts is not None:
            out[f.name] = CategoricalDistribution(list(opts))
        elif f.name == "sitl_seed":
            out[f.name] = IntDistribution(int(f.metadata["low"]), int(f.metadata["high"]))
        else:
            out[f.name] = FloatDistribution(f.metadata["low"], f.metadata["high"])
    return out


def suggest(trial: Any) -> FlightParams:
    """Ask an Optuna trial for a point (``suggest_*`` per field, named as the field)."""
    values: dict[str, Any] = {}
    for f in param_fields():
        opts = choices(f)
        if opts is not None:
            values[f.name] = trial.suggest_categorical(f.name, list(opts))
        elif f.name == "sitl_seed":
            values[f.name] = trial.suggest_int(f.name, int(f.metadata["low"]), int(f.metadata["high"]))
        else:
            values[f.name] = trial.suggest_float(f.name, f.metadata["low"], f.metadata["high"])
    return FlightParams(**values)


def sample(rng: np.random.Generator) -> FlightParams:
    """A uniform random point (tests; the search samples through Optuna)."""
    values: dict[str, Any] = {}
    for f in param_fields():
        opts = choices(f)
        if opts is not None:
            values[f.name] = opts[int(rng.integers(len(opts)))]
        elif f.name == "sitl_seed":
            values[f.name] = int(rng.integers(f.metadata["low"], f.metadata["high"] + 1))
        else:
            values[f.name] = float(rng.uniform(f.metadata["low"], f.metadata["high"]))
    return FlightParams(**values)


# --- the flight a point maps to --------------------------------------------------------------------------------


@dataclass(frozen=True)
class FalsifyFlight:
    params: FlightParams
    duration_s: float
    scenario: ScenarioConfig
    operator: OperatorKind  # the operator that flies it (diagonal/across: offboard)
    script: dict[str, Any]  # teleop script (haptic) or offboard plan (offboard)
    vehicle: dict[str, Any]
    sitl: dict[str, Any]
    companion: dict[str, Any]  # sections merged into configs/companion.yaml
    record: dict[str, Any]  # draws.json


def _unit(angle_rad: float) -> np.ndarray:
    return np.array([math.cos(angle_rad), math.sin(angle_rad)])


def _slab(name: str, centre: np.ndarray, along: np.ndarray, length_m: float, height_m: float) -> SceneObject:
    """A wall-high slab SLAB_THICKNESS_M thick whose long side runs along ``along``."""
    yaw = math.degrees(math.atan2(along[1], along[0]))
    return SceneObject(kind="box", name=name, position_m=(round(float(centre[0]), 4), round(float(centre[1]), 4),
                                                           round(-height_m / 2, 4)),
                       size_m=(round(length_m, 4), SLAB_THICKNESS_M, round(height_m, 4)), yaw_deg=round(yaw, 3),
                       texture="concrete", color=(0.75, 0.72, 0.68), surface="wall")


def obstacles(params: FlightParams) -> tuple[SceneObject, ...]:
    """The obstacle of ``params`` in the arena frame (take-off at the origin, heading north), of its material."""
    return tuple(dataclasses.replace(o, material=params.obstacle_material) for o in _obstacles(params))


def _obstacles(params: FlightParams) -> tuple[SceneObject, ...]:
    phi = MOTION_OFFSET_RAD + math.radians(params.obstacle_bearing_deg)
    u = _unit(phi)  # toward the obstacle
    t = _unit(phi + math.pi / 2)  # across it
    d, h = params.obstacle_distance_m, params.room_height_m
    lo, hi = SIZE_RANGES_M[params.obstacle_kind]
    size = lo + (hi - lo) * params.obstacle_size
    half_t = SLAB_THICKNESS_M / 2
    kind = params.obstacle_kind
    if kind == "wall":
        return (_slab("wall", (d + half_t) * u, t, size, h),)
    if kind == "doorway":
        leaf_m = 2.5
        return tuple(_slab(f"doorway-{k}", (d + half_t) * u + s * (size / 2 + leaf_m / 2) * t, t, leaf_m, h)
                     for k, s in enumerate((-1.0, 1.0)))
    if kind == "corner":  # an inside corner: vertex at d sqrt 2, legs coming back at +-45 deg to the line of sight
        vertex = d * math.sqrt(2.0) * u
        out = []
        for k, s in enumerate((-1.0, 1.0)):
            w = _unit(phi + math.pi + s * math.pi / 4)  # along the leg, away from the vertex
            foot = vertex - float(vertex @ w) * w  # the leg's nearest point to the take-off point, d away
            n = foot / np.linalg.norm(foot)  # the leg's outward normal: the slab lies beyond its inner face
            length = max(size, d + 0.5)
            # the leg starts a slab's thickness behind the vertex so the two legs close the corner
            centre = vertex + w * (length / 2 - SLAB_THICKNESS_M) + n * half_t
            out.append(_slab(f"corner-{k}", centre, w, length, h))
        return tuple(out)
    if kind in ("pole", "column"):
        c = (d + size) * u
        return (SceneObject(kind="cylinder", name=kind, position_m=(round(float(c[0]), 4), round(float(c[1]), 4),
                                                                   round(-h / 2, 4)),
                            radius_m=round(size, 4), height_m=round(h, 4), texture="wood", color=(0.6, 0.45, 0.3)),)
    # box: a face toward the take-off point; its top between 0.6 m and 1.6 m (in and around the flight band)
    box_h = 0.6 + 1.0 * params.obstacle_size
    c = (d + size / 2) * u
    return (SceneObject(kind="box", name="box", position_m=(round(float(c[0]), 4), round(float(c[1]), 4),
                                                           round(-box_h / 2, 4)),
                        size_m=(round(size, 4), round(size, 4), round(box_h, 4)),
                        yaw_deg=round(math.degrees(phi), 3), texture="noise", color=(0.55, 0.65, 0.8)),)


def scenario_of(params: FlightParams, name: str = "falsify") -> ScenarioConfig:
    room = RoomConfig(size_m=ROOM_SIZE_M, height_m=round(params.room_height_m, 4), floor_texture="carpet",
                      wall_texture="concrete", ceiling_texture="noise")
    p = params
    what = p.obstacle_kind if p.obstacle_material == "matte" else f"{p.obstacle_material} {p.obstacle_kind}"
    return ScenarioConfig(name=name, description=(
        f"falsify: {what} {p.obstacle_distance_m:.2f} m at {p.obstacle_bearing_deg:+.0f} deg from the "
        f"camera axis, room {p.room_height_m:.2f} m high"), room=room, start=StartPose((0.0, 0.0), 0.0),
        objects=obstacles(params))


def operator_of(params: FlightParams) -> OperatorKind:
    return params.operator if params.push_direction in HAPTIC_DIRECTIONS else "offboard"


def _phases(params: FlightParams, duration_s: float) -> tuple[float, float, float]:
    """(hold before the push, push, hold after it) in seconds, between the take-off phase and the landing."""
    window = max(0.0, duration_s - TAKEOFF_S - LANDING_S)
    before = min(params.push_start_s, window)
    push = min(params.push_duration_s, window - before)
    return before, push, window - before - push


def session_of(params: FlightParams, duration_s: float) -> tuple[OperatorKind, dict[str, Any]]:
    """The operator and its script (haptic: a virtual-device teleop script; offboard: a velocity plan)."""
    before, push, after = _phases(params, duration_s)
    speed = params.push_speed_fraction
    yaw_frac = params.push_yaw_rate_rad_s / MAX_YAW_RATE_RAD_S
    kind = operator_of(params)
    if kind == "haptic":
        sign = 1.0 if params.push_direction == "along" else -1.0
        force = [round(sign * speed * FULL_DEFLECTION_N * HANDLE_GAIN, 4),
                 round(yaw_frac * FULL_DEFLECTION_N * HANDLE_GAIN, 4),
                 round(-params.push_climb_m_s / CLIMB_MAX_M_S * FULL_DEFLECTION_N * HANDLE_GAIN, 4)]
        steps: list[dict[str, Any]] = [{"wait_s": 2.0}, {"button": "arm"}, {"wait_s": 1.0}, {"button": "takeoff"},
                                       {"wait_s": TAKEOFF_S - 3.0}]
        for dur, step in ((before, {"release": True}), (push, {"force_d_n": force}), (after, {"release": True})):
            if dur > 0:
                steps.append({**step, "duration_s": round(dur, 4)})
        steps += [{"button": "land"}, {"wait_s": LANDING_S}]
        return kind, {"name": "falsify session", "steps": steps}
    v = speed * MAX_SPEED_M_S
    a = MOTION_OFFSET_RAD + PUSH_ANGLE_RAD[params.push_direction]  # from the heading (body x)
    hold = {"frame": "body", "forward_m_s": 0.0, "right_m_s": 0.0, "down_m_s": 0.0, "yawspeed_deg_s": 0.0}
    segments = []
    for dur, seg in ((before, hold),
                     (push, {"frame": "body", "forward_m_s": round(v * math.cos(a), 4),
                             "right_m_s": round(v * math.sin(a), 4), "down_m_s": round(-params.push_climb_m_s, 4),
                             "yawspeed_deg_s": round(math.degrees(params.push_yaw_rate_rad_s), 3)}),
                     (after, hold)):
        if dur > 0:
            segments.append({**seg, "duration_s": round(dur, 4)})
    return kind, {"name": "falsify offboard session", "takeoff_s": TAKEOFF_S, "landing_s": LANDING_S,
                  "duration_s": duration_s, "segments": segments}


def vehicle_and_sitl(params: FlightParams) -> tuple[dict[str, Any], dict[str, Any]]:
    """The SITL's truth: the vehicle (mass, camera mount) and the SITL config (seed, IMU bias spreads)."""
    vehicle = yaml.safe_load((CONFIG_DIR / "vehicle.yaml").read_text())
    vehicle["mass_kg"] = round(vehicle["mass_kg"] * params.mass_scale, 6)
    vehicle["camera"]["R_qc"] = mount_turned(vehicle["camera"]["R_qc"], [
        params.camera_roll_error_deg, params.camera_pitch_error_deg, params.camera_yaw_error_deg])
    sitl = yaml.safe_load((CONFIG_DIR / "sitl.yaml").read_text())
    sitl["seed"] = int(params.sitl_seed)
    imu = ImuNoiseConfig()
    sitl.setdefault("imu_noise", {})
    sitl["imu_noise"]["accel_bias_init_m_s2"] = round(imu.accel_bias_init_m_s2 * params.accel_bias_scale, 9)
    sitl["imu_noise"]["gyro_bias_init_rad_s"] = round(imu.gyro_bias_init_rad_s * params.gyro_bias_scale, 9)
    sitl.setdefault("camera_noise", {})
    sitl["camera_noise"]["depth_sigma_per_m2"] = CameraNoiseConfig().depth_sigma_per_m2
    return vehicle, sitl


def build_flight(params: FlightParams, duration_s: float, name: str = "falsify") -> FalsifyFlight:
    """The flight of a point (pure, deterministic). Raises :class:`ConfigError` if the arena leaves no room to
    take off (cannot happen within the bounds; checked because the runner would fly it anyway)."""
    check(params)
    scenario = scenario_of(params, name)
    start_clear_m = clearance_2d(scenario, scenario.start.position_m)
    if not start_clear_m >= MIN_START_CLEARANCE_M:
        raise ConfigError(f"falsify point: the take-off point is {start_clear_m:.2f} m from the {params.obstacle_kind}")
    kind, script = session_of(params, duration_s)
    vehicle, sitl = vehicle_and_sitl(params)
    entered = round(params.room_height_m + params.room_height_error_m, 4) if params.room_height_entered else None
    companion = {"reference": {"room_height_m": entered},
                 "pan_scan": {"enabled": bool(params.pan_scan)}}
    record = {"falsify": dataclasses.asdict(params), "duration_s": duration_s, "operator_flown": kind,
              "start_clearance_m": start_clear_m, "phases_s": list(_phases(params, duration_s)),
              "arena": {"layout": f"falsify:{params.obstacle_kind}", "room_size_m": list(ROOM_SIZE_M),
                        "room_height_m": params.room_height_m, "objects": len(scenario.objects)}}
    return FalsifyFlight(params, duration_s, scenario, kind, script, vehicle, sitl, companion, record)


def write_flight(flight: FalsifyFlight, folder: Path) -> tuple[FlightFiles, Path]:
    """``scenario.yaml``, ``operator.yaml``, ``vehicle.yaml``, ``sitl.yaml``, ``companion.yaml``, ``draws.json``
    in ``folder``; returns the files and the companion config's path."""
    files = write_sitl_files(flight.scenario, flight.vehicle, flight.sitl, flight.record, folder)
    files.operator.write_text(yaml.safe_dump(flight.script, sort_keys=False))
    companion = write_companion_config(folder, **flight.companion)
    return files, companion

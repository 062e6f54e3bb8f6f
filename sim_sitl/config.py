"""Typed configuration of the SITL (``configs/sitl.yaml``) and of its scenarios (``configs/scenarios/*.yaml``).

Scenario geometry is given in the *arena frame*: NED (x north, y east, z down) with its origin on the
floor at the centre of the room, so a box standing on the floor with height h has its centre at
z = -h/2. Ground truth is published in local NED with its origin at the vehicle's start position.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from quadlink import CONFIG_DIR
from quadlink.config import find_config, load_config
from quadlink.errors import ConfigError
from sim_sitl.baro import BaroConfig
from sim_sitl.disturbance import Push


@dataclass(frozen=True)
class FirmwareConfig:
    """The board's attitude loop (500 Hz) and its safety logic."""

    loop_rate_hz: float = 500.0
    angle_kp_1_s: float = 7.0  # roll/pitch angle error (rad) -> rate setpoint (rad/s)
    rate_kp_1_s: float = 16.0  # rate error (rad/s) -> angular acceleration (rad/s^2) per rad/s
    rate_ki_1_s2: float = 20.0
    rate_kd: float = 0.15  # on the measured rate (rad/s^2 per rad/s^2)
    yaw_rate_kp_1_s: float = 8.0
    yaw_rate_ki_1_s2: float = 4.0
    max_tilt_rad: float = 0.6  # setpoint clamp on roll and pitch
    max_rate_rad_s: float = 3.5  # roll/pitch rate setpoint clamp
    max_yaw_rate_rad_s: float = 2.5
    integrator_limit_rad_s2: float = 20.0  # anti wind-up, angular acceleration units
    setpoint_timeout_s: float = 0.5  # no setpoint for this long while armed and flying -> failsafe
    failsafe_descent_thrust_fraction: float = 0.85  # of hover thrust: a slow descent holding level attitude
    landed_thrust_fraction: float = 0.15  # collective below this (of max) with no climb = landed
    failsafe_ground_speed_m_s: float = 0.15  # |vz| below this near ground while descending = on the ground


@dataclass(frozen=True)
class ImuNoiseConfig:
    """IMU error model on top of the 10-bit quantisation of ``VehicleConfig.imu``."""

    accel_noise_m_s2: float = 0.06  # white noise sigma per sample
    gyro_noise_rad_s: float = 0.004
    accel_bias_walk_m_s2_sqrt_s: float = 0.003  # random-walk density: sigma grows with sqrt(t)
    gyro_bias_walk_rad_s_sqrt_s: float = 0.0005
    accel_bias_init_m_s2: float = 0.05  # sigma of the bias at power-up
    gyro_bias_init_rad_s: float = 0.005
    vibration_accel_m_s2: float = 0.4  # amplitude at full thrust, per motor
    vibration_gyro_rad_s: float = 0.01
    rotor_hz_at_full_thrust: float = 140.0  # propeller frequency at max thrust (aliases at 500 Hz)


@dataclass(frozen=True)
class PhysicsConfig:
    rate_hz: float = 500.0  # pybullet steps per second (>= the firmware loop rate)
    rotor_drag_n_s_m_per_n: float = 0.02  # horizontal rotor (induced) drag per newton of thrust
    body_size_m: tuple[float, float, float] = (0.36, 0.36, 0.20)  # collision box incl. landing gear; CoM centred
    ground_friction: float = 0.8


@dataclass(frozen=True)
class LinkConfig:
    baud: int = 115200
    bits_per_byte: int = 10  # 8N1: start + 8 data + stop
    tx_buffer_bytes: int = 256  # UART TX ring of the board; frames that do not fit are dropped
    late_after_s: float = 0.004  # a frame that waits longer than this before its first byte is "late"


@dataclass(frozen=True)
class CameraNoiseConfig:
    depth_sigma_per_m2: float = 0.0025  # sigma_z = k z^2 (structured-light sensors)
    max_incidence_deg: float = 78.0  # grazing angle beyond which depth is invalid
    depth_quantum_m: float = 0.001
    rgb_noise_levels: float = 1.5  # sigma of the colour noise, 8-bit levels
    near_clip_m: float = 0.05
    far_clip_m: float = 20.0


RendererName = Literal["raster", "pybullet"]
BoardName = Literal["model", "avr"]


@dataclass(frozen=True)
class SitlCameraConfig:
    """How the SITL renders its camera (the mount and intrinsics are the vehicle's: ``VehicleConfig.camera``)."""

    renderer: RendererName = "raster"  # raster (sim_sitl/raster.py, fast) | pybullet (ER_TINY_RENDERER)


@dataclass(frozen=True)
class SitlConfig:
    vehicle: str = "vehicle"  # vehicle config name or path
    scenario: str = "paper-arena"
    seed: int = 1
    battery_drain_mv_per_s: float = 3.0  # flying; a 3S pack from 12.6 V
    firmware: FirmwareConfig = field(default_factory=FirmwareConfig)
    imu_noise: ImuNoiseConfig = field(default_factory=ImuNoiseConfig)
    physics: PhysicsConfig = field(default_factory=PhysicsConfig)
    link: LinkConfig = field(default_factory=LinkConfig)
    camera: SitlCameraConfig = field(default_factory=SitlCameraConfig)
    camera_noise: CameraNoiseConfig = field(default_factory=CameraNoiseConfig)
    truth_rate_hz: float = 50.0
    lockstep_chunk_s: float = 0.01
    lockstep_timeout_s: float = 2.0
    # what flies: the Python board model (sim_sitl/firmware.py) or the firmware binary in simavr (sim_sitl/avr_board.py)
    board: BoardName = "model"
    firmware_elf: str | None = None  # board avr: the ELF to fly; None = the repo's firmware/build/quadlink-fc.elf
    baro: BaroConfig = field(default_factory=BaroConfig)  # board avr: the pressure sensor on ADC6


@dataclass(frozen=True)
class SceneObject:
    """A static body: ``box`` (size_m = full extents, arena NED axes before yaw) or ``cylinder`` (vertical)."""

    kind: Literal["box", "cylinder"] = "box"
    name: str = ""
    position_m: tuple[float, float, float] = (0.0, 0.0, 0.0)  # centre, arena NED
    size_m: tuple[float, float, float] = (1.0, 1.0, 1.0)
    radius_m: float = 0.25
    height_m: float = 1.0
    yaw_deg: float = 0.0
    texture: str = "noise"  # procedural: carpet, wood, concrete, noise, checker, plain
    color: tuple[float, float, float] = (0.7, 0.7, 0.7)
    surface: Literal["object", "floor", "wall", "ceiling"] = "object"  # a rug counts as floor for truth id 1


@dataclass(frozen=True)
class RoomConfig:
    size_m: tuple[float, float] = (10.0, 10.0)  # north x east extent
    height_m: float = 3.0
    walls: bool = True
    ceiling: bool = True
    floor_texture: str = "carpet"
    wall_texture: str = "concrete"
    ceiling_texture: str = "plain"


@dataclass(frozen=True)
class StartPose:
    position_m: tuple[float, float] = (0.0, 0.0)  # arena north, east (on the floor)
    yaw_deg: float = 0.0


@dataclass(frozen=True)
class ScenarioConfig:
    name: str = "empty"
    description: str = ""
    room: RoomConfig = field(default_factory=RoomConfig)
    start: StartPose = field(default_factory=StartPose)
    objects: tuple[SceneObject, ...] = ()
    disturbances: tuple[Push, ...] = ()  # scripted pushes on the vehicle (sim_sitl/disturbance.py), SITL time


SCENARIO_DIR = Path(CONFIG_DIR) / "scenarios"


def known_scenarios() -> list[str]:
    return sorted(p.stem for p in SCENARIO_DIR.glob("*.yaml"))


def load_scenario(name_or_path: str) -> ScenarioConfig:
    """Load a scenario by name (``configs/scenarios/<name>.yaml``) or by path; unknown name -> ConfigError."""
    path = Path(name_or_path)
    if path.suffix in (".yaml", ".yml") and path.is_file():
        return load_config(path, ScenarioConfig)
    candidate = SCENARIO_DIR / f"{name_or_path}.yaml"
    if not candidate.is_file():
        raise ConfigError(f"unknown scenario {name_or_path!r} (known: {', '.join(known_scenarios())})")
    return load_config(candidate, ScenarioConfig)


def load_sitl_config(path: str | Path | None = None) -> SitlConfig:
    """Load ``configs/sitl.yaml`` (or the given file)."""
    if path is None:
        return load_config(find_config("sitl"), SitlConfig)
    return load_config(path, SitlConfig)

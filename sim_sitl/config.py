"""Typed configuration of the SITL (``configs/sitl.yaml``) and of its scenarios (``configs/scenarios/*.yaml``).

Scenario geometry is given in the *arena frame*: NED (x north, y east, z down) with its origin on the
floor at the centre of the room, so a box standing on the floor with height h has its centre at
z = -h/2. Ground truth is published in local NED with its origin at the vehicle's start position.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, get_args

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
class XtionConfig:
    """How a structured-light RGB-D camera (Asus Xtion, Kinect v1) fails; used when ``CameraNoiseConfig.model``
    is ``xtion`` (``sim_sitl/xtion.py`` implements it; the valid range is the mount's ``min/max_range_m``).

    Depth comes from the disparity d = f b / z between the IR camera and the projected pattern, measured in
    1/8 pixel; noise and steps live in disparity, so in depth both grow with z^2 (Khoshelham & Oude Elberink,
    "Accuracy and resolution of Kinect depth data for indoor mapping applications", Sensors 12 (2012) 1437:
    the disparity-depth relation and its error propagation): sigma_z = z^2 sigma_d / (f b), step_z = z^2 step_d
    / (f b).
    """

    ir_focal_px: float = 580.0  # IR camera focal length at 640x480 (Kinect/Xtion calibrations give 570-590 px)
    # the projector's position along the IR camera's optical x axis: the baseline b = |projector_x_m| (K&OE 2012:
    # ~7.5 cm). A point the projector cannot light is a hole: a band f b (1/z_near - 1/z_far) px wide beside a
    # foreground edge, on the side away from the projector (light from the right casts shadows to the left).
    # +x, the camera's right: the PrimeSense layout (Kinect, Xtion), whose shadows fall left of foreground objects.
    projector_x_m: float = 0.075
    disparity_step_px: float = 0.125  # disparity is reported in 1/8 px: step_z = z^2 / 348 m^-1, 1.15 cm at 2 m
    # sigma_z = z^2 sigma_d / (f b): 0.0696 px gives 4.0 cm at 5 m, the random error K&OE 2012 measured there
    disparity_sigma_px: float = 0.0696
    frame_drop_probability: float = 0.01  # each 30 Hz frame independently lost on the USB link (not published)
    stamp_jitter_s: float = 0.002  # sigma of the stamp's error (host-side stamping of USB frames)
    stamp_jitter_max_s: float = 0.006  # the jitter is clipped here (and stays below half a frame period)
    exposure_s: float = 0.015  # RGB exposure: motion blur integrates the image motion over it (indoor auto-exposure)
    blur_min_px: float = 0.5  # no blur below this smear length (at rest it costs nothing)
    blur_sample_spacing_px: float = 1.5  # shifted samples averaged along the motion, this far apart (bilinear)...
    blur_max_samples: int = 8  # ...and at most this many (each costs ~0.2 ms at 320x240)

    def __post_init__(self) -> None:
        if not self.ir_focal_px > 0:
            raise ValueError(f"ir_focal_px must be > 0, got {self.ir_focal_px!r}")
        if self.projector_x_m == 0:
            raise ValueError("projector_x_m must not be 0 (no baseline, no depth)")
        for name in ("disparity_step_px", "disparity_sigma_px", "stamp_jitter_s", "stamp_jitter_max_s",
                     "exposure_s", "blur_min_px"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)!r}")
        if not 0.0 <= self.frame_drop_probability < 1.0:
            raise ValueError(f"frame_drop_probability must be in [0, 1), got {self.frame_drop_probability!r}")
        if self.blur_max_samples < 2:
            raise ValueError(f"blur_max_samples must be >= 2, got {self.blur_max_samples!r}")
        if not self.blur_sample_spacing_px > 0:
            raise ValueError(f"blur_sample_spacing_px must be > 0, got {self.blur_sample_spacing_px!r}")


CameraModelName = Literal["basic", "xtion"]


@dataclass(frozen=True)
class CameraNoiseConfig:
    # basic: sigma = k z^2, fixed depth steps, grazing-angle dropouts; xtion: ``XtionConfig`` on top of the
    # grazing-angle dropouts (disparity noise and steps, IR shadows, dark/specular/glass, drops, jitter, blur)
    model: CameraModelName = "basic"
    depth_sigma_per_m2: float = 0.0025  # sigma_z = k z^2 (structured-light sensors); basic model
    max_incidence_deg: float = 78.0  # grazing angle beyond which depth is invalid
    depth_quantum_m: float = 0.001  # basic model
    rgb_noise_levels: float = 1.5  # sigma of the colour noise, 8-bit levels
    near_clip_m: float = 0.05
    far_clip_m: float = 20.0
    xtion: XtionConfig = field(default_factory=XtionConfig)


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


#: what a surface does to the structured light (``sim_sitl/xtion.py``): matte returns it; dark (a black monitor)
#: absorbs it and specular (a glossy panel) mirrors it away: no return; glass passes it and the visible light:
#: invisible in depth and colour (the renderer sees what is behind), yet a solid body for the physics
Material = Literal["matte", "dark", "specular", "glass"]
MATERIALS: tuple[str, ...] = get_args(Material)


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
    material: Material = "matte"


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

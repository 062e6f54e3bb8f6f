"""Typed configuration of the ground station (``configs/teleop.yaml``), defaults in one place.

Device frame D is NED (x forward, y right, z down), origin at the handle's rest position
(paper 000 section II). Gains are diagonal (one value per D axis).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from quadlink.config import find_config, load_config
from quadlink.ids import COMPANION_COMPONENT_ID, GROUND_COMPONENT_ID
from quadlink.mavlink import mavlink

Vec3Cfg = tuple[float, float, float]


@dataclass(frozen=True)
class DeviceConfig:
    """Haptic device model and limits (eq. (1): M q'' + C q' = tau + f, diagonal M and C)."""

    mass_kg: Vec3Cfg = (0.25, 0.25, 0.25)              # M, effective handle mass per axis
    damping_n_s_m: Vec3Cfg = (2.0, 2.0, 2.0)           # C, mechanism viscous friction
    workspace_m: Vec3Cfg = (0.08, 0.08, 0.08)          # half range per axis (omega.6: about +-0.08 m)
    force_limit_n: float = 12.0                        # omega.6 continuous force limit
    force_rate_hz: float = 1000.0                      # force loop rate
    spin_s: float = 0.0001                             # busy-wait before each tick (precise sleep)
    realtime_priority: int = 20                        # SCHED_FIFO priority of the force thread; 0 = normal

    def __post_init__(self) -> None:
        if min(self.mass_kg) <= 0 or min(self.damping_n_s_m) < 0 or min(self.workspace_m) <= 0:
            raise ValueError("mass_kg and workspace_m must be > 0, damping_n_s_m >= 0")
        if self.force_limit_n <= 0 or self.force_rate_hz <= 0:
            raise ValueError("force_limit_n and force_rate_hz must be > 0")


@dataclass(frozen=True)
class ForceConfig:
    """Force feedback gains, eq. (15): tau = -B q' - K_f q - K (q - q~)."""

    B_n_s_m: Vec3Cfg = (3.0, 3.0, 3.0)                 # damping
    K_f_n_m: Vec3Cfg = (20.0, 20.0, 20.0)              # centring spring
    K_n_m: Vec3Cfg = (60.0, 40.0, 60.0)                # haptic cue on the velocity error
    link_timeout_s: float = 0.5                        # no TELEOP_FEEDBACK for this long = link lost
    fade_time_s: float = 1.0                           # force fades 1 -> 0 over this time (rate-limited)
    pan_scan_source: Literal["estimated", "commanded"] = "commanded"  # the psi_s' removed in eq. (17)
    cue_modes: tuple[int, ...] = (mavlink.QUADLINK_TELEOP_MODE_TELEOP,   # companion modes with the cue
                                  mavlink.QUADLINK_TELEOP_MODE_HOLD)     # K (q - q~)

    def __post_init__(self) -> None:
        if min(self.B_n_s_m + self.K_f_n_m + self.K_n_m) < 0:
            raise ValueError("force gains must be >= 0")
        if self.fade_time_s <= 0 or self.link_timeout_s <= 0:
            raise ValueError("fade_time_s and link_timeout_s must be > 0")


@dataclass(frozen=True)
class PassivityConfig:
    """Time-domain passivity observer/controller on the device port (teleop/passivity.py, Hannaford & Ryu 2002).

    The observer always runs (its energy is logged); ``enabled`` adds the variable damping that keeps the
    observed energy >= 0 when the force loop is closed through a delayed link, and ``tank_layer`` the
    energy-tank bound behind it (Franken et al., IEEE T-RO 27(4), 2011): the port never delivers work the
    observed energy does not hold, predicted over the measured period.
    """

    enabled: bool = False
    max_damping_n_s_m: float = 150.0     # bound on alpha (sampled damper: alpha T / M < 2, 500 at 1 kHz, 0.25 kg)
    max_force_n: float = 6.0             # bound on the controller's force per axis
    min_speed_m_s: float = 0.002         # no damping below this speed (alpha would be unbounded)
    energy_cap_j: float = 0.0            # cap on each axis' stored credit (energy tank ceiling); 0 = none
    log_period_s: float = 5.0            # energy account to the log every this many seconds
    tank_layer: bool = True              # the passivity layer behind the damping (only with enabled)
    period_hold_s: float = 2.0           # the layer predicts over the longest period measured in this window

    def __post_init__(self) -> None:
        values = (self.max_damping_n_s_m, self.max_force_n, self.min_speed_m_s, self.energy_cap_j,
                  self.log_period_s, self.period_hold_s)
        if not all(math.isfinite(v) for v in values):
            raise ValueError("passivity values must be finite")
        if min(self.max_damping_n_s_m, self.max_force_n, self.log_period_s, self.period_hold_s) <= 0:
            raise ValueError("passivity max_damping_n_s_m, max_force_n, log_period_s and period_hold_s must be > 0")
        if self.min_speed_m_s < 0 or self.energy_cap_j < 0:
            raise ValueError("passivity min_speed_m_s and energy_cap_j must be >= 0")


@dataclass(frozen=True)
class MappingConfig:
    """q -> MANUAL_CONTROL (eqs. (2)-(3)). Full scale (1000) = the companion's maximum command.

    The ``max_*`` values and ``companion_deadband`` must match the companion's ``reference`` config
    (k_v_m_s, k_climb_m_s, k_psi_rad_s, deadband): the force law inverts the whole chain (eqs. (16)-(18)).
    """

    deadband_m: Vec3Cfg = (0.004, 0.004, 0.004)
    max_speed_m_s: float = 0.6              # companion k_v_m_s: speed at x = +-1000
    max_climb_m_s: float = 0.4              # companion k_climb_m_s: climb rate at z = 0 or 1000
    max_yaw_rate_rad_s: float = 0.8         # companion k_psi_rad_s: yaw rate at full yaw deflection
    companion_deadband: float = 0.03        # companion's own dead-band on the normalized axes
    yaw_axis: Literal["y", "r"] = "y"       # MANUAL_CONTROL field carrying the yaw command (companion: y)
    yaw_sign: float = 1.0                   # eq. (3) in NED: handle right -> turn right (positive yaw rate)
    rate_hz: float = 50.0                   # MANUAL_CONTROL rate
    target_system: int = 1

    def __post_init__(self) -> None:
        if self.rate_hz < 50.0:
            raise ValueError("rate_hz must be >= 50 (DESIGN.md operator command rate)")
        if self.yaw_sign not in (-1.0, 1.0):
            raise ValueError("yaw_sign must be -1 or 1")
        if not 0.0 <= self.companion_deadband < 1.0:
            raise ValueError("companion_deadband must be in [0, 1)")


@dataclass(frozen=True)
class CommandsConfig:
    """Buttons -> COMMAND_LONG / PARAM_SET, with acks.

    arm/disarm/takeoff/land go to ``command_component``: the companion (191) runs them through its mode
    machine (checks, autonomous take-off, then the autopilot); 1 would send them to the autopilot directly,
    bypassing the companion's modes.
    """

    autopilot_system: int = 1
    autopilot_component: int = 1
    companion_component: int = COMPANION_COMPONENT_ID
    command_component: int = COMPANION_COMPONENT_ID
    pan_scan_param: str = "PANSCAN_EN"
    takeoff_altitude_m: float = 1.0
    ack_timeout_s: float = 1.0
    retries: int = 2


@dataclass(frozen=True)
class ViewConfig:
    """Operator view (section VI-B)."""

    canvas_width_px: int = 560
    canvas_height_px: int = 420
    background_decay_s: float = 0.6          # time constant of the exponential decay of old images
    jpeg_quality: int = 80
    min_frequency_hz: float = 0.05           # peak-to-peak estimator range
    max_frequency_hz: float = 3.0
    initial_frequency_hz: float = 0.25       # companion default: omega 1.5 rad/s
    bandpass_q: float = 1.5                  # quality factor of the band-pass (unit gain at f0)
    bias_periods: float = 1.0                # length of the moving-average bias low-pass, in periods
    operator_yaw_time_constant_s: float = 0.15  # yaw-loop model for removing the operator's turns (0 = step)
    obstacle_warning_m: float = 0.8
    battery_warning_v: float = 10.5


@dataclass(frozen=True)
class NetworkConfig:
    vehicle_url: str = "udpout:127.0.0.1:14555"
    image_stream_url: str = "tcp://127.0.0.1:5770"
    http_host: str = "127.0.0.1"
    http_port: int = 8080
    source_system: int = 255
    source_component: int = GROUND_COMPONENT_ID
    heartbeat_timeout_s: float = 2.0      # no autopilot HEARTBEAT (through the companion) this long: a warning
    signing_key_file: str | None = None   # MAVLink 2 signing key shared with the vehicle (quadlink keygen FILE)
    signing_link_id: int = 0              # signing stream id: distinct per ground station sharing a system id


@dataclass(frozen=True)
class TeleopConfig:
    device: DeviceConfig = field(default_factory=DeviceConfig)
    force: ForceConfig = field(default_factory=ForceConfig)
    passivity: PassivityConfig = field(default_factory=PassivityConfig)
    mapping: MappingConfig = field(default_factory=MappingConfig)
    commands: CommandsConfig = field(default_factory=CommandsConfig)
    view: ViewConfig = field(default_factory=ViewConfig)
    network: NetworkConfig = field(default_factory=NetworkConfig)


def load_teleop_config(name_or_path: str | Path = "teleop") -> TeleopConfig:
    return load_config(find_config(str(name_or_path)), TeleopConfig)

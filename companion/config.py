"""Typed configuration of the companion daemon (``configs/companion.yaml``), defaults in one place."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from companion.arbiter import ArbiterParams
from companion.landing_spot import LandingSpotParams
from companion.latency import LatencyParams
from companion.modes import ModeParams
from companion.pan_scan import PanScanParams
from companion.position_hold import PositionHoldParams
from companion.reference_params import ReferenceParams
from companion.seen_ground import SeenGroundParams
from quadlink.config import find_config, load_config
from quadlink.ids import COMPANION_COMPONENT_ID
from quadlink.mavlink.security import SecurityConfig


@dataclass(frozen=True)
class LinksConfig:
    """Where the daemon connects (each overridable on the command line)."""

    autopilot: str = "udpin:0.0.0.0:14540"  # MAVLink, where the bridge (or PX4) sends
    gcs: str = "udpin:0.0.0.0:14555"  # MAVLink, where ground stations send to the vehicle
    camera: str = "tcp://127.0.0.1:5762"  # SITL camera stream, or a TUM-format folder for replay
    image_host: str = "127.0.0.1"  # operator image stream (camera record format, JPEG colour)
    image_port: int = 5770
    gcs_client_timeout_s: float = 10.0  # a GCS client silent this long stops receiving telemetry
    # commands have an age (issue 18, companion/command_age.py): stamped commands older than this are dropped;
    # the HOLD and LAND timeouts on no fresh command are modes.gcs_timeout_s and modes.gcs_land_timeout_s
    max_command_age_s: float = 0.5
    gcs_timesync_period_s: float = 0.5  # TIMESYNC requests to each ground station (the commands' clock offset)
    gcs_timesync_max_rtt_s: float = 2.0  # round trips above this are not used for the offset


@dataclass(frozen=True)
class IdentityConfig:
    """MAVLink identity: the companion uses the autopilot's system id and MAV_COMP_ID_ONBOARD_COMPUTER."""

    system_id: int = 1  # used until the autopilot's HEARTBEAT tells the real one
    component_id: int = COMPANION_COMPONENT_ID
    autopilot_component_id: int = 1


@dataclass(frozen=True)
class TimingConfig:
    """Rates and timeouts. ``camera_stamps``: 'autopilot' when frame stamps are already autopilot time
    (the SITL: both are simulated time), 'local' when they are this computer's monotonic clock (a real
    camera) and are converted with the TIMESYNC offset."""

    feedback_rate_hz: float = 50.0
    heartbeat_rate_hz: float = 1.0
    timesync_period_s: float = 1.0
    camera_stamps: Literal["autopilot", "local"] = "autopilot"
    imu_wait_s: float = 0.005  # wait at most this long for the IMU to catch up with a frame ...
    imu_slack_s: float = 0.005  # ... when its last sample is older than the frame by more than this
    camera_timeout_s: float = 0.3  # no frame for this long (wall): obstacle data stale, odometry failed
    fallback_setpoint_rate_hz: float = 10.0  # setpoints sent while the camera is silent
    poll_s: float = 0.004  # main loop wait per iteration
    # the process's niceness (quadlink.realtime.set_nice; 0: leave it; below 0 needs CAP_SYS_NICE): on a board the
    # companion shares, -5 keeps perception ahead of the rest, behind the bridge's SCHED_FIFO
    nice: int = 0


@dataclass(frozen=True)
class PanScanConfig:
    """Pan-scan carrier (eq. 4) and how its closed-loop response (eq. 5) is obtained.

    ``response``: 'model' computes A'_omega, phi_omega from the first-order yaw model
    (yaw_time_constant_s, yaw_delay_s); 'fixed' uses gain and phase_rad as given (e.g. identified from
    a logged flight with ``quadlink.analysis.yaw_identification.identify_from_log``).
    """

    enabled: bool = True
    amplitude_rad_s: float = 0.6
    omega_rad_s: float = 1.5
    response: Literal["model", "fixed"] = "model"
    yaw_time_constant_s: float = 0.15
    yaw_delay_s: float = 0.02
    gain: float = 1.0
    phase_rad: float = -math.pi


@dataclass(frozen=True)
class ObstacleConfig:
    """OBSTACLE_DISTANCE ranges (cm, the camera's 0.5-3.5 m) and the unknown-sector policy."""

    min_distance_cm: int = 50
    max_distance_cm: int = 350
    allow_unknown_when_fresh: bool = True  # like PX4 CP_GO_NO_DATA=1 while the data are fresh
    # scripted commands (offboard setpoints, trajectories) toward sectors the map has not looked at: refused by
    # default (PX4 CP_GO_NO_DATA=0 for scripts); True lets them go where the map has not looked, with fresh data
    # (paper 003's experiments: a trajectory around the vehicle, the camera looking one way)
    scripts_into_unknown: bool = False


@dataclass(frozen=True)
class CompanionConfig:
    links: LinksConfig = field(default_factory=LinksConfig)
    identity: IdentityConfig = field(default_factory=IdentityConfig)
    timing: TimingConfig = field(default_factory=TimingConfig)
    reference: ReferenceParams = field(default_factory=ReferenceParams)
    pan_scan: PanScanConfig = field(default_factory=PanScanConfig)
    modes: ModeParams = field(default_factory=ModeParams)
    obstacles: ObstacleConfig = field(default_factory=ObstacleConfig)
    arbiter: ArbiterParams = field(default_factory=ArbiterParams)   # sources of motion (companion.arbiter)
    landing_spot: LandingSpotParams = field(default_factory=LandingSpotParams)   # commanded landings over objects
    seen_ground: SeenGroundParams = field(default_factory=SeenGroundParams)   # ... and over ground never seen
    latency: LatencyParams = field(default_factory=LatencyParams)   # late data: what the safety law pays for it
    # where the reference stops the vehicle, hold the place (companion.position_hold), not just v = 0
    position_hold: PositionHoldParams = field(default_factory=PositionHoldParams)
    # signing and the sender allowlist on the ground-station endpoint (the autopilot link is internal)
    security: SecurityConfig = field(default_factory=SecurityConfig)
    vehicle: str = "vehicle"  # vehicle config (camera mount R_qc, p_qc) by name or path
    perception_config: str | None = None  # YAML for perception.pipeline.PerceptionConfig; None = defaults
    seed: int = 0


def load_companion_config(path: str | Path = "companion") -> CompanionConfig:
    return load_config(find_config(str(path)), CompanionConfig)


def pan_scan_params(cfg: PanScanConfig) -> PanScanParams:
    """The pan-scan parameters with the closed-loop response (eq. 5) from the model or as given."""
    from quadlink.analysis.yaw_identification import identify_first_order

    gain, phase = cfg.gain, cfg.phase_rad
    if cfg.response == "model" and cfg.omega_rad_s > 0:
        r = identify_first_order(cfg.yaw_time_constant_s, cfg.omega_rad_s, cfg.yaw_delay_s)
        gain, phase = r.gain, r.phase_rad
    return PanScanParams(cfg.enabled, cfg.amplitude_rad_s, cfg.omega_rad_s, gain, phase)

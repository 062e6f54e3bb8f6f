"""The bridge's MAVLink parameters: names, defaults, bounds, persistence.

Names follow PX4 where PX4 has the same parameter (so MAVSDK's ``action.set_takeoff_altitude``,
which writes ``MIS_TAKEOFF_ALT``, and users' habits work); the bridge's own carry the ``BRG_``
prefix. All are ``MAV_PARAM_TYPE_REAL32`` (so PX4's bytewise and ArduPilot's C-cast encodings
coincide). Angles are in degrees as in PX4.
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass
from pathlib import Path

import yaml

from firmware_bridge.velocity_tracker import TrackerGains
from quadlink.errors import ConfigError

log = logging.getLogger(__name__)

DEFAULT_PARAMS_PATH = Path("~/.local/state/quadlink/bridge_params.yaml")


@dataclass(frozen=True)
class ParamSpec:
    name: str  # at most 16 characters (MAVLink param_id)
    default: float
    min: float
    max: float
    description: str


PARAM_SPECS: tuple[ParamSpec, ...] = (
    ParamSpec("MPC_XY_VEL_P", 2.0, 0.0, 10.0, "horizontal velocity P gain, (m/s^2)/(m/s)"),
    ParamSpec("MPC_XY_VEL_I", 0.6, 0.0, 10.0, "horizontal velocity I gain, (m/s^2)/m"),
    ParamSpec("MPC_XY_VEL_D", 0.05, 0.0, 2.0, "horizontal velocity D gain, s"),
    ParamSpec("MPC_Z_VEL_P", 3.0, 0.0, 15.0, "vertical velocity P gain, (m/s^2)/(m/s)"),
    ParamSpec("MPC_Z_VEL_I", 1.0, 0.0, 10.0, "vertical velocity I gain, (m/s^2)/m"),
    ParamSpec("MPC_Z_VEL_D", 0.0, 0.0, 2.0, "vertical velocity D gain, s"),
    ParamSpec("BRG_I_MAX_XY", 2.0, 0.0, 10.0, "horizontal integral clamp, m/s^2"),
    ParamSpec("BRG_I_MAX_Z", 3.0, 0.0, 10.0, "vertical integral clamp, m/s^2"),
    ParamSpec("MPC_TILTMAX_AIR", 25.0, 5.0, 60.0, "maximum tilt, deg"),
    ParamSpec("MPC_XY_VEL_MAX", 3.0, 0.1, 10.0, "maximum horizontal speed, m/s"),
    ParamSpec("MPC_Z_VEL_MAX_UP", 1.5, 0.1, 5.0, "maximum climb rate, m/s"),
    ParamSpec("MPC_Z_VEL_MAX_DN", 1.0, 0.1, 5.0, "maximum descent rate, m/s"),
    ParamSpec("MPC_YAWRAUTO_MAX", 90.0, 5.0, 360.0, "maximum yaw rate, deg/s"),
    ParamSpec("MC_YAW_P", 1.5, 0.0, 5.0, "heading hold gain, (rad/s)/rad (0: pure yaw-rate pass-through)"),
    ParamSpec("MIS_TAKEOFF_ALT", 1.0, 0.2, 10.0, "take-off height above the take-off point, m"),
    ParamSpec("MPC_TKO_SPEED", 0.5, 0.1, 3.0, "take-off climb rate, m/s"),
    ParamSpec("MPC_LAND_SPEED", 0.4, 0.1, 2.0, "landing descent rate, m/s"),
    ParamSpec("LNDMC_Z_VEL_MAX", 0.15, 0.02, 1.0, "touchdown: vertical speed below this, m/s"),
    ParamSpec("LNDMC_THR_MAX", 0.8, 0.1, 1.0, "touchdown: thrust below this fraction of hover"),
    ParamSpec("LNDMC_TIME_S", 0.5, 0.1, 5.0, "touchdown: conditions held this long, s"),
    ParamSpec("COM_OF_LOSS_T", 1.0, 0.1, 60.0, "offboard setpoint loss timeout, s"),
    ParamSpec("BRG_FS_HOVER_T", 3.0, 0.0, 60.0, "failsafe: hover this long before landing, s"),
    ParamSpec("BRG_ODOM_LOSS_T", 0.5, 0.05, 10.0, "odometry loss timeout, s"),
    ParamSpec("BRG_FS_DESC_THR", 0.9, 0.5, 1.0, "odometry-lost descent thrust, fraction of hover"),
    ParamSpec("BRG_BOARD_LOSS_T", 0.5, 0.05, 10.0, "board link loss timeout, s"),
    ParamSpec("COM_DISARM_PRFLT", 10.0, 0.0, 60.0, "auto-disarm when armed on the ground, s (0 off)"),
    ParamSpec("BRG_ATT_TAU", 1.0, 0.05, 20.0, "complementary attitude filter time constant, s"),
    ParamSpec("BRG_ODOM_QMIN", 1.0, 0.0, 100.0, "odometry quality below this is not used, % (0: accept unknown)"),
    ParamSpec("BRG_TKO_OL_SPD", 0.4, 0.1, 1.0, "take-off phase 1 (no odometry yet): climb rate, m/s"),
    ParamSpec("BRG_TKO_OL_ALT", 1.5, 0.3, 5.0, "take-off phase 1: height bound (accelerometer estimate), m"),
    ParamSpec("BRG_TKO_OL_T", 6.0, 1.0, 30.0, "take-off phase 1: time bound, s"),
    ParamSpec("BRG_TKO_THR_MRG", 0.25, 0.05, 0.6, "take-off phase 1: thrust ceiling above hover, fraction"),
    ParamSpec("BRG_TKO_RAMP_T", 1.0, 0.0, 5.0, "take-off phase 1: thrust ramp from idle, s"),
    ParamSpec("BRG_OL_LAND_SPD", 0.3, 0.1, 1.0, "landing with no odometry yet: descent rate, m/s"),
)

SPECS_BY_NAME: dict[str, ParamSpec] = {p.name: p for p in PARAM_SPECS}
assert all(len(p.name) <= 16 for p in PARAM_SPECS)


class ParamTable:
    """Values by name, in a fixed index order (PARAM_VALUE.param_index)."""

    def __init__(self, overrides: dict[str, float] | None = None) -> None:
        self.values: dict[str, float] = {p.name: p.default for p in PARAM_SPECS}
        self.dirty = False
        for name, value in (overrides or {}).items():
            if name in SPECS_BY_NAME:
                self.values[name] = self._bounded(name, float(value))
            else:
                log.warning("ignoring unknown parameter %s from the parameter file", name)

    @staticmethod
    def _bounded(name: str, value: float) -> float:
        spec = SPECS_BY_NAME[name]
        if not math.isfinite(value):
            return spec.default
        return min(max(value, spec.min), spec.max)

    def names(self) -> list[str]:
        return [p.name for p in PARAM_SPECS]

    def index_of(self, name: str) -> int:
        return self.names().index(name)

    def __getitem__(self, name: str) -> float:
        return self.values[name]

    def __len__(self) -> int:
        return len(PARAM_SPECS)

    def set(self, name: str, value: float) -> float | None:
        """Set (clamped into bounds); the stored value, or None for an unknown name."""
        if name not in SPECS_BY_NAME:
            return None
        stored = self._bounded(name, float(value))
        if stored != self.values[name]:
            self.values[name] = stored
            self.dirty = True
        return stored

    def tracker_gains(self) -> TrackerGains:
        v = self.values
        return TrackerGains(
            kp_xy_1_s=v["MPC_XY_VEL_P"], ki_xy_1_s2=v["MPC_XY_VEL_I"], kd_xy_s=v["MPC_XY_VEL_D"],
            kp_z_1_s=v["MPC_Z_VEL_P"], ki_z_1_s2=v["MPC_Z_VEL_I"], kd_z_s=v["MPC_Z_VEL_D"],
            integral_max_xy_m_s2=v["BRG_I_MAX_XY"], integral_max_z_m_s2=v["BRG_I_MAX_Z"],
            max_tilt_rad=math.radians(v["MPC_TILTMAX_AIR"]), max_speed_xy_m_s=v["MPC_XY_VEL_MAX"],
            max_climb_m_s=v["MPC_Z_VEL_MAX_UP"], max_descent_m_s=v["MPC_Z_VEL_MAX_DN"],
            max_yaw_rate_rad_s=math.radians(v["MPC_YAWRAUTO_MAX"]))


def load_param_file(path: Path) -> dict[str, float]:
    """Stored parameter values ({} when the file does not exist yet)."""
    path = path.expanduser()
    if not path.is_file():
        return {}
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8")) or {}
    except (OSError, yaml.YAMLError) as exc:
        raise ConfigError(f"{path}: cannot read the parameter file: {str(exc).splitlines()[0]}") from exc
    if not isinstance(data, dict) or not all(isinstance(v, (int, float)) for v in data.values()):
        raise ConfigError(f"{path}: expected a mapping of parameter name -> number")
    return {str(k): float(v) for k, v in data.items()}


def save_param_file(path: Path, values: dict[str, float]) -> None:
    """Write atomically (temporary file + rename), so a crash never leaves half a file."""
    path = path.expanduser()
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(yaml.safe_dump({k: float(v) for k, v in values.items()}, sort_keys=False), encoding="utf-8")
    os.replace(tmp, path)

"""The bridge's MAVLink parameters: names, defaults, bounds, persistence.

Names follow PX4 where PX4 has the same parameter (so MAVSDK's ``action.set_takeoff_altitude``,
which writes ``MIS_TAKEOFF_ALT``, and users' habits work); the bridge's own carry the ``BRG_``
prefix. This table is the one place their bounds live: the shared parameter service
(:mod:`quadlink.mavlink.param_service`) refuses a PARAM_SET outside them. All are
``MAV_PARAM_TYPE_REAL32`` (so PX4's bytewise and ArduPilot's C-cast encodings coincide; a PARAM_SET
of another type is refused). Angles are in degrees as in PX4.
"""

from __future__ import annotations

import logging
import math
import os
from pathlib import Path

import yaml

from firmware_bridge.geometric_tracker import GEOMETRIC_PARAM_SPECS, GeometricGains, geometric_gains_from_params
from firmware_bridge.velocity_tracker import TrackerGains
from quadlink.errors import ConfigError
from quadlink.mavlink import param_service as quadlink_params
from quadlink.mavlink.param_service import ParamSpec

log = logging.getLogger(__name__)

DEFAULT_PARAMS_PATH = Path("~/.local/state/quadlink/bridge_params.yaml")


PARAM_SPECS: tuple[ParamSpec, ...] = (
    ParamSpec("MPC_XY_VEL_P", 2.0, 0.0, 10.0, "(m/s^2)/(m/s)", "horizontal velocity P gain"),
    ParamSpec("MPC_XY_VEL_I", 0.6, 0.0, 10.0, "(m/s^2)/m", "horizontal velocity I gain"),
    ParamSpec("MPC_XY_VEL_D", 0.05, 0.0, 2.0, "s", "horizontal velocity D gain"),
    ParamSpec("MPC_Z_VEL_P", 3.0, 0.0, 15.0, "(m/s^2)/(m/s)", "vertical velocity P gain"),
    ParamSpec("MPC_Z_VEL_I", 1.0, 0.0, 10.0, "(m/s^2)/m", "vertical velocity I gain"),
    ParamSpec("MPC_Z_VEL_D", 0.0, 0.0, 2.0, "s", "vertical velocity D gain"),
    ParamSpec("BRG_I_MAX_XY", 2.0, 0.0, 10.0, "m/s^2", "horizontal integral clamp"),
    ParamSpec("BRG_I_MAX_Z", 3.0, 0.0, 10.0, "m/s^2", "vertical integral clamp"),
    ParamSpec("MPC_TILTMAX_AIR", 25.0, 5.0, 60.0, "deg", "maximum tilt"),
    ParamSpec("MPC_XY_VEL_MAX", 3.0, 0.1, 10.0, "m/s", "maximum horizontal speed"),
    ParamSpec("MPC_Z_VEL_MAX_UP", 1.5, 0.1, 5.0, "m/s", "maximum climb rate"),
    ParamSpec("MPC_Z_VEL_MAX_DN", 1.0, 0.1, 5.0, "m/s", "maximum descent rate"),
    ParamSpec("MPC_YAWRAUTO_MAX", 90.0, 5.0, 360.0, "deg/s", "maximum yaw rate"),
    ParamSpec("MC_YAW_P", 1.5, 0.0, 5.0, "(rad/s)/rad", "heading hold gain (0: pure yaw-rate pass-through)"),
    ParamSpec("MIS_TAKEOFF_ALT", 1.0, 0.2, 10.0, "m", "take-off height above the take-off point"),
    ParamSpec("MPC_TKO_SPEED", 0.5, 0.1, 3.0, "m/s", "take-off climb rate"),
    ParamSpec("MPC_LAND_SPEED", 0.4, 0.1, 2.0, "m/s", "landing descent rate"),
    ParamSpec("LNDMC_Z_VEL_MAX", 0.15, 0.02, 1.0, "m/s", "touchdown: vertical speed below this"),
    ParamSpec("LNDMC_THR_MAX", 0.8, 0.1, 1.0, "fraction", "touchdown: thrust below this fraction of hover"),
    ParamSpec("LNDMC_TIME_S", 0.5, 0.1, 5.0, "s", "touchdown: conditions held this long"),
    ParamSpec("COM_OF_LOSS_T", 1.0, 0.1, 60.0, "s", "offboard setpoint loss timeout"),
    ParamSpec("BRG_FS_HOVER_T", 3.0, 0.0, 60.0, "s", "failsafe: hover this long before landing"),
    ParamSpec("BRG_ODOM_LOSS_T", 0.5, 0.05, 10.0, "s", "odometry loss timeout"),
    ParamSpec("BRG_FS_DESC_THR", 0.9, 0.5, 1.0, "fraction", "odometry-lost descent thrust, fraction of hover"),
    ParamSpec("BRG_BOARD_LOSS_T", 0.5, 0.05, 10.0, "s", "board link loss timeout"),
    ParamSpec("COM_DISARM_PRFLT", 10.0, 0.0, 60.0, "s", "auto-disarm when armed on the ground (0 off)"),
    ParamSpec("BRG_ATT_TAU", 1.0, 0.05, 20.0, "s", "complementary attitude filter time constant"),
    ParamSpec("BRG_ATT_ODOM_TAU", 0.3, 0.0, 5.0, "s",
              "the attitude's tilt follows the odometry's with this time constant, the accelerometer's correction "
              "held off while it comes (0: the accelerometer only)"),
    ParamSpec("BRG_ODOM_QMIN", 1.0, 0.0, 100.0, "%", "odometry quality below this is not used (0: accept unknown)"),
    ParamSpec("BRG_TKO_OL_SPD", 0.4, 0.1, 1.0, "m/s", "take-off phase 1 (no odometry yet): climb rate"),
    ParamSpec("BRG_TKO_OL_ALT", 0.7, 0.3, 5.0, "m", "take-off phase 1: height bound (accelerometer estimate)"),
    ParamSpec("BRG_TKO_OL_T", 6.0, 1.0, 30.0, "s", "take-off phase 1: time bound"),
    ParamSpec("BRG_TKO_THR_MRG", 0.25, 0.05, 0.6, "fraction", "take-off phase 1: thrust ceiling above hover, fraction"),
    ParamSpec("BRG_TKO_RAMP_T", 1.0, 0.0, 5.0, "s", "take-off phase 1: thrust ramp from idle"),
    ParamSpec("BRG_OL_LAND_SPD", 0.5, 0.1, 1.0, "m/s", "landing without odometry: descent rate (ArduPilot LAND_SPEED)"),
    ParamSpec("BRG_BARO_REF_T", 20.0, 0.0, 600.0, "s",
              "in the air on good odometry (above 0.5 m, not landing) the baro's ground reference follows the "
              "odometry's height over this time constant: its drift leaves the floor a landing reads (0: never)"),
    ParamSpec("BRG_OL_LAND_BAND", 1.0, 0.0, 2.0, "m",
              "a landing's level descent on the barometer (the last BRG_LAND_LVL_ALT, or all of one without "
              "odometry): once the estimate reads the floor its thrust is held while the baro's climb rate says "
              "it still descends, at most this far on (the baro's drift since the take-off)"),
    ParamSpec("BRG_ODOM_VGATE", 0.3, 0.0, 5.0, "m/s",
              "odometry velocity further than this from the IMU's prediction is refused (0: off)"),
    ParamSpec("BRG_ODOM_VZGATE", 0.5, 0.0, 5.0, "m/s",
              "odometry whose vertical velocity is further than this from the barometer-fused estimate's is refused "
              "(in a take-off, and above 0.3 m on the baro; 0: off)"),
    ParamSpec("BRG_ODOM_VZBAND", 0.1, 0.0, 5.0, "m/s",
              "the vertical velocity flown is held within this of the barometer-fused estimate's (where the vertical "
              "gate has a reference; 0: off, the odometry's as it is)"),
    ParamSpec("BRG_ODOM_VGATE_K", 0.3, 0.05, 1.0, "fraction",
              "the gate's reference takes this share of an accepted odometry velocity, the rest from the IMU "
              "(1: the last accepted velocity)"),
    ParamSpec("BRG_ODOM_DGATE", 0.2, 0.0, 5.0, "m/s",
              "in the air, once the drag is learnt, an odometry velocity whose low-pass has been farther than this "
              "(horizontally) from the drag's for BRG_ODOM_DGATE_T is not used (0: off)"),
    ParamSpec("BRG_ODOM_DGATE_T", 0.2, 0.0, 5.0, "s", "how long the disagreement lasts before the drag gate acts"),
    ParamSpec("BRG_DRAG_HOLD", 1.0, 0.0, 1.0, "bool",
              "without odometry (stale, lost), hold on the drag-learnt velocity instead of the IMU's integral or "
              "flying level (0: off)"),
    ParamSpec("BRG_DRAG_K_NOM", 0.45, 0.0, 5.0, "1/s",
              "the drag coefficient held on before the flight has moved enough to learn it (the 'Drag learnt' "
              "message gives the vehicle's; PX4's EKF2_MCOEF; 0: none)"),
    ParamSpec("BRG_LAND_LVL_ALT", 0.3, 0.0, 2.0, "m",
              "LAND: below this baro height, descend level on the baro (0: off)"),
    ParamSpec("BRG_LVL_TRIM", 1.0, 0.0, 1.0, "bool",
              "fly 'level' (the level landing, the blind descent) level by the bridge's attitude estimate: the "
              "board's error, learnt in steady flight on odometry, commanded away (0: the board's own level)"),
) + GEOMETRIC_PARAM_SPECS  # BRG_TRACKER (0 PID, 1 geometric) and the geometric tracker's gains (issue 19)

SPECS_BY_NAME: dict[str, ParamSpec] = {p.name: p for p in PARAM_SPECS}


class ParamTable(quadlink_params.ParamTable):
    """The bridge's table (:data:`PARAM_SPECS`), plus the velocity tracker's gains it holds."""

    def __init__(self, overrides: dict[str, float] | None = None) -> None:
        super().__init__(PARAM_SPECS, overrides)

    def tracker_gains(self) -> TrackerGains:
        v = self.values
        return TrackerGains(
            kp_xy_1_s=v["MPC_XY_VEL_P"], ki_xy_1_s2=v["MPC_XY_VEL_I"], kd_xy_s=v["MPC_XY_VEL_D"],
            kp_z_1_s=v["MPC_Z_VEL_P"], ki_z_1_s2=v["MPC_Z_VEL_I"], kd_z_s=v["MPC_Z_VEL_D"],
            integral_max_xy_m_s2=v["BRG_I_MAX_XY"], integral_max_z_m_s2=v["BRG_I_MAX_Z"],
            max_tilt_rad=math.radians(v["MPC_TILTMAX_AIR"]), max_speed_xy_m_s=v["MPC_XY_VEL_MAX"],
            max_climb_m_s=v["MPC_Z_VEL_MAX_UP"], max_descent_m_s=v["MPC_Z_VEL_MAX_DN"],
            max_yaw_rate_rad_s=math.radians(v["MPC_YAWRAUTO_MAX"]))

    def geometric_gains(self) -> GeometricGains:
        return geometric_gains_from_params(self.values)


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

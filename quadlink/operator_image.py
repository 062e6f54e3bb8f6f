"""The operator image's metadata: the one definition the companion (producer) and the ground station
(consumer) import.

The companion sends the operator view as camera-stream records (:mod:`quadlink.camera`); each record's
``meta`` is :meth:`OperatorImageMeta.to_wire` of the frame's state. Frames: attitude is the odometry's
(roll, pitch, yaw of Q, rad, NED), velocities are in H (the heading frame, x along the heading, z down,
m/s), obstacle points in the camera frame C (m).

Decoding is strict (:meth:`OperatorImageMeta.from_wire`): a missing or unknown key, a wrong type, a
non-finite number or another ``version`` is a :class:`ProtocolError` — a renamed key on one side
fails loudly instead of the view falling back to something else.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from quadlink.errors import ProtocolError

OPERATOR_IMAGE_META_VERSION = 2   # 2: the vertical limits
MAX_OBSTACLE_POINTS = 400

Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class PanScanMeta:
    """The pan-scan state at the frame (paper 000 eqs. (6)-(8))."""

    enabled: bool                 # the oscillation is active (TELEOP with PANSCAN_EN)
    yaw_rate_rad_s: float         # psi_s', the commanded pan-scan yaw rate now
    yaw_offset_rad: float         # its integral, the swing angle now
    alpha_rad: float              # camera direction in H used for the operator command, eq. (6)
    amplitude_rad_s: float        # A of the generator
    omega_rad_s: float            # its pulsation


@dataclass(frozen=True)
class VerticalMeta:
    """The safety layer's vertical limits at the frame (companion.vertical_limits; heights above the take-off
    floor, m). None: unknown (no height estimate) or no limit (no ceiling or fence configured)."""

    height_m: float | None            # the height the limits were computed from
    floor_height_m: float | None      # the lowest height the reference descends to
    ceiling_height_m: float | None    # the highest it climbs to (room ceiling minus d_safe, or the fence)


NO_VERTICAL = VerticalMeta(None, None, None)


@dataclass(frozen=True)
class OperatorImageMeta:
    """What the ground station's view needs besides the image."""

    stamp_s: float                # the frame's stamp (autopilot time)
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    gyro_yaw_rate_rad_s: float    # Euler yaw rate from the gyro, for the view's pan-scan estimator
    obstacle_points_c_m: tuple[Vec3, ...]
    v_cmd_h_m_s: Vec3             # the reference velocity sent to the autopilot
    v_est_h_m_s: Vec3             # the odometry's velocity
    pan_scan: PanScanMeta
    mode: str                     # companion mode name, lower case (idle, takeoff, teleop, hold, land)
    vertical: VerticalMeta = NO_VERTICAL
    version: int = OPERATOR_IMAGE_META_VERSION

    def to_wire(self) -> dict[str, Any]:
        """The JSON-ready dict carried in the camera record's ``meta``."""
        ps = self.pan_scan
        return {
            "version": self.version, "stamp_s": self.stamp_s, "roll_rad": self.roll_rad,
            "pitch_rad": self.pitch_rad, "yaw_rad": self.yaw_rad, "gyro_yaw_rate_rad_s": self.gyro_yaw_rate_rad_s,
            "obstacle_points_c_m": [list(p) for p in self.obstacle_points_c_m],
            "v_cmd_h_m_s": list(self.v_cmd_h_m_s), "v_est_h_m_s": list(self.v_est_h_m_s),
            "pan_scan": {"enabled": ps.enabled, "yaw_rate_rad_s": ps.yaw_rate_rad_s,
                         "yaw_offset_rad": ps.yaw_offset_rad, "alpha_rad": ps.alpha_rad,
                         "amplitude_rad_s": ps.amplitude_rad_s, "omega_rad_s": ps.omega_rad_s},
            "mode": self.mode,
            "vertical": {"height_m": self.vertical.height_m, "floor_height_m": self.vertical.floor_height_m,
                         "ceiling_height_m": self.vertical.ceiling_height_m},
        }

    @classmethod
    def from_wire(cls, meta: Any) -> OperatorImageMeta:
        """Strict decode of :meth:`to_wire`'s dict (after JSON); :class:`ProtocolError` on any mismatch."""
        d = _exact_keys(meta, _TOP_KEYS, "operator image meta")
        version = d["version"]
        if type(version) is not int or version != OPERATOR_IMAGE_META_VERSION:
            raise ProtocolError(f"operator image meta version {version!r}, expected {OPERATOR_IMAGE_META_VERSION}")
        ps = _exact_keys(d["pan_scan"], _PAN_SCAN_KEYS, "operator image meta pan_scan")
        if type(ps["enabled"]) is not bool:
            raise ProtocolError(f"operator image meta pan_scan.enabled must be a bool, got {ps['enabled']!r}")
        points = d["obstacle_points_c_m"]
        if not isinstance(points, list) or len(points) > MAX_OBSTACLE_POINTS:
            raise ProtocolError(f"operator image meta obstacle_points_c_m: a list of at most {MAX_OBSTACLE_POINTS}")
        mode = d["mode"]
        if not isinstance(mode, str):
            raise ProtocolError(f"operator image meta mode must be a string, got {mode!r}")
        vd = _exact_keys(d["vertical"], _VERTICAL_KEYS, "operator image meta vertical")
        return cls(
            stamp_s=_real(d, "stamp_s"), roll_rad=_real(d, "roll_rad"), pitch_rad=_real(d, "pitch_rad"),
            yaw_rad=_real(d, "yaw_rad"), gyro_yaw_rate_rad_s=_real(d, "gyro_yaw_rate_rad_s"),
            obstacle_points_c_m=tuple(_vec3(p, "obstacle_points_c_m[]") for p in points),
            v_cmd_h_m_s=_vec3(d["v_cmd_h_m_s"], "v_cmd_h_m_s"), v_est_h_m_s=_vec3(d["v_est_h_m_s"], "v_est_h_m_s"),
            pan_scan=PanScanMeta(enabled=ps["enabled"], yaw_rate_rad_s=_real(ps, "yaw_rate_rad_s"),
                                 yaw_offset_rad=_real(ps, "yaw_offset_rad"), alpha_rad=_real(ps, "alpha_rad"),
                                 amplitude_rad_s=_real(ps, "amplitude_rad_s"), omega_rad_s=_real(ps, "omega_rad_s")),
            mode=mode, vertical=VerticalMeta(*(_optional(vd, k) for k in ("height_m", "floor_height_m",
                                                                           "ceiling_height_m"))),
            version=version)


_TOP_KEYS = frozenset({"version", "stamp_s", "roll_rad", "pitch_rad", "yaw_rad", "gyro_yaw_rate_rad_s",
                       "obstacle_points_c_m", "v_cmd_h_m_s", "v_est_h_m_s", "pan_scan", "mode", "vertical"})
_VERTICAL_KEYS = frozenset({"height_m", "floor_height_m", "ceiling_height_m"})
_PAN_SCAN_KEYS = frozenset({"enabled", "yaw_rate_rad_s", "yaw_offset_rad", "alpha_rad", "amplitude_rad_s",
                            "omega_rad_s"})


def _exact_keys(value: Any, keys: frozenset[str], what: str) -> dict[str, Any]:
    if not isinstance(value, dict):
        raise ProtocolError(f"{what}: expected an object, got {type(value).__name__}")
    missing, unknown = keys - value.keys(), value.keys() - keys
    if missing or unknown:
        raise ProtocolError(f"{what}: missing keys {sorted(missing)}, unknown keys {sorted(unknown)}")
    return value


def _number(value: Any, what: str) -> float:
    # bool is an int in Python: reject it where a number is meant
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ProtocolError(f"operator image meta {what}: expected a finite number, got {value!r}")
    return float(value)


def _real(d: dict[str, Any], key: str) -> float:
    return _number(d[key], key)


def _optional(d: dict[str, Any], key: str) -> float | None:
    """A finite number or null (JSON has no inf or nan: unknown and unbounded are null)."""
    return None if d[key] is None else _number(d[key], key)


def finite_or_none(value: float) -> float | None:
    """The producer's side of :func:`_optional`."""
    return float(value) if math.isfinite(value) else None


def _vec3(value: Any, what: str) -> Vec3:
    if not isinstance(value, (list, tuple)) or len(value) != 3:
        raise ProtocolError(f"operator image meta {what}: expected 3 numbers, got {value!r}")
    return (_number(value[0], what), _number(value[1], what), _number(value[2], what))

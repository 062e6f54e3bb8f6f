"""The bridge's flight modes in PX4's custom-mode numbering (:mod:`quadlink.px4_modes`, defined once there).

HEARTBEAT reports ``MAV_AUTOPILOT_PX4`` with PX4's ``custom_mode``, so QGroundControl's PX4 plugin, MAVProxy
(pymavlink's px4_map) and MAVSDK name these modes and set them by name (firmware_bridge/README.md
"Identity"). DO_SET_MODE also accepts
ArduCopter's mode numbers (what pymavlink/MAVProxy send for a generic quadrotor: ``mode LAND`` = 9,
``LOITER`` = 5, ``POSHOLD`` = 16, ``GUIDED`` = 4 -> OFFBOARD) wherever they do not collide with PX4's main
modes (PX4 wins).
"""

from __future__ import annotations

import enum
import math

from quadlink import px4_modes
from quadlink.mavlink import mavlink
from quadlink.px4_modes import Px4MainMode, Px4Mode


class FlightMode(enum.Enum):
    """Bridge modes; each value is its PX4 (main, sub) mode."""

    ALTCTL = px4_modes.ALTCTL  # hold (velocity zero), like POSCTL: no sticks here
    POSCTL = px4_modes.POSCTL
    OFFBOARD = px4_modes.OFFBOARD
    TAKEOFF = px4_modes.AUTO_TAKEOFF
    LOITER = px4_modes.AUTO_LOITER
    LAND = px4_modes.AUTO_LAND

    @property
    def custom_mode(self) -> int:
        return self.value.custom_mode

    @classmethod
    def from_px4(cls, main: int, sub: int) -> FlightMode | None:
        for mode in cls:
            if mode.value == Px4Mode(main, sub):
                return mode
        return None

    @classmethod
    def from_custom_mode(cls, custom_mode: int) -> FlightMode | None:
        decoded = px4_modes.decode_custom_mode(custom_mode)
        return cls.from_px4(decoded.main, decoded.sub)


class ArduCopterMode(enum.IntEnum):
    """ArduCopter's mode numbers (its ``control_mode``; pymavlink's mode map for a generic quadrotor)."""

    GUIDED = 4
    LOITER = 5
    LAND = px4_modes.ARDUCOPTER_LAND
    POSHOLD = 16


ARDUCOPTER_MODES: dict[int, FlightMode] = {ArduCopterMode.LAND: FlightMode.LAND,
                                           ArduCopterMode.LOITER: FlightMode.LOITER,
                                           ArduCopterMode.POSHOLD: FlightMode.POSCTL,
                                           ArduCopterMode.GUIDED: FlightMode.OFFBOARD}

HOLD_MODES = (FlightMode.ALTCTL, FlightMode.POSCTL, FlightMode.LOITER)


class TakeoffPhase(enum.Enum):
    """Take-off phases (the camera sees the floor closer than its minimum range until ~0.3-0.5 m up)."""

    OPEN_LOOP = 1  # no odometry yet: level, heading hold, climb on the accelerometer's vertical estimate
    CLOSED_LOOP = 2  # odometry: the velocity tracker finishes the climb


def int_param(value: float, default: int = 0) -> int:
    """A command parameter as an integer; NaN/inf (MAVLink's "unused") -> ``default``."""
    return int(round(value)) if math.isfinite(value) and abs(value) < 2.0**31 else default


def decode_set_mode(base_mode: float, custom_main: float, custom_sub: float) -> FlightMode | None:
    """DO_SET_MODE params -> mode: PX4's (main, sub) first, ArduCopter's numbers where unambiguous."""
    if not int_param(base_mode) & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
        return None
    main, sub = int_param(custom_main), int_param(custom_sub)
    mode = FlightMode.from_px4(main, sub)
    if mode is not None:
        return mode
    if sub == 0 and main not in (Px4MainMode.ALTCTL, Px4MainMode.POSCTL, Px4MainMode.OFFBOARD):
        return ARDUCOPTER_MODES.get(main)
    return None

"""The COMMAND_LONGs a ground client sends, built once (pure): arm, disarm, take-off, land, PX4 mode changes.

Params follow MAVLink's NaN = "unused" convention as MAVSDK sends it and :mod:`quadlink.mavlink.command_params`
reads it: the take-off's and the landing's yaw and position are NaN ("keep the heading, here"), their altitude a
number (the take-off's height above the ground, m; 0 for the landing: the ground).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from quadlink.mavlink import mavlink
from quadlink.px4_modes import Px4Mode

Params7 = tuple[float, float, float, float, float, float, float]


@dataclass(frozen=True)
class CommandLong:
    """One COMMAND_LONG: the MAV_CMD and its seven params."""

    command: int
    params: Params7

    @property
    def name(self) -> str:
        return command_name(self.command)


def command_name(command: int) -> str:
    """``MAV_CMD_NAV_TAKEOFF`` for 22 (the number for a command the dialect does not know)."""
    entry = mavlink.enums["MAV_CMD"].get(command)
    return entry.name if entry is not None else f"MAV_CMD {command}"


def arm_command() -> CommandLong:
    return CommandLong(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, (1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))


def disarm_command() -> CommandLong:
    return CommandLong(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))


def takeoff_command(altitude_m: float) -> CommandLong:
    """MAV_CMD_NAV_TAKEOFF to ``altitude_m`` above the ground (the companion's and the bridge's reading)."""
    return CommandLong(mavlink.MAV_CMD_NAV_TAKEOFF, (0.0, 0.0, 0.0, math.nan, math.nan, math.nan, float(altitude_m)))


def land_command() -> CommandLong:
    return CommandLong(mavlink.MAV_CMD_NAV_LAND, (0.0, 0.0, 0.0, math.nan, math.nan, math.nan, 0.0))


def set_px4_mode_command(mode: Px4Mode) -> CommandLong:
    """MAV_CMD_DO_SET_MODE as PX4 reads it: the custom-mode flag, then the main and the sub mode."""
    return CommandLong(mavlink.MAV_CMD_DO_SET_MODE, (float(mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED),
                                                     float(mode.main), float(mode.sub), 0.0, 0.0, 0.0, 0.0))

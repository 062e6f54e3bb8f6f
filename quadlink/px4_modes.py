"""PX4's custom-mode encoding (px4_custom_mode.h): the one definition every part of the stack imports.

``custom_mode = main_mode << 16 | sub_mode << 24``. The bridge reports its modes this way in HEARTBEAT,
and the companion, the ground station and the demo's report decode them with the same functions.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass


class Px4MainMode(enum.IntEnum):
    """PX4_CUSTOM_MAIN_MODE_* (bits 16..23 of custom_mode)."""

    MANUAL = 1
    ALTCTL = 2
    POSCTL = 3
    AUTO = 4
    ACRO = 5
    OFFBOARD = 6
    STABILIZED = 7
    RATTITUDE = 8


class Px4AutoSubMode(enum.IntEnum):
    """PX4_CUSTOM_SUB_MODE_AUTO_* (bits 24..31 of custom_mode, with main mode AUTO)."""

    READY = 1
    TAKEOFF = 2
    LOITER = 3
    MISSION = 4
    RTL = 5
    LAND = 6


@dataclass(frozen=True)
class Px4Mode:
    """A PX4 (main, sub) mode pair; ``sub`` is 0 unless ``main`` is AUTO."""

    main: int
    sub: int = 0

    @property
    def custom_mode(self) -> int:
        return encode_custom_mode(self.main, self.sub)


def encode_custom_mode(main: int, sub: int = 0) -> int:
    """(main, sub) -> HEARTBEAT.custom_mode."""
    if not (0 <= main <= 0xFF and 0 <= sub <= 0xFF):
        raise ValueError(f"PX4 mode out of range: main {main}, sub {sub}")
    return (int(main) << 16) | (int(sub) << 24)


def decode_custom_mode(custom_mode: int) -> Px4Mode:
    """HEARTBEAT.custom_mode -> (main, sub)."""
    return Px4Mode((int(custom_mode) >> 16) & 0xFF, (int(custom_mode) >> 24) & 0xFF)


OFFBOARD = Px4Mode(Px4MainMode.OFFBOARD)
POSCTL = Px4Mode(Px4MainMode.POSCTL)
ALTCTL = Px4Mode(Px4MainMode.ALTCTL)
AUTO_TAKEOFF = Px4Mode(Px4MainMode.AUTO, Px4AutoSubMode.TAKEOFF)
AUTO_LOITER = Px4Mode(Px4MainMode.AUTO, Px4AutoSubMode.LOITER)
AUTO_LAND = Px4Mode(Px4MainMode.AUTO, Px4AutoSubMode.LAND)
ARDUCOPTER_LAND = 9   # ArduCopter's LAND: what MAVProxy's ``mode land`` sends for a generic quadrotor (the bridge
                      # takes ArduCopter's numbers where they are unambiguous, firmware_bridge.modes)


def is_land_mode(main: int, sub: int) -> bool:
    """A mode request (DO_SET_MODE's or SET_MODE's main and sub mode) that lands the vehicle: PX4's AUTO.LAND (what
    QGroundControl's Land action asks a PX4 vehicle for) or ArduCopter's LAND."""
    return (main, sub) in ((AUTO_LAND.main, AUTO_LAND.sub), (ARDUCOPTER_LAND, 0))

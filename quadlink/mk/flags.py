"""The MK board's state words (the one definition the bridge and the SITL's firmware import).

``BoardStatus.flight_state`` is a :class:`BoardFlightState`, ``BoardStatus.error_flags`` a set of
:class:`BoardError` bits (uint16 on the wire), the status ``flags`` byte :class:`StatusFlag`, the
``AttitudeSetpoint`` flags byte :class:`SetpointFlag`. ``PROTOCOL.md`` beside this file has the layouts.
"""

from __future__ import annotations

import enum


class BoardFlightState(enum.IntEnum):
    """``BoardStatus.flight_state`` (uint8)."""

    LANDED = 0
    FLYING = 1
    FAILSAFE_DESCEND = 2  # setpoint timeout in flight: level, slow descent, motor cut on the ground


class BoardError(enum.IntFlag):
    """``BoardStatus.error_flags`` bits (uint16)."""

    NONE = 0
    SETPOINT_TIMEOUT = 0x0001  # no valid 's' frame within the firmware's timeout (failsafe trigger)
    BATTERY_LOW = 0x0002  # battery below the warning threshold
    IMU_SATURATED = 0x0004  # an IMU channel hit 0 or 1023 since the last status
    RX_FRAMES_DROPPED = 0x0008  # the board dropped received frames (checksum/garbage) since the last status


class StatusFlag(enum.IntFlag):
    """``BoardStatus`` flags byte."""

    NONE = 0
    ARMED = 0x01
    FAILSAFE = 0x02


class SetpointFlag(enum.IntFlag):
    """``AttitudeSetpoint`` flags byte (bits 1-7 zero)."""

    NONE = 0
    ARMED = 0x01

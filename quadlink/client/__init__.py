"""``quadlink.client``: the one ground client of the stack, a small MAVSDK-like API over pymavlink (issue 28).

* :mod:`quadlink.client.client`: :func:`connect` and :class:`GroundClient` (heartbeat, commands with their
  acks, parameters, setpoints, MANUAL_CONTROL with COMMAND_STAMP, TIMESYNC answers, signing);
* :mod:`quadlink.client.commands`: the COMMAND_LONGs (arm, disarm, take-off, land, PX4 modes), pure;
* :mod:`quadlink.client.setpoints`: SET_POSITION_TARGET_LOCAL_NED as :class:`PositionTarget` and MAVSDK's
  setpoints (velocity body / NED, position-velocity-acceleration), pure.

Used by the ground station (``teleop/link.py``), the campaign's offboard client, ``quadlink paper003`` and
``quadlink trajectory``. Guide: ``docs/reference/client.md``.
"""

from quadlink.client.client import (
    DEFAULT_TIMEOUT_S,
    HEARTBEAT_PERIOD_S,
    RESULT_NAMES,
    CommandRejected,
    GroundClient,
    Signing,
    VehicleState,
    connect,
)
from quadlink.client.commands import (
    CommandLong,
    arm_command,
    command_name,
    disarm_command,
    land_command,
    set_px4_mode_command,
    takeoff_command,
)
from quadlink.client.setpoints import PositionTarget, position_velocity_accel_ned, velocity_body, velocity_ned

__all__ = [
    "DEFAULT_TIMEOUT_S", "HEARTBEAT_PERIOD_S", "RESULT_NAMES", "CommandLong", "CommandRejected", "GroundClient",
    "PositionTarget", "Signing", "VehicleState", "arm_command", "command_name", "connect", "disarm_command",
    "land_command", "position_velocity_accel_ned", "set_px4_mode_command", "takeoff_command", "velocity_body",
    "velocity_ned",
]

"""SET_POSITION_TARGET_LOCAL_NED / SET_ATTITUDE_TARGET type-mask groups and frame families, defined once.

A set bit in a POSITION_TARGET_TYPEMASK means "ignore this field". The groups below are built from the
dialect's enum entries; the bridge, the companion's arbiter and the ground client (:mod:`quadlink.client`) import
them.
"""

from __future__ import annotations

from dataclasses import dataclass

from quadlink.mavlink import mavlink

TM_POSITION = (mavlink.POSITION_TARGET_TYPEMASK_X_IGNORE | mavlink.POSITION_TARGET_TYPEMASK_Y_IGNORE
               | mavlink.POSITION_TARGET_TYPEMASK_Z_IGNORE)
TM_VELOCITY = (mavlink.POSITION_TARGET_TYPEMASK_VX_IGNORE | mavlink.POSITION_TARGET_TYPEMASK_VY_IGNORE
               | mavlink.POSITION_TARGET_TYPEMASK_VZ_IGNORE)
TM_ACCEL = (mavlink.POSITION_TARGET_TYPEMASK_AX_IGNORE | mavlink.POSITION_TARGET_TYPEMASK_AY_IGNORE
            | mavlink.POSITION_TARGET_TYPEMASK_AZ_IGNORE)
TM_FORCE = mavlink.POSITION_TARGET_TYPEMASK_FORCE_SET
TM_YAW = mavlink.POSITION_TARGET_TYPEMASK_YAW_IGNORE
TM_YAW_RATE = mavlink.POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE

#: velocity + yaw rate (MAVSDK's set_velocity_body, the companion's own setpoint): 1479
TM_VELOCITY_YAW_RATE = TM_POSITION | TM_ACCEL | TM_YAW
#: velocity + acceleration + yaw rate: the acceleration bits of 1479 cleared
TM_VELOCITY_ACCEL_YAW_RATE = TM_POSITION | TM_YAW
#: velocity + yaw (MAVSDK's set_velocity_ned): 2503
TM_VELOCITY_YAW = TM_POSITION | TM_ACCEL | TM_YAW_RATE
#: position + velocity + acceleration + yaw (a PX4 trajectory setpoint, ``quadlink trajectory``): 2048
TM_POSITION_VELOCITY_ACCEL_YAW = TM_YAW_RATE

#: frames whose velocity is rotated by yaw only (PX4's and ArduPilot's reading for velocity setpoints)
BODY_FRAMES = (mavlink.MAV_FRAME_BODY_NED, mavlink.MAV_FRAME_BODY_OFFSET_NED, mavlink.MAV_FRAME_BODY_FRD)
LOCAL_FRAMES = (mavlink.MAV_FRAME_LOCAL_NED, mavlink.MAV_FRAME_LOCAL_OFFSET_NED, mavlink.MAV_FRAME_LOCAL_FRD)

ATM_YAW_RATE = mavlink.ATTITUDE_TARGET_TYPEMASK_BODY_YAW_RATE_IGNORE
ATM_THRUST = mavlink.ATTITUDE_TARGET_TYPEMASK_THROTTLE_IGNORE
ATM_ATTITUDE = mavlink.ATTITUDE_TARGET_TYPEMASK_ATTITUDE_IGNORE


class PartialTypeMask(ValueError):
    """A field group (position, velocity, acceleration) used on some axes only: PX4 flies none of these."""


@dataclass(frozen=True)
class MaskGroups:
    """Which field groups a POSITION_TARGET_TYPEMASK uses (a group is used when all its ignore bits are clear)."""

    position: bool
    velocity: bool
    acceleration: bool
    force: bool      # the acceleration fields are a force (no one here flies it)
    yaw: bool
    yaw_rate: bool


def mask_groups(type_mask: int) -> MaskGroups:
    """The groups ``type_mask`` uses; :class:`PartialTypeMask` if a three-axis group is used on some axes only.
    The one reading of the rule for the bridge's tracker and the companion's arbiter."""
    tm = int(type_mask)
    used = {}
    for name, bits in (("position", TM_POSITION), ("velocity", TM_VELOCITY), ("acceleration", TM_ACCEL)):
        if tm & bits not in (0, bits):
            raise PartialTypeMask(f"type_mask {tm}: {name} must be used on all three axes or none")
        used[name] = tm & bits == 0
    return MaskGroups(used["position"], used["velocity"], used["acceleration"], bool(tm & TM_FORCE),
                      not tm & TM_YAW, not tm & TM_YAW_RATE)

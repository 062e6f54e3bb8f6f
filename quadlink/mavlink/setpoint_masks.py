"""SET_POSITION_TARGET_LOCAL_NED / SET_ATTITUDE_TARGET type-mask groups and frame families, defined once.

A set bit in a POSITION_TARGET_TYPEMASK means "ignore this field". The groups below are built from the
dialect's enum entries; the bridge, the companion's arbiter and the trajectory tools import them.
"""

from __future__ import annotations

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

#: frames whose velocity is rotated by yaw only (PX4's and ArduPilot's reading for velocity setpoints)
BODY_FRAMES = (mavlink.MAV_FRAME_BODY_NED, mavlink.MAV_FRAME_BODY_OFFSET_NED, mavlink.MAV_FRAME_BODY_FRD)
LOCAL_FRAMES = (mavlink.MAV_FRAME_LOCAL_NED, mavlink.MAV_FRAME_LOCAL_OFFSET_NED, mavlink.MAV_FRAME_LOCAL_FRD)

ATM_YAW_RATE = mavlink.ATTITUDE_TARGET_TYPEMASK_BODY_YAW_RATE_IGNORE
ATM_THRUST = mavlink.ATTITUDE_TARGET_TYPEMASK_THROTTLE_IGNORE
ATM_ATTITUDE = mavlink.ATTITUDE_TARGET_TYPEMASK_ATTITUDE_IGNORE

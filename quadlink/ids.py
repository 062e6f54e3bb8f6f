"""Who is who on the stack's MAVLink links, and the truth stream's sensor ids: defined once (issue 28).

The vehicle is system 1: the bridge (the autopilot, MAV_COMP_ID_AUTOPILOT1) and the companion
(MAV_COMP_ID_ONBOARD_COMPUTER, 191). The stack's own ground clients (the haptic station, the campaign's scripts,
the experiment CLIs) speak as system 255, MAV_COMP_ID_MISSIONPLANNER (190), as QGroundControl and MAVProxy do. The
SITL's truth stream is system 250 (never read by the flight code) and carries two DISTANCE_SENSOR ids.
"""

from __future__ import annotations

from quadlink.mavlink import mavlink

VEHICLE_SYSTEM_ID = 1
AUTOPILOT_COMPONENT_ID = mavlink.MAV_COMP_ID_AUTOPILOT1              # 1: the bridge
COMPANION_COMPONENT_ID = mavlink.MAV_COMP_ID_ONBOARD_COMPUTER       # 191: the companion daemon
GROUND_SYSTEM_ID = 255                                              # a ground station's system id
GROUND_COMPONENT_ID = mavlink.MAV_COMP_ID_MISSIONPLANNER            # 190: the stack's ground clients

TRUTH_SYSTEM_ID = 250
TRUTH_COMPONENT_ID = 1
TRUTH_SENSOR_ANY_SURFACE = 0    # DISTANCE_SENSOR id: centre of mass to the nearest surface of any kind
TRUTH_SENSOR_NON_FLOOR = 1      # ... to the nearest wall or object (neither floor nor ceiling)

"""Which MAVLink messages go where (pure): the companion's routing decision, like mavlink-router's on a
companion computer.

* From the autopilot: everything goes on to the ground station except what is addressed to this
  component; the companion also consumes the few kinds it needs (IMU, state, acks, TIMESYNC).
* From a ground station: a message for the autopilot's system (or broadcast) goes to the autopilot,
  except MANUAL_CONTROL (the operator's command to the companion, consumed here) and what is addressed to
  this component (COMMAND_LONG, PARAM_* for compid 191) and motion commands (setpoints, SET_MODE: the
  companion arbitrates all motion, issue 14). Broadcast parameter requests are answered by both. TIMESYNC
  and COMMAND_STAMP end at the companion: it is the clock the ground station's commands are aged against
  (companion.command_age).
"""

from __future__ import annotations

from dataclasses import dataclass

AUTOPILOT_CONSUMED = frozenset({"HIGHRES_IMU", "HEARTBEAT", "EXTENDED_SYS_STATE", "ALTITUDE", "COMMAND_ACK",
                                "TIMESYNC"})
BROADCAST_PARAM_KINDS = frozenset({"PARAM_REQUEST_LIST", "PARAM_REQUEST_READ", "PARAM_SET"})
# Motion commands from a ground station: the companion is the one arbiter of motion (companion.arbiter),
# so they are consumed here and never reach the autopilot raw; so are mode changes (the companion answers
# them for the autopilot while it is in control: see companion.gcs_commands).
MOTION_KINDS = frozenset({"SET_POSITION_TARGET_LOCAL_NED", "SET_POSITION_TARGET_GLOBAL_INT", "SET_ATTITUDE_TARGET",
                          "SET_MODE"})
# the command clock with a ground station is the companion's (issue 18): its TIMESYNC and command stamps end here
GCS_CONSUMED = frozenset({"TIMESYNC", "COMMAND_STAMP"})


@dataclass(frozen=True)
class RouteDecision:
    """``consume``: the companion handles the message; ``forward``: it goes on to the other endpoint."""

    consume: bool
    forward: bool


def route_from_autopilot(kind: str, target_component: int | None, compid: int) -> RouteDecision:
    """A message from the autopilot with ``target_component`` (None: the message has no target)."""
    to_me = target_component == compid
    consume = kind in AUTOPILOT_CONSUMED and (kind != "COMMAND_ACK" or to_me or target_component == 0)
    return RouteDecision(consume=consume, forward=not to_me)


def route_from_gcs(kind: str, target_system: int | None, target_component: int | None, sysid: int,
                   compid: int) -> RouteDecision:
    """A message from a ground station (MANUAL_CONTROL's ``target`` is passed as ``target_system``)."""
    if kind == "MANUAL_CONTROL":
        return RouteDecision(consume=target_system in (0, sysid), forward=False)
    if kind in GCS_CONSUMED:
        return RouteDecision(consume=target_system in (None, 0, sysid) and target_component in (None, 0, compid),
                             forward=False)
    if target_system not in (None, 0, sysid):
        return RouteDecision(consume=False, forward=False)  # another system: nothing behind us has it
    if target_component == compid or kind in MOTION_KINDS:
        return RouteDecision(consume=True, forward=False)
    broadcast_param = target_component in (None, 0) and kind in BROADCAST_PARAM_KINDS
    return RouteDecision(consume=broadcast_param, forward=True)

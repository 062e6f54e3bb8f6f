"""The autopilot's messages the companion takes in, by type (pure: the clock is injected, replies returned).

* HEARTBEAT of an autopilot (:func:`is_autopilot_heartbeat`) -> the vehicle's state
  (:class:`companion.vehicle_state.VehicleState`); the daemon also takes the vehicle's system id from it;
* EXTENDED_SYS_STATE -> the vehicle's landed state;
* ALTITUDE -> the autopilot's barometer-fused height (its ``altitude_relative``) and its barometer's own altitude
  (``altitude_monotonic``, taken less its value on the ground), the higher of which the ceiling limit takes when it
  is higher than the odometry's (:func:`companion.vertical_limits.vertical_limits`);
* COMMAND_ACK -> the acked command queue (:mod:`companion.commands`); a command refused or never acknowledged
  goes back to the mode machine (:meth:`companion.modes.ModeMachine.on_request_failed`);
* TIMESYNC -> the offset to the autopilot's clock (:class:`companion.timesync.TimeSync`); its requests are
  answered (:class:`companion.outbound.ToAutopilot`).

:meth:`AutopilotInput.poll_commands` is the other half of the acked commands: those due (re)sent, those that
timed out back to the mode machine.

HIGHRES_IMU takes the IMU-clocked path (:mod:`companion.imu_clock`), which the daemon feeds. Which messages the
companion consumes, and which go on to the ground stations, is :func:`companion.router.route_from_autopilot`'s
decision.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

from companion.commands import CommandQueue
from companion.modes import ModeMachine
from companion.outbound import Output, ToAutopilot
from companion.timesync import TimeSync
from companion.vehicle_state import VehicleState
from quadlink.mavlink import mavlink

log = logging.getLogger("companion.daemon")


def is_autopilot_heartbeat(msg: Any) -> bool:
    """A HEARTBEAT from an autopilot, not from a ground station or another companion on the link."""
    return bool(msg.autopilot != mavlink.MAV_AUTOPILOT_INVALID and msg.type != mavlink.MAV_TYPE_GCS)


class AutopilotInput:
    """``vehicle``, ``commands``, ``modes``, ``timesync``: the state the autopilot's messages change; ``clock``:
    monotonic seconds (the command acks' and the TIMESYNC's time)."""

    def __init__(self, vehicle: VehicleState, commands: CommandQueue, modes: ModeMachine, timesync: TimeSync,
                 clock: Callable[[], float]) -> None:
        self.vehicle, self.commands, self.modes, self.timesync = vehicle, commands, modes, timesync
        self._clock = clock

    def on_message(self, msg: Any) -> list[Output]:
        """A message from the autopilot the companion consumes (not HIGHRES_IMU): what to send, in order."""
        kind = msg.get_type()
        out: list[Output] = []
        if kind == "HEARTBEAT":
            if is_autopilot_heartbeat(msg):
                self.vehicle.on_heartbeat(msg.base_mode, msg.custom_mode, self._clock())
        elif kind == "EXTENDED_SYS_STATE":
            self.vehicle.landed_state = msg.landed_state
        elif kind == "ALTITUDE":
            self.vehicle.on_altitude(msg.altitude_relative, self._clock(), msg.altitude_monotonic)
        elif kind == "COMMAND_ACK":
            done, failed = self.commands.on_ack(msg.command, msg.result, self._clock())
            if done is not None:
                log.info("autopilot accepted %s", done.name)
            for req, why in failed:
                out += self.modes.on_request_failed(req, self._clock(), why)
        elif kind == "TIMESYNC":
            reply = self.timesync.on_message(msg, self._clock())   # TIMESYNC with the autopilot
            if reply is not None:
                out.append(ToAutopilot(reply))
        return out

    def poll_commands(self, now_s: float, sysid: int, ap_compid: int) -> list[Output]:
        """The acked commands at ``now_s``: the failures' consequences (the mode machine's), then the COMMAND_LONGs
        due, (re)sent to ``ap_compid`` of ``sysid``."""
        send, failed = self.commands.poll(now_s)
        out: list[Output] = []
        for req, why in failed:
            out += self.modes.on_request_failed(req, now_s, why)
        for command, confirmation in send:
            out.append(ToAutopilot(mavlink.MAVLink_command_long_message(sysid, ap_compid, command.command,
                                                                        confirmation, *command.params)))
        return out

"""The ground stations' messages to the companion, by type, to the services that own them (pure: the clock is
injected, what is to be sent is returned).

The endpoint is hostile (issue 16): a sender not on the allowlist is refused (:mod:`companion.security`) before
anything else. Then:

* HEARTBEAT keeps the ground-station link alive for the motion arbiter (:mod:`companion.arbiter`);
* MANUAL_CONTROL: only a fresh command (:mod:`companion.command_clock`) reaches the arbiter and keeps the mode
  machine's link alive;
* SET_POSITION_TARGET_LOCAL_NED, mode changes for the autopilot (SET_MODE, MAV_CMD_DO_SET_MODE) and COMMAND_LONG /
  COMMAND_INT for compid 191: :mod:`companion.gcs_commands`; the other motion commands are refused;
* TIMESYNC and COMMAND_STAMP: the command clock; PARAM_* for compid 191: :class:`companion.params.ParamService`.

What goes on to the autopilot is :func:`companion.router.route_from_gcs`'s decision (and a mode change the
companion does not answer); the daemon forwards it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from companion.arbiter import Arbiter, Pose
from companion.command_clock import GcsCommandClock
from companion.gcs_commands import GcsCommands
from companion.modes import ModeMachine
from companion.outbound import GcsReply, Output
from companion.params import ParamService
from companion.router import route_from_gcs
from companion.security import GcsSecurity
from companion.stats import Stats
from quadlink.mavlink import mavlink
from quadlink.px4_modes import decode_custom_mode


@dataclass(frozen=True)
class GcsHandled:
    """What a ground station's message does: ``outputs`` to send, in order; ``forward``: it goes on to the
    autopilot as it came."""

    outputs: list[Output]
    forward: bool


class GcsInput:
    """The services a ground station's message goes to; ``compid``: the companion's component id; ``clock``:
    monotonic seconds (the arbiter's, the mode machine's and the command clock's time)."""

    def __init__(self, security: GcsSecurity, command_clock: GcsCommandClock, gcs_commands: GcsCommands,
                 params: ParamService, arbiter: Arbiter, modes: ModeMachine, stats: Stats, compid: int,
                 clock: Callable[[], float]) -> None:
        self.security, self.command_clock, self.gcs_commands = security, command_clock, gcs_commands
        self.params, self.arbiter, self.modes, self.stats = params, arbiter, modes, stats
        self.compid = compid
        self._clock = clock

    def on_message(self, msg: Any, sysid: int, ap_compid: int, pose: Callable[[], Pose]) -> GcsHandled:
        """``msg`` from a ground station, the vehicle being system ``sysid`` with its autopilot ``ap_compid``;
        ``pose``: the vehicle's pose now (for a setpoint)."""
        kind = msg.get_type()
        if not self.security.permits(msg):
            self.stats.refused_senders += 1
            return GcsHandled(list(self.security.refuse_sender(msg)), forward=False)
        target_system = msg.target if kind == "MANUAL_CONTROL" else getattr(msg, "target_system", None)
        out: list[Output] = []
        if kind == "HEARTBEAT":
            self.arbiter.on_heartbeat(self._clock())
        elif kind == "COMMAND_LONG" and msg.command == mavlink.MAV_CMD_DO_SET_MODE and \
                target_system in (0, sysid) and msg.target_component in (0, ap_compid):
            handled, out = self.gcs_commands.on_set_mode(msg, msg.param1, msg.param2, msg.param3)
            if handled:
                return GcsHandled(out, forward=False)
        elif kind in ("COMMAND_LONG", "COMMAND_INT") and msg.command == mavlink.MAV_CMD_NAV_LAND and \
                target_system in (0, sysid) and msg.target_component in (0, ap_compid):
            handled, out = self.gcs_commands.on_autopilot_land(msg)
            if handled:
                return GcsHandled(out, forward=False)
        route = route_from_gcs(kind, target_system, getattr(msg, "target_component", None), sysid, self.compid)
        forward = route.forward
        if route.consume:
            forward = self._consume(kind, msg, pose, out) or forward
        return GcsHandled(out, forward)

    def _consume(self, kind: str, msg: Any, pose: Callable[[], Pose], out: list[Output]) -> bool:
        """A message the companion handles: its outputs appended to ``out``; does it go on to the autopilot?"""
        if kind == "MANUAL_CONTROL":
            self._on_manual_control(msg)
        elif kind == "SET_POSITION_TARGET_LOCAL_NED":
            out += self.gcs_commands.on_setpoint(msg, pose())
        elif kind in ("SET_POSITION_TARGET_GLOBAL_INT", "SET_ATTITUDE_TARGET"):
            out += self.gcs_commands.refuse_motion(f"{kind} not supported: use SET_POSITION_TARGET_LOCAL_NED velocity")
        elif kind == "SET_MODE":
            mode = decode_custom_mode(msg.custom_mode)
            handled, replies = self.gcs_commands.on_set_mode(msg, msg.base_mode, mode.main, mode.sub, ack=False)
            out += replies
            return not handled   # not ours to answer: the autopilot's mode
        elif kind == "TIMESYNC":
            reply = self.command_clock.on_timesync(msg, self._clock())
            if reply is not None:
                out.append(GcsReply(reply))
        elif kind == "COMMAND_STAMP":
            self.command_clock.on_stamp(msg, self._clock())
        elif kind == "COMMAND_LONG":
            out += self.gcs_commands.on_command_long(msg)
        elif kind == "COMMAND_INT":
            out += self.gcs_commands.on_command_int(msg)
        else:
            out += self.params.on_message(msg)
        return False

    def _on_manual_control(self, msg: Any) -> None:
        """Only a fresh command moves the vehicle (companion.command_age) or keeps the link alive.

        The link's liveness counts from the *arrival* of the newest accepted command (counting from its send
        time would leave ``gcs_timeout_s`` minus the one-way delay of slack: at 300 ms one way the vehicle
        flapped between TELEOP and HOLD on every loss burst); the operator input itself is zeroed once that
        command is older than the age (the daemon asks :meth:`companion.command_age.CommandAgeFilter.fresh`)."""
        now = self._clock()
        age = self.command_clock.on_command(msg, now)
        self.stats.manual_controls += 1
        if not age.accepted:
            return
        self.arbiter.on_manual_control(now, msg.x, msg.y, msg.z)
        self.modes.on_manual_control(now)

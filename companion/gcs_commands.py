"""The ground stations' commands to the companion, and the mode changes it answers for the autopilot.

* COMMAND_LONG and COMMAND_INT for compid 191 (:meth:`GcsCommands.on_command_long`, ``on_command_int``):
  ``arm``, ``disarm``, ``takeoff`` and ``land`` go to the mode machine (a takeoff without camera frames is
  refused: perception is not running), MAV_CMD_DO_SET_PARAMETER to the parameter service; everything else
  is UNSUPPORTED. A ``land`` over an object (:mod:`companion.landing_spot`) is DENIED, and so is a LAND sent to
  the autopilot while the companion flies (:meth:`GcsCommands.on_autopilot_land`); one over ground the camera
  has not seen is ACCEPTED and moves to seen ground first (:mod:`companion.modes`). Params are read through
  :mod:`quadlink.mavlink.command_params` (NaN = unused; a required param NaN, infinite or out of range:
  DENIED). Every command is acked.
* Setpoints (:meth:`GcsCommands.on_setpoint`): SET_POSITION_TARGET_LOCAL_NED to the motion arbiter, which
  refuses what it cannot fly; a refusal is told by a STATUSTEXT once per distinct reason (a script streams
  at 20 Hz), as are the motion commands the companion does not take (:meth:`GcsCommands.refuse_motion`).
* Mode changes for the autopilot (:meth:`GcsCommands.on_set_mode`, from MAV_CMD_DO_SET_MODE or SET_MODE):
  OFFBOARD engages a script, a hold-like mode (POSCTL, ALTCTL, AUTO_LOITER) disengages it (the motion
  arbiter, :mod:`companion.arbiter`); a landing mode (AUTO.LAND: QGroundControl's Land; ArduCopter's LAND:
  MAVProxy's ``mode land``) is checked as a LAND is. While the companion flies the vehicle it answers them as the
  autopilot would (its forwarded heartbeat reports the arbiter's mode); other modes (LAND, RTL, ...) and
  every mode change while it is not in control go on to the autopilot.
* The mode the ground stations see (:meth:`GcsCommands.mode_heartbeat`): while the companion is in control
  the autopilot's heartbeat is forwarded with the arbiter's mode (OFFBOARD while a script is engaged,
  POSCTL while the operator flies, else AUTO_LOITER).

Pure: the clock and the vehicle's state are injected, the replies returned (:mod:`companion.outbound`) for
the daemon to send in order.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

from companion.arbiter import Arbiter, Pose, Setpoint
from companion.modes import ModeMachine, SpotRefusal, StatusText, VehicleStatus
from companion.outbound import AutopilotAck, GcsReply, Output
from companion.params import ParamService
from quadlink.mavlink import mavlink
from quadlink.mavlink.command_params import COMMAND_PARAMS, CommandParamError, read_params
from quadlink.px4_modes import AUTO_LOITER, OFFBOARD, POSCTL, Px4MainMode, is_land_mode

GCS_COMMAND_NAMES = {mavlink.MAV_CMD_NAV_TAKEOFF: "takeoff", mavlink.MAV_CMD_NAV_LAND: "land"}


def command_ack(msg: Any, command: int, result: int) -> GcsReply:
    """COMMAND_ACK ``result`` for ``command`` to the sender of ``msg``, from the companion."""
    return GcsReply(mavlink.MAVLink_command_ack_message(command, result, 0, 0, msg.get_srcSystem(),
                                                        msg.get_srcComponent()))


class GcsCommands:
    """``modes``, ``arbiter``, ``params``: the state the commands change; ``clock``: monotonic seconds (the
    mode machine's and the arbiter's time); ``vehicle_status``: the autopilot's state now; ``camera_fresh``:
    whether camera frames arrive (a takeoff needs perception)."""

    def __init__(self, modes: ModeMachine, arbiter: Arbiter, params: ParamService, clock: Callable[[], float],
                 vehicle_status: Callable[[], VehicleStatus], camera_fresh: Callable[[], bool],
                 land_refusal: Callable[[], SpotRefusal | None] = lambda: None) -> None:
        self.modes, self.arbiter, self.params = modes, arbiter, params
        self._clock = clock
        self._vehicle_status = vehicle_status
        self._camera_fresh = camera_fresh
        self._land_refusal = land_refusal
        self._last_refusal = ""

    def on_command_long(self, msg: Any) -> list[Output]:
        """A COMMAND_LONG addressed to the companion: what it does, then its ack."""
        return self._command(msg, (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6,
                                   msg.param7))

    def on_command_int(self, msg: Any) -> list[Output]:
        """A COMMAND_INT addressed to the companion: the same commands (none of them is positional: x, y are
        plain params 5 and 6 here), the same ack. MAVLink: every command gets a COMMAND_ACK."""
        return self._command(msg, (msg.param1, msg.param2, msg.param3, msg.param4, float(msg.x), float(msg.y),
                                   msg.z))

    def _command(self, msg: Any, raw: tuple[float, ...]) -> list[Output]:
        cmd = msg.command
        result = mavlink.MAV_RESULT_UNSUPPORTED
        try:   # MAVLink's NaN = "unused" per command; a required param NaN/inf/out of range: DENIED
            p = read_params(cmd, raw) if cmd in COMMAND_PARAMS else (math.nan,) * 7
        except CommandParamError as exc:
            return [StatusText(mavlink.MAV_SEVERITY_WARNING, f"companion: {exc}"),
                    command_ack(msg, cmd, mavlink.MAV_RESULT_DENIED)]
        out: list[Output] = []
        name = GCS_COMMAND_NAMES.get(cmd)
        if cmd == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
            name = "arm" if p[0] == 1.0 else "disarm"
        if name == "takeoff" and not self._camera_fresh():
            out.append(StatusText(mavlink.MAV_SEVERITY_WARNING,
                                  "companion: takeoff refused: no camera frames (perception not running)"))
            result = mavlink.MAV_RESULT_TEMPORARILY_REJECTED
        elif name is not None:
            refusal = self._land_refusal() if name == "land" else None
            ok, actions = self.modes.request(name, self._clock(), self._vehicle_status(), refusal)
            out += actions
            result = mavlink.MAV_RESULT_ACCEPTED if ok else \
                mavlink.MAV_RESULT_DENIED if refusal is not None else mavlink.MAV_RESULT_TEMPORARILY_REJECTED
        elif cmd == mavlink.MAV_CMD_DO_SET_PARAMETER:
            changed, replies = self.params.set_by_index(int(p[0]), p[1])   # read_params: p[0] a finite whole number
            out += replies
            result = mavlink.MAV_RESULT_ACCEPTED if changed else mavlink.MAV_RESULT_DENIED
        return [*out, command_ack(msg, cmd, result)]

    def on_autopilot_land(self, msg: Any) -> tuple[bool, list[Output]]:
        """A LAND for the autopilot (MAV_CMD_NAV_LAND, as MAVSDK's ``action.land()`` sends it) while the companion
        flies the vehicle: if the spot below is no place to land, answered as the autopilot (handled, outputs):
        refused over an object, accepted over unseen ground (the companion moves to seen ground, then asks the
        autopilot to land); else it goes on to the autopilot, which lands (and the mode machine follows it)."""
        return self._land_as_autopilot(msg, msg.command, ack=True)

    def _land_as_autopilot(self, msg: Any, command: int, ack: bool) -> tuple[bool, list[Output]]:
        """A landing asked of the autopilot (``command``: NAV_LAND or DO_SET_MODE; ``ack``: answer it) while the
        companion flies the vehicle: handled here only if the spot below is no place to land (see
        :meth:`on_autopilot_land`)."""
        if not self.modes.in_control:
            return False, []
        refusal = self._land_refusal()
        if refusal is None:
            return False, []
        ok, actions = self.modes.request("land", self._clock(), self._vehicle_status(), refusal)
        out: list[Output] = list(actions)
        if ack:
            result = mavlink.MAV_RESULT_ACCEPTED if ok else mavlink.MAV_RESULT_DENIED
            out.append(AutopilotAck(mavlink.MAVLink_command_ack_message(
                command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent())))
        return True, out

    def refuse_motion(self, text: str) -> list[Output]:
        """A refused motion command: a STATUSTEXT if ``text`` is not the reason last told."""
        if text == self._last_refusal:
            return []
        self._last_refusal = text
        return [StatusText(mavlink.MAV_SEVERITY_WARNING, f"companion: {text}")]

    def on_setpoint(self, msg: Any, pose: Pose) -> list[Output]:
        """A SET_POSITION_TARGET_LOCAL_NED for the arbiter, the vehicle at ``pose``: its refusal, if any."""
        sp = Setpoint(msg.coordinate_frame, msg.type_mask, (msg.x, msg.y, msg.z), (msg.vx, msg.vy, msg.vz), msg.yaw,
                      msg.yaw_rate, (msg.afx, msg.afy, msg.afz))
        refusal = self.arbiter.on_setpoint(self._clock(), sp, pose)
        if refusal is not None:
            return self.refuse_motion(refusal.text)
        self._last_refusal = ""
        return []

    def on_set_mode(self, msg: Any, base_mode: float, main: float, sub: float,
                    ack: bool = True) -> tuple[bool, list[Output]]:
        """A mode change for the autopilot (``base_mode`` and the PX4 main/sub mode, as floats from a command's
        params): handled here (else it goes on to the autopilot)?, and what to send (the arbiter's events; the
        ack as the autopilot when ``ack`` and handled: SET_MODE has none)."""
        # a NaN or inf param (MAVSDK sends NaN for unused ones) goes on to the autopilot, which refuses it
        if not all(map(math.isfinite, (base_mode, main, sub))) or \
                not (int(base_mode) & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED):
            return False, []
        main_i, sub_i = int(main), int(sub)
        if is_land_mode(main_i, sub_i):   # QGroundControl's Land, MAVProxy's "mode land": a LAND like any other
            return self._land_as_autopilot(msg, mavlink.MAV_CMD_DO_SET_MODE, ack)
        offboard = main_i == Px4MainMode.OFFBOARD
        hold = main_i in (Px4MainMode.POSCTL, Px4MainMode.ALTCTL) or \
            (main_i == AUTO_LOITER.main and sub_i == AUTO_LOITER.sub)
        if not (offboard or hold):
            return False, []
        accepted = self.arbiter.on_set_mode(self._clock(), offboard)
        out: list[Output] = [StatusText(mavlink.MAV_SEVERITY_INFO, f"companion: {text}")
                             for text in self.arbiter.take_events()]
        if accepted:
            out += self.modes.end_commanded_clearing(self._clock())
        if not self.modes.in_control:
            return False, out   # the autopilot flies its own mode: it answers
        if ack:
            result = mavlink.MAV_RESULT_ACCEPTED if accepted else mavlink.MAV_RESULT_DENIED
            out.append(AutopilotAck(mavlink.MAVLink_command_ack_message(
                mavlink.MAV_CMD_DO_SET_MODE, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent())))
        return True, out


    def reported_mode(self) -> int:
        """The PX4 custom mode the ground station sees while the companion flies the vehicle: OFFBOARD while a
        script is engaged (MAVSDK's offboard plugin checks it), POSCTL while the operator flies, else hold."""
        now = self._clock()
        if self.arbiter.offboard_engaged:
            return OFFBOARD.custom_mode
        return (POSCTL if self.arbiter.operator_alive(now) else AUTO_LOITER).custom_mode

    def mode_heartbeat(self, msg: Any) -> Any:
        """The autopilot's HEARTBEAT ``msg`` with :meth:`reported_mode` (and the custom-mode flag)."""
        base_mode = msg.base_mode | mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        return mavlink.MAVLink_heartbeat_message(msg.type, msg.autopilot, base_mode, self.reported_mode(),
                                                 msg.system_status, msg.mavlink_version)

"""How each COMMAND_LONG's seven params are read: MAVLink's NaN = "unused" convention, per command (pure).

MAVLink (and PX4, whose reading this table follows) lets a sender put NaN in a command param it does not
use: MAVSDK fills every param it has no value for with NaN. So a NaN is never a number to act on: in an
*optional* param it means "use the default" (a stated value, or the handler's own choice: the current
heading, the configured take-off altitude), and a command whose *required* param is NaN is refused
(issue 16: ``int(round(NaN))`` ended the companion's loop; ``NaN >= 0.5`` read as "disarm"). Infinity is
never "unused": in any param the command reads it is refused. Params a command does not read (reserved)
are ignored whatever they hold.

One table for every component that handles or sends commands (the companion and the bridge); the
companion's fuzz tests also use it to tell an intended NaN in an outgoing COMMAND_LONG from a bug.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from quadlink.errors import ProtocolError
from quadlink.mavlink import mavlink

N_PARAMS = 7


class CommandParamError(ProtocolError):
    """A command param that cannot be acted on (missing, non-finite, not an integer, out of range)."""


@dataclass(frozen=True)
class ParamRule:
    """How one param is read. ``required``: NaN refused. ``default``: what an optional NaN reads as
    (None: it stays NaN, the handler picks its own value). ``integer``: the value must be a whole number;
    ``choices``: it must be one of these; ``lo``/``hi``: inclusive bounds."""

    required: bool = False
    default: float | None = 0.0
    integer: bool = False
    choices: frozenset[float] | None = None
    lo: float = -math.inf
    hi: float = math.inf

    def read(self, value: float, where: str) -> float:
        value = float(value)
        if math.isnan(value):
            if self.required:
                raise CommandParamError(f"{where} is required (NaN means unused)")
            return math.nan if self.default is None else self.default
        if not math.isfinite(value):
            raise CommandParamError(f"{where} is not finite")
        if self.integer and not value.is_integer():
            raise CommandParamError(f"{where} {value:g} is not an integer")
        if self.choices is not None and value not in self.choices:
            raise CommandParamError(f"{where} {value:g} is not one of {sorted(self.choices)}")
        if not self.lo <= value <= self.hi:
            raise CommandParamError(f"{where} {value:g} outside {self.lo:g}..{self.hi:g}")
        return value


RESERVED = None  # a param the command does not read
OPTIONAL = ParamRule()
KEEP = ParamRule(default=None)  # optional; NaN left for the handler ("current heading", "configured height")

#: command id -> rules of params 1..7 (RESERVED: not read). Commands not listed are not executed by any
#: quadlink component (answered UNSUPPORTED) and their params are never read.
COMMAND_PARAMS: dict[int, tuple[ParamRule | None, ...]] = {
    # param1: 1 arm, 0 disarm (exactly); param2: 21196 forces (the handler compares it), NaN = not forced
    mavlink.MAV_CMD_COMPONENT_ARM_DISARM: (
        ParamRule(required=True, choices=frozenset({0.0, 1.0})), OPTIONAL, RESERVED, RESERVED, RESERVED, RESERVED,
        RESERVED),
    # base mode, custom main mode, custom sub mode
    mavlink.MAV_CMD_DO_SET_MODE: (
        ParamRule(required=True, integer=True, lo=0, hi=255), ParamRule(integer=True, lo=0, hi=255),
        ParamRule(integer=True, lo=0, hi=255), RESERVED, RESERVED, RESERVED, RESERVED),
    # pitch, -, -, yaw (NaN: keep the heading), latitude, longitude, altitude (NaN: the configured one)
    mavlink.MAV_CMD_NAV_TAKEOFF: (OPTIONAL, RESERVED, RESERVED, KEEP, KEEP, KEEP, KEEP),
    # abort altitude, land mode, -, yaw, latitude, longitude, altitude: all "here, as configured"
    mavlink.MAV_CMD_NAV_LAND: (OPTIONAL, OPTIONAL, RESERVED, KEEP, KEEP, KEEP, KEEP),
    mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH: (RESERVED,) * N_PARAMS,
    # parameter index (the component's param_index), new value
    mavlink.MAV_CMD_DO_SET_PARAMETER: (
        ParamRule(required=True, integer=True, lo=0, hi=65535), ParamRule(required=True), RESERVED, RESERVED,
        RESERVED, RESERVED, RESERVED),
    # message id, interval in us (-1 off, 0 default), ..., param7 response target
    mavlink.MAV_CMD_SET_MESSAGE_INTERVAL: (
        ParamRule(required=True, integer=True, lo=0, hi=2**24 - 1), ParamRule(required=True), RESERVED, RESERVED,
        RESERVED, RESERVED, OPTIONAL),
    mavlink.MAV_CMD_REQUEST_MESSAGE: (
        ParamRule(required=True, integer=True, lo=0, hi=2**24 - 1), OPTIONAL, OPTIONAL, OPTIONAL, OPTIONAL,
        OPTIONAL, OPTIONAL),
    mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES: (ParamRule(default=1.0), RESERVED, RESERVED, RESERVED,
                                                      RESERVED, RESERVED, RESERVED),
}


def command_name(command: int) -> str:
    entry = mavlink.enums["MAV_CMD"].get(int(command))
    return entry.name if entry is not None else str(command)


def read_params(command: int, params: Sequence[float]) -> tuple[float, ...]:
    """The seven params of ``command`` as its handler may use them: an optional NaN replaced by its default,
    reserved params read as NaN (never used). Raises :class:`CommandParamError` with the reason; a command
    not in :data:`COMMAND_PARAMS` raises it too (nothing here executes it)."""
    rules = COMMAND_PARAMS.get(int(command))
    if rules is None:
        raise CommandParamError(f"{command_name(command)} is not supported")
    if len(params) != N_PARAMS:
        raise ValueError(f"a command has {N_PARAMS} params, got {len(params)}")
    name = command_name(command)
    return tuple(math.nan if rule is None else rule.read(value, f"{name} param{i + 1}")
                 for i, (rule, value) in enumerate(zip(rules, params, strict=True)))


def nan_means_unused(command: int, index: int) -> bool:
    """Whether a NaN in param ``index`` (0-based) of ``command`` is MAVLink's "unused" (so sending one is
    intended): the param is optional or reserved, or the command is not in the table."""
    rules = COMMAND_PARAMS.get(int(command))
    if rules is None:
        return False
    rule = rules[index]
    return rule is None or not rule.required

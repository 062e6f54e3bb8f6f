"""One MAVLink parameter service for every component (bridge now, companion later): pure, time as argument.

A component declares its parameters once, as a tuple of :class:`ParamSpec` (name, MAV_PARAM_TYPE,
default, bounds, unit, description), keeps the values in a :class:`ParamTable`, and hands each
PARAM_REQUEST_LIST / PARAM_REQUEST_READ / PARAM_SET to :meth:`ParamService.handle`, which returns a
:class:`ParamReply`: what to send back to the requester, what to send to every endpoint, the STATUSTEXT
events and the name of a changed parameter (so the owner re-applies its gains). No sockets, no clock.

Wire encoding of ``param_value`` (a float32 on the wire): REAL32 parameters carry the value; integer
parameters are packed *bytewise* as PX4 does (``MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE``): the
integer's little-endian bytes fill the float's four bytes (zero-padded for 8/16-bit types), so an INT32 7
is the float whose bits are 0x00000007, not 7.0.

PARAM_SET is validated at the boundary (issue 16): the ``param_type`` must be the parameter's type, the
decoded value finite and inside ``[min, max]``; a refused set is answered with PARAM_VALUE holding the
*unchanged* value (to the requester, so its retry logic ends) and a STATUSTEXT warning.
"""

from __future__ import annotations

import logging
import math
import struct
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from quadlink.mavlink import mavlink

log = logging.getLogger(__name__)

PARAM_ID_MAX_CHARS = 16  # PARAM_VALUE.param_id is char[16]

# MAV_PARAM_TYPE -> (struct format of its bytes, inclusive integer range); REAL32 is the float itself
_INT_FORMATS: dict[int, tuple[str, int, int]] = {
    mavlink.MAV_PARAM_TYPE_UINT8: ("<B", 0, 0xFF),
    mavlink.MAV_PARAM_TYPE_INT8: ("<b", -0x80, 0x7F),
    mavlink.MAV_PARAM_TYPE_UINT16: ("<H", 0, 0xFFFF),
    mavlink.MAV_PARAM_TYPE_INT16: ("<h", -0x8000, 0x7FFF),
    mavlink.MAV_PARAM_TYPE_UINT32: ("<I", 0, 0xFFFFFFFF),
    mavlink.MAV_PARAM_TYPE_INT32: ("<i", -0x80000000, 0x7FFFFFFF),
}
SUPPORTED_TYPES = frozenset(_INT_FORMATS) | {mavlink.MAV_PARAM_TYPE_REAL32}


class ParamError(ValueError):
    """A parameter table that cannot be (a bad spec, an unknown name in code)."""


@dataclass(frozen=True)
class ParamSpec:
    """One parameter: its wire name and type, default, inclusive bounds, unit and meaning."""

    name: str  # at most 16 characters (MAVLink param_id)
    default: float
    min: float
    max: float
    unit: str
    description: str
    param_type: int = mavlink.MAV_PARAM_TYPE_REAL32

    def __post_init__(self) -> None:
        if not self.name or len(self.name) > PARAM_ID_MAX_CHARS or not self.name.isascii():
            raise ParamError(f"parameter name {self.name!r}: 1..16 ASCII characters")
        if self.param_type not in SUPPORTED_TYPES:
            raise ParamError(f"{self.name}: unsupported MAV_PARAM_TYPE {self.param_type}")
        if not all(math.isfinite(v) for v in (self.default, self.min, self.max)):
            raise ParamError(f"{self.name}: default and bounds must be finite")
        if not self.min <= self.default <= self.max:
            raise ParamError(f"{self.name}: default {self.default} outside [{self.min}, {self.max}]")
        if self.is_integer and not all(float(v).is_integer() for v in (self.default, self.min, self.max)):
            raise ParamError(f"{self.name}: an integer parameter needs integer default and bounds")

    @property
    def is_integer(self) -> bool:
        return self.param_type in _INT_FORMATS

    def check(self, value: float) -> str | None:
        """Why ``value`` can not be stored, or None."""
        if not math.isfinite(value):
            return "not finite"
        if not self.min <= value <= self.max:
            return f"outside {self.min:g}..{self.max:g}"
        if self.is_integer and not float(value).is_integer():
            return "not an integer"
        return None


def encode_param_value(value: float, param_type: int) -> float:
    """The float32 carried in PARAM_VALUE/PARAM_SET.param_value for ``value`` (bytewise for integers)."""
    if param_type == mavlink.MAV_PARAM_TYPE_REAL32:
        return float(value)
    fmt, _, _ = _INT_FORMATS[param_type]
    raw = struct.pack(fmt, int(value)).ljust(4, b"\x00")
    return float(struct.unpack("<f", raw)[0])


def decode_param_value(wire_value: float, param_type: int) -> float:
    """``param_value`` as sent -> the parameter's value (inverse of :func:`encode_param_value`).

    Raises ``ValueError`` for a type this service does not know. Integers are read from the float's
    bytes, so an INT32 NaN pattern is simply an integer (and any float32 decodes to some integer).
    """
    if param_type == mavlink.MAV_PARAM_TYPE_REAL32:
        return float(wire_value)
    if param_type not in _INT_FORMATS:
        raise ValueError(f"unsupported MAV_PARAM_TYPE {param_type}")
    fmt, _, _ = _INT_FORMATS[param_type]
    raw = struct.pack("<f", wire_value)
    return float(struct.unpack(fmt, raw[: struct.calcsize(fmt)])[0])


class ParamTable:
    """A component's parameter values by name, in the spec's fixed order (PARAM_VALUE.param_index)."""

    def __init__(self, specs: Sequence[ParamSpec], overrides: Mapping[str, float] | None = None,
                 source: str = "the parameter file") -> None:
        names = [s.name for s in specs]
        if len(set(names)) != len(names):
            raise ParamError("duplicate parameter names")
        self.specs: tuple[ParamSpec, ...] = tuple(specs)
        self.by_name: dict[str, ParamSpec] = {s.name: s for s in self.specs}
        self._index = {name: i for i, name in enumerate(names)}
        self.values: dict[str, float] = {s.name: float(s.default) for s in self.specs}
        self.dirty = False
        for name, value in (overrides or {}).items():
            spec = self.by_name.get(name)
            if spec is None:
                log.warning("ignoring unknown parameter %s from %s", name, source)
                continue
            value = float(value)
            if not math.isfinite(value):
                log.warning("ignoring %s = %r from %s: not finite (keeping %g)", name, value, source, spec.default)
                continue
            bounded = min(max(value, spec.min), spec.max)
            if spec.is_integer:
                bounded = float(round(bounded))
            if bounded != value:
                log.warning("%s = %r from %s: bounded to %g", name, value, source, bounded)
            self.values[name] = bounded

    def names(self) -> list[str]:
        return [s.name for s in self.specs]

    def index_of(self, name: str) -> int:
        return self._index[name]

    def __getitem__(self, name: str) -> float:
        return self.values[name]

    def __contains__(self, name: object) -> bool:
        return name in self.values

    def __len__(self) -> int:
        return len(self.specs)

    def set(self, name: str, value: float) -> float | None:
        """Store ``value`` if valid; the stored value, or None for an unknown name or a refused value."""
        spec = self.by_name.get(name)
        if spec is None or spec.check(float(value)) is not None:
            return None
        if float(value) != self.values[name]:
            self.values[name] = float(value)
            self.dirty = True
        return self.values[name]


@dataclass
class ParamReply:
    """What one request produced: ``to_sender`` goes back on the request's link, ``to_all`` everywhere."""

    to_sender: list[Any] = field(default_factory=list)
    to_all: list[Any] = field(default_factory=list)
    events: list[tuple[int, str]] = field(default_factory=list)  # (MAV_SEVERITY, STATUSTEXT text)
    changed: str | None = None
    refused: bool = False


def param_name(raw: Any) -> str:
    """PARAM_*.param_id as a str (pymavlink gives str or bytes, NUL-padded to 16)."""
    if isinstance(raw, bytes):
        raw = raw.decode("ascii", "replace")
    return str(raw).split("\x00", 1)[0]


class ParamService:
    """PARAM_REQUEST_LIST / PARAM_REQUEST_READ / PARAM_SET for one component (``sysid``, ``compid``).

    ``mav`` is the component's pymavlink encoder (``mavlink.MAVLink(None, sysid, compid)``), used only
    to build messages. Requests addressed to another system or component are ignored (0 = broadcast).
    """

    def __init__(self, table: ParamTable, mav: Any, sysid: int, compid: int) -> None:
        self.table = table
        self.mav = mav
        self.sysid, self.compid = sysid, compid
        self.refused_sets = 0

    def _for_us(self, msg: Any) -> bool:
        return getattr(msg, "target_system", 0) in (0, self.sysid) and \
            getattr(msg, "target_component", 0) in (0, self.compid)

    def param_value(self, name: str) -> Any:
        spec = self.table.by_name[name]
        return self.mav.param_value_encode(name.encode("ascii"),
                                           encode_param_value(self.table[name], spec.param_type),
                                           spec.param_type, len(self.table), self.table.index_of(name))

    def all_values(self) -> Iterable[Any]:
        return (self.param_value(name) for name in self.table.names())

    def handle(self, now_s: float, msg: Any) -> ParamReply:
        """One PARAM_* message (others: an empty reply). ``now_s`` is for the log only."""
        mtype = msg.get_type()
        reply = ParamReply()
        if mtype not in ("PARAM_REQUEST_LIST", "PARAM_REQUEST_READ", "PARAM_SET") or not self._for_us(msg):
            return reply
        if mtype == "PARAM_REQUEST_LIST":
            reply.to_sender.extend(self.all_values())
        elif mtype == "PARAM_REQUEST_READ":
            name = self._requested_name(msg)
            if name is not None:
                reply.to_sender.append(self.param_value(name))
        else:
            self._set(now_s, msg, reply)
        return reply

    def _requested_name(self, msg: Any) -> str | None:
        names = self.table.names()
        if msg.param_index >= 0:
            return names[msg.param_index] if msg.param_index < len(names) else None
        name = param_name(msg.param_id)
        return name if name in self.table else None

    def _set(self, now_s: float, msg: Any, reply: ParamReply) -> None:
        name = param_name(msg.param_id)
        spec = self.table.by_name.get(name)
        if spec is None:
            reply.events.append((mavlink.MAV_SEVERITY_WARNING, f"Unknown parameter {name}"))
            return
        why: str | None = None
        value = math.nan
        if msg.param_type != spec.param_type:
            why = f"type {msg.param_type}, expected {spec.param_type}"
        else:
            value = decode_param_value(float(msg.param_value), spec.param_type)
            why = spec.check(value)
        if why is not None:
            self.refused_sets += 1
            log.warning("t=%.3f PARAM_SET %s refused: %s (value stays %g)", now_s, name, why, self.table[name])
            reply.refused = True
            reply.events.append((mavlink.MAV_SEVERITY_WARNING, f"{name} refused: {why}"))
            reply.to_sender.append(self.param_value(name))  # the unchanged value ends the sender's retries
            return
        stored = self.table.set(name, value)
        assert stored is not None  # checked above
        log.info("parameter %s = %g", name, stored)
        reply.changed = name
        reply.to_all.append(self.param_value(name))  # every GCS sees the change

"""MikroKopter's standard serial commands, with their MK meaning (version, debug data, labels, 3D data,
ExternControl, motor test). Conventions: :mod:`quadlink.mk.messages`; wire layout: ``PROTOCOL.md``.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from typing import ClassVar

from quadlink.mk.fields import (
    DECIDEG_RAD,
    INT8,
    INT16,
    UINT8,
    finite,
    ints,
    need,
    sat_int,
    scaled,
)

# --------------------------------------------------------------------------------------------------------------
# Standard MK messages
# --------------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class VersionRequest:
    """``'v'``: ask a board for its version. Empty payload. Answer: :class:`Version`."""

    COMMAND: ClassVar[str] = "v"

    def pack(self) -> bytes:
        return b""

    @classmethod
    def unpack(cls, payload: bytes) -> VersionRequest:
        return cls()


@dataclass(frozen=True)
class Version:
    """``'V'``: a board's firmware version (MK ``str_VersionInfo``), 10 bytes, ``<10B``.

    ==================  =========  ======================================================
    field               type       meaning
    ==================  =========  ======================================================
    sw_major            uint8      firmware major version
    sw_minor            uint8      firmware minor version (84 -> "0.84")
    proto_major         uint8      serial protocol major version (11 for FC 0.84)
    proto_minor         uint8      serial protocol minor version
    sw_patch            uint8      patch level, shown as a letter ('a' + sw_patch)
    hardware_error      uint8[5]   hardware error flag bytes (0 = ok)
    ==================  =========  ======================================================
    """

    COMMAND: ClassVar[str] = "V"
    STRUCT: ClassVar[struct.Struct] = struct.Struct("<10B")

    sw_major: int
    sw_minor: int
    proto_major: int
    proto_minor: int
    sw_patch: int = 0
    hardware_error: tuple[int, int, int, int, int] = (0, 0, 0, 0, 0)

    @property
    def version_str(self) -> str:
        """MK's spelling, e.g. ``"0.84a"`` (patch 0 -> 'a')."""
        patch = chr(ord("a") + self.sw_patch) if 0 <= self.sw_patch < 26 else f"+{self.sw_patch}"
        return f"{self.sw_major}.{self.sw_minor:02d}{patch}"

    def pack(self) -> bytes:
        head = ints(
            (self.sw_major, self.sw_minor, self.proto_major, self.proto_minor, self.sw_patch), 5, UINT8, "version"
        )
        return self.STRUCT.pack(*head, *ints(self.hardware_error, 5, UINT8, "hardware_error"))

    @classmethod
    def unpack(cls, payload: bytes) -> Version:
        need(payload, cls.STRUCT.size, cls)
        v = cls.STRUCT.unpack_from(payload)
        return cls(v[0], v[1], v[2], v[3], v[4], tuple(v[5:10]))  # type: ignore[arg-type]


@dataclass(frozen=True)
class DebugRequest:
    """``'d'``: start (or refresh) the :class:`DebugData` stream. ``<B``: interval_10ms uint8, 10 ms units, 0 stops.

    MK stops streaming after a timeout (about 4 s on FlightCtrl) unless the request is repeated; the stack's
    firmware keeps that behaviour, so a reader re-sends it every second or two.
    """

    COMMAND: ClassVar[str] = "d"
    STRUCT: ClassVar[struct.Struct] = struct.Struct("<B")

    interval_10ms: int

    def pack(self) -> bytes:
        return self.STRUCT.pack(sat_int(finite(self.interval_10ms, "interval_10ms"), UINT8))

    @classmethod
    def unpack(cls, payload: bytes) -> DebugRequest:
        need(payload, cls.STRUCT.size, cls)
        return cls(payload[0])


@dataclass(frozen=True)
class DebugData:
    """``'D'``: MK debug values (``str_DebugOut``), 66 bytes, ``<2B32h``.

    status: uint8[2] (status bytes); analog: int16[32] (the debug channels; their names come from
    ``'a'``/:class:`DebugLabel`; units are whatever each channel's firmware variable holds).
    """

    COMMAND: ClassVar[str] = "D"
    STRUCT: ClassVar[struct.Struct] = struct.Struct("<2B32h")
    N_ANALOG: ClassVar[int] = 32

    status: tuple[int, int] = (0, 0)
    analog: tuple[int, ...] = (0,) * 32

    def pack(self) -> bytes:
        return self.STRUCT.pack(*ints(self.status, 2, UINT8, "status"), *ints(self.analog, 32, INT16, "analog"))

    @classmethod
    def unpack(cls, payload: bytes) -> DebugData:
        need(payload, cls.STRUCT.size, cls)
        v = cls.STRUCT.unpack_from(payload)
        return cls((v[0], v[1]), tuple(v[2:]))


@dataclass(frozen=True)
class DebugLabelRequest:
    """``'a'``: ask for the name of debug channel ``index``. ``<B``: index uint8 (0..31)."""

    COMMAND: ClassVar[str] = "a"
    STRUCT: ClassVar[struct.Struct] = struct.Struct("<B")

    index: int

    def pack(self) -> bytes:
        return self.STRUCT.pack(sat_int(finite(self.index, "index"), UINT8))

    @classmethod
    def unpack(cls, payload: bytes) -> DebugLabelRequest:
        need(payload, cls.STRUCT.size, cls)
        return cls(payload[0])


@dataclass(frozen=True)
class DebugLabel:
    """``'A'``: name of one debug channel, 17 bytes, ``<B16s``: index uint8; label char[16] (ASCII, space/NUL padded).

    ``pack`` truncates a longer label to 16 bytes and replaces non-ASCII characters by '?'.
    """

    COMMAND: ClassVar[str] = "A"
    STRUCT: ClassVar[struct.Struct] = struct.Struct("<B16s")

    index: int
    label: str

    def pack(self) -> bytes:
        text = self.label.encode("ascii", errors="replace")[:16].ljust(16, b" ")
        return self.STRUCT.pack(sat_int(finite(self.index, "index"), UINT8), text)

    @classmethod
    def unpack(cls, payload: bytes) -> DebugLabel:
        need(payload, cls.STRUCT.size, cls)
        index, raw = cls.STRUCT.unpack_from(payload)
        return cls(index, raw.decode("ascii", errors="replace").rstrip(" \x00"))


@dataclass(frozen=True)
class Data3DRequest:
    """``'c'``: start (or refresh) the :class:`Data3D` stream. ``<B``: interval_10ms uint8, 10 ms units, 0 stops."""

    COMMAND: ClassVar[str] = "c"
    STRUCT: ClassVar[struct.Struct] = struct.Struct("<B")

    interval_10ms: int

    def pack(self) -> bytes:
        return self.STRUCT.pack(sat_int(finite(self.interval_10ms, "interval_10ms"), UINT8))

    @classmethod
    def unpack(cls, payload: bytes) -> Data3DRequest:
        need(payload, cls.STRUCT.size, cls)
        return cls(payload[0])


@dataclass(frozen=True)
class Data3D:
    """``'C'``: attitude as the board sees it (MK ``Data3D_t``), 14 bytes, ``<3h3B5B``.

    ==============  ==========  ========================================================================
    wire field      type        unit / mapping
    ==============  ==========  ========================================================================
    angle[0] nick   int16       0.1 deg -> ``pitch_rad`` (MK "Nick" is pitch)
    angle[1] roll   int16       0.1 deg -> ``roll_rad``
    angle[2] yaw    int16       0.1 deg -> ``yaw_rad`` (heading; MK sends 0..3599, decoded to [-pi, pi))
    centroid        uint8[3]    raw (MK: centre-of-gravity estimate), kept as is
    reserve         uint8[5]    reserved, sent as zeros, kept as received
    ==============  ==========  ========================================================================

    Angles follow the stack's convention (body FRD, ZYX Euler of ``quadlink.frames.R_from_euler``: positive
    pitch = nose up, positive roll = right side down, yaw clockwise from north seen from above); the stack's
    firmware sends them that way. The stock MK firmware's signs are not guaranteed to match.
    ``pack`` wraps ``yaw_rad`` to [-180 deg, 180 deg) and saturates roll/pitch to the int16 range (+-3276.7 deg).
    """

    COMMAND: ClassVar[str] = "C"
    STRUCT: ClassVar[struct.Struct] = struct.Struct("<3h3B5B")

    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    centroid: tuple[int, int, int] = (0, 0, 0)
    reserve: tuple[int, int, int, int, int] = (0, 0, 0, 0, 0)

    def pack(self) -> bytes:
        yaw = finite(self.yaw_rad, "yaw_rad")
        yaw_wrapped = (yaw + math.pi) % (2.0 * math.pi) - math.pi
        nick = scaled(self.pitch_rad, DECIDEG_RAD, INT16, "pitch_rad")
        roll = scaled(self.roll_rad, DECIDEG_RAD, INT16, "roll_rad")
        yaw_dd = sat_int(yaw_wrapped / DECIDEG_RAD, (-1800, 1799))
        return self.STRUCT.pack(
            nick, roll, yaw_dd, *ints(self.centroid, 3, UINT8, "centroid"), *ints(self.reserve, 5, UINT8, "reserve")
        )

    @classmethod
    def unpack(cls, payload: bytes) -> Data3D:
        need(payload, cls.STRUCT.size, cls)
        v = cls.STRUCT.unpack_from(payload)
        yaw_dd = (v[2] + 1800) % 3600 - 1800  # heading 0..3599 -> [-1800, 1800)
        return cls(
            roll_rad=v[1] * DECIDEG_RAD,
            pitch_rad=v[0] * DECIDEG_RAD,
            yaw_rad=yaw_dd * DECIDEG_RAD,
            centroid=(v[3], v[4], v[5]),
            reserve=(v[6], v[7], v[8], v[9], v[10]),
        )


@dataclass(frozen=True)
class ExternControl:
    """``'b'``: MK external control (the classic 11-byte ``ExternControl_t``), ``<2BBbbbBbBBB``.

    =================  ========  ==============================================================
    field              type      meaning (stick units as the MK firmware scales them)
    =================  ========  ==============================================================
    digital            uint8[2]  digital channels
    remote_buttons     uint8     remote buttons
    nick               int8      pitch stick
    roll               int8      roll stick
    yaw                int8      yaw stick
    gas                uint8     throttle
    height             int8      height setpoint
    free               uint8     unused
    frame              uint8     frame counter, echoed by the board in ``'B'`` (:class:`ExternControlAck`)
    config             uint8     config flags (bit0: the board uses the external values)
    =================  ========  ==============================================================

    FlightCtrl 2.10+ ignores this 11-byte form (it expects 7 bytes). The stack's own firmware does not use
    ExternControl (it takes :class:`AttitudeSetpoint`); the class exists for standard MK tools and boards.
    """

    COMMAND: ClassVar[str] = "b"
    STRUCT: ClassVar[struct.Struct] = struct.Struct("<2BBbbbBbBBB")

    digital: tuple[int, int] = (0, 0)
    remote_buttons: int = 0
    nick: int = 0
    roll: int = 0
    yaw: int = 0
    gas: int = 0
    height: int = 0
    free: int = 0
    frame: int = 0
    config: int = 0

    def pack(self) -> bytes:
        d0, d1 = ints(self.digital, 2, UINT8, "digital")
        return self.STRUCT.pack(
            d0,
            d1,
            sat_int(finite(self.remote_buttons, "remote_buttons"), UINT8),
            sat_int(finite(self.nick, "nick"), INT8),
            sat_int(finite(self.roll, "roll"), INT8),
            sat_int(finite(self.yaw, "yaw"), INT8),
            sat_int(finite(self.gas, "gas"), UINT8),
            sat_int(finite(self.height, "height"), INT8),
            sat_int(finite(self.free, "free"), UINT8),
            sat_int(finite(self.frame, "frame"), UINT8),
            sat_int(finite(self.config, "config"), UINT8),
        )

    @classmethod
    def unpack(cls, payload: bytes) -> ExternControl:
        need(payload, cls.STRUCT.size, cls)
        v = cls.STRUCT.unpack_from(payload)
        return cls((v[0], v[1]), *v[2:])


@dataclass(frozen=True)
class ExternControlAck:
    """``'B'``: the board's receipt of an :class:`ExternControl`, ``<B``: frame uint8 (the echoed frame counter)."""

    COMMAND: ClassVar[str] = "B"
    STRUCT: ClassVar[struct.Struct] = struct.Struct("<B")

    frame: int

    def pack(self) -> bytes:
        return self.STRUCT.pack(sat_int(finite(self.frame, "frame"), UINT8))

    @classmethod
    def unpack(cls, payload: bytes) -> ExternControlAck:
        need(payload, cls.STRUCT.size, cls)
        return cls(payload[0])


@dataclass(frozen=True)
class MotorTest:
    """``'t'``: motor test, ``<16B``: motor uint8[16] (0 off .. 255 full). Boards obey it only when disarmed."""

    COMMAND: ClassVar[str] = "t"
    STRUCT: ClassVar[struct.Struct] = struct.Struct("<16B")

    motor: tuple[int, ...] = (0,) * 16

    def pack(self) -> bytes:
        return self.STRUCT.pack(*ints(self.motor, 16, UINT8, "motor"))

    @classmethod
    def unpack(cls, payload: bytes) -> MotorTest:
        need(payload, cls.STRUCT.size, cls)
        return cls(tuple(cls.STRUCT.unpack_from(payload)))



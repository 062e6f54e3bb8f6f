"""Typed payloads of the MK frames the stack speaks (the one definition every side imports).

Each message is a frozen dataclass with a class attribute ``COMMAND`` (its frame letter), ``pack() -> bytes``
(the raw payload; :func:`encode_message` frames it) and ``@classmethod unpack(payload) -> message``.
All layouts are explicit little-endian :mod:`struct` formats (the AVR's byte order), stated in each docstring
as ``field: type, unit, scaling``. ``firmware_bridge/PROTOCOL.md`` documents the same on the wire.

Conventions:

* **Saturation.** ``pack`` never raises on a finite out-of-range value: scaled and bounded fields are rounded
  to the nearest LSB and clamped to their integer range (e.g. ``thrust`` 1.3 -> 65535, a roll of 400 deg ->
  327.67 deg). Rolling counters (``seq``, ``sample_counter``, ``board_time_ms``, ``imu_sample_count``) wrap
  modulo their width instead, and bit-field words are masked. A NaN or infinite float raises
  ``ProtocolError`` (there is no safe integer for it; the caller decides what a broken setpoint means).
* **Trailing bytes.** ``unpack`` needs at least the struct's size and ignores bytes beyond it: MK's base64
  decoder returns whole 3-byte groups (zero padding), and newer firmware may append fields. A shorter payload
  raises ``ProtocolError``. :func:`decode_message` turns that into ``None`` (and a debug log) so a reader loop
  just skips the frame.
* **Letters.** Standard MK commands keep their meaning (``v/V`` version, ``d/D`` debug, ``a/A`` debug labels,
  ``c/C`` 3D data, ``b/B`` ExternControl, ``t`` motor test). The stack's firmware adds ``I`` IMU sample
  (port 2, board -> companion), ``s`` attitude/thrust setpoint (port 1, companion -> board) and ``S`` board
  status (port 1, board -> companion). Every letter means one message in both directions and on both ports,
  so :func:`decode_message` dispatches on the letter alone.
"""

from __future__ import annotations

import logging
import math
import struct
from collections.abc import Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar, Protocol

import numpy as np

from firmware_bridge.mk_protocol import ADDR_FC, Frame, encode_frame
from quadlink.errors import ProtocolError

if TYPE_CHECKING:
    from quadlink.vehicle import ImuConfig

logger = logging.getLogger(__name__)

DECIDEG_RAD = math.radians(0.1)  # one LSB of a 0.1-degree angle, rad
CENTIDEG_RAD = math.radians(0.01)  # one LSB of a 0.01-degree angle, rad
DECIDEG_S_RAD_S = math.radians(0.1)  # one LSB of a 0.1 deg/s rate, rad/s
THRUST_FULL_SCALE = 65535  # uint16 thrust count for fraction 1.0

IMU_COUNT_MAX = 1023  # 10-bit ADC
IMU_COUNT_MASK = 0x3FF
IMU_COUNTER_MODULO = 4096  # 12-bit rolling sample counter

INT8 = (-128, 127)
UINT8 = (0, 255)
INT16 = (-32768, 32767)
UINT16 = (0, 65535)


class MkMessage(Protocol):
    """What every message class provides."""

    COMMAND: ClassVar[str]

    def pack(self) -> bytes: ...


def _finite(value: float, name: str) -> float:
    value = float(value)
    if not math.isfinite(value):
        raise ProtocolError(f"{name} must be finite, got {value!r}")
    return value


def _sat_int(value: float, bounds: tuple[int, int]) -> int:
    """Round to the nearest integer and clamp to ``bounds`` (inclusive)."""
    lo, hi = bounds
    return max(lo, min(hi, round(value)))


def _scaled(value: float, lsb: float, bounds: tuple[int, int], name: str) -> int:
    """``value / lsb`` rounded and saturated to ``bounds``; ProtocolError if not finite."""
    return _sat_int(_finite(value, name) / lsb, bounds)


def _wrap(value: int, modulo: int, name: str) -> int:
    """A rolling counter modulo ``modulo``; ProtocolError if not a finite number."""
    return int(_finite(value, name)) % modulo


def _need(payload: bytes, size: int, cls: type) -> None:
    if len(payload) < size:
        raise ProtocolError(f"{cls.__name__} payload needs {size} bytes, got {len(payload)}")


def _ints(values: Iterable[float], n: int, bounds: tuple[int, int], name: str) -> tuple[int, ...]:
    """``n`` values rounded and saturated to ``bounds`` (fast path for in-range ints: the common case)."""
    lo, hi = bounds
    out = tuple(
        (v if lo <= v <= hi else (lo if v < lo else hi)) if type(v) is int else _sat_int(_finite(v, name), bounds)
        for v in values
    )
    if len(out) != n:
        raise ProtocolError(f"{name} needs {n} values, got {len(out)}")
    return out


def _three_floats(values: Iterable[float] | np.ndarray, name: str) -> tuple[float, float, float]:
    """Three finite floats from a sequence or array (plain Python: numpy is slow on 3 elements)."""
    seq: Iterable[float] = values.tolist() if isinstance(values, np.ndarray) else values
    try:
        x, y, z = (float(v) for v in seq)
    except (TypeError, ValueError) as exc:
        raise ProtocolError(f"{name} needs 3 numbers, got {values!r}") from exc
    if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
        raise ProtocolError(f"{name} values must be finite, got {values!r}")
    return x, y, z


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
        head = _ints(
            (self.sw_major, self.sw_minor, self.proto_major, self.proto_minor, self.sw_patch), 5, UINT8, "version"
        )
        return self.STRUCT.pack(*head, *_ints(self.hardware_error, 5, UINT8, "hardware_error"))

    @classmethod
    def unpack(cls, payload: bytes) -> Version:
        _need(payload, cls.STRUCT.size, cls)
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
        return self.STRUCT.pack(_sat_int(_finite(self.interval_10ms, "interval_10ms"), UINT8))

    @classmethod
    def unpack(cls, payload: bytes) -> DebugRequest:
        _need(payload, cls.STRUCT.size, cls)
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
        return self.STRUCT.pack(*_ints(self.status, 2, UINT8, "status"), *_ints(self.analog, 32, INT16, "analog"))

    @classmethod
    def unpack(cls, payload: bytes) -> DebugData:
        _need(payload, cls.STRUCT.size, cls)
        v = cls.STRUCT.unpack_from(payload)
        return cls((v[0], v[1]), tuple(v[2:]))


@dataclass(frozen=True)
class DebugLabelRequest:
    """``'a'``: ask for the name of debug channel ``index``. ``<B``: index uint8 (0..31)."""

    COMMAND: ClassVar[str] = "a"
    STRUCT: ClassVar[struct.Struct] = struct.Struct("<B")

    index: int

    def pack(self) -> bytes:
        return self.STRUCT.pack(_sat_int(_finite(self.index, "index"), UINT8))

    @classmethod
    def unpack(cls, payload: bytes) -> DebugLabelRequest:
        _need(payload, cls.STRUCT.size, cls)
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
        return self.STRUCT.pack(_sat_int(_finite(self.index, "index"), UINT8), text)

    @classmethod
    def unpack(cls, payload: bytes) -> DebugLabel:
        _need(payload, cls.STRUCT.size, cls)
        index, raw = cls.STRUCT.unpack_from(payload)
        return cls(index, raw.decode("ascii", errors="replace").rstrip(" \x00"))


@dataclass(frozen=True)
class Data3DRequest:
    """``'c'``: start (or refresh) the :class:`Data3D` stream. ``<B``: interval_10ms uint8, 10 ms units, 0 stops."""

    COMMAND: ClassVar[str] = "c"
    STRUCT: ClassVar[struct.Struct] = struct.Struct("<B")

    interval_10ms: int

    def pack(self) -> bytes:
        return self.STRUCT.pack(_sat_int(_finite(self.interval_10ms, "interval_10ms"), UINT8))

    @classmethod
    def unpack(cls, payload: bytes) -> Data3DRequest:
        _need(payload, cls.STRUCT.size, cls)
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
        yaw = _finite(self.yaw_rad, "yaw_rad")
        yaw_wrapped = (yaw + math.pi) % (2.0 * math.pi) - math.pi
        nick = _scaled(self.pitch_rad, DECIDEG_RAD, INT16, "pitch_rad")
        roll = _scaled(self.roll_rad, DECIDEG_RAD, INT16, "roll_rad")
        yaw_dd = _sat_int(yaw_wrapped / DECIDEG_RAD, (-1800, 1799))
        return self.STRUCT.pack(
            nick, roll, yaw_dd, *_ints(self.centroid, 3, UINT8, "centroid"), *_ints(self.reserve, 5, UINT8, "reserve")
        )

    @classmethod
    def unpack(cls, payload: bytes) -> Data3D:
        _need(payload, cls.STRUCT.size, cls)
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
        d0, d1 = _ints(self.digital, 2, UINT8, "digital")
        return self.STRUCT.pack(
            d0,
            d1,
            _sat_int(_finite(self.remote_buttons, "remote_buttons"), UINT8),
            _sat_int(_finite(self.nick, "nick"), INT8),
            _sat_int(_finite(self.roll, "roll"), INT8),
            _sat_int(_finite(self.yaw, "yaw"), INT8),
            _sat_int(_finite(self.gas, "gas"), UINT8),
            _sat_int(_finite(self.height, "height"), INT8),
            _sat_int(_finite(self.free, "free"), UINT8),
            _sat_int(_finite(self.frame, "frame"), UINT8),
            _sat_int(_finite(self.config, "config"), UINT8),
        )

    @classmethod
    def unpack(cls, payload: bytes) -> ExternControl:
        _need(payload, cls.STRUCT.size, cls)
        v = cls.STRUCT.unpack_from(payload)
        return cls((v[0], v[1]), *v[2:])


@dataclass(frozen=True)
class ExternControlAck:
    """``'B'``: the board's receipt of an :class:`ExternControl`, ``<B``: frame uint8 (the echoed frame counter)."""

    COMMAND: ClassVar[str] = "B"
    STRUCT: ClassVar[struct.Struct] = struct.Struct("<B")

    frame: int

    def pack(self) -> bytes:
        return self.STRUCT.pack(_sat_int(_finite(self.frame, "frame"), UINT8))

    @classmethod
    def unpack(cls, payload: bytes) -> ExternControlAck:
        _need(payload, cls.STRUCT.size, cls)
        return cls(payload[0])


@dataclass(frozen=True)
class MotorTest:
    """``'t'``: motor test, ``<16B``: motor uint8[16] (0 off .. 255 full). Boards obey it only when disarmed."""

    COMMAND: ClassVar[str] = "t"
    STRUCT: ClassVar[struct.Struct] = struct.Struct("<16B")

    motor: tuple[int, ...] = (0,) * 16

    def pack(self) -> bytes:
        return self.STRUCT.pack(*_ints(self.motor, 16, UINT8, "motor"))

    @classmethod
    def unpack(cls, payload: bytes) -> MotorTest:
        _need(payload, cls.STRUCT.size, cls)
        return cls(tuple(cls.STRUCT.unpack_from(payload)))


# --------------------------------------------------------------------------------------------------------------
# The stack's firmware additions
# --------------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ImuSample:
    """``'I'`` (port 2, board -> companion, 500 Hz): one raw IMU sample, 12 bytes, ``<6H``.

    ======  ==================================================================================================
    word    content (uint16 each)
    ======  ==================================================================================================
    0       bits 0-9: accel x count; bits 10-15: ``sample_counter`` bits 0-5
    1       bits 0-9: accel y count; bits 10-15: ``sample_counter`` bits 6-11
    2       bits 0-9: accel z count; bits 10-15: reserved, 0
    3..5    bits 0-9: gyro x, y, z counts; bits 10-15: reserved, 0
    ======  ==================================================================================================

    Counts are raw 10-bit ADC values 0..1023 on body FRD axes, zero at ``ImuConfig.zero_count`` (512); SI value
    ``(count - zero_count) * lsb`` with ``ImuConfig.accel_lsb_m_s2`` / ``gyro_lsb_rad_s``. The accelerometer
    reports specific force (at rest, level: z = -g in FRD). ``sample_counter`` is a 12-bit rolling counter
    (sample k carries k mod 4096; the board takes sample k at board time k * 2 ms, so the counter wraps every
    8.192 s — ``BoardStatus.imu_sample_count`` at 10 Hz disambiguates the wrap). Reserved bits are ignored on
    ``unpack``.

    Link budget: 12 bytes -> 16 base64 characters -> 16 + 6 framing = **22 bytes on the wire**;
    500 Hz x 22 B = 11,000 B/s of the 11,520 B/s a 115200-baud 8N1 link carries (10 bits per byte): 95.5 %.
    One more base64 group (a 13..15-byte payload, 26 bytes framed) would need 13,000 B/s and not fit, which
    is why the counter lives in the ADC's unused high bits.

    ``pack`` saturates counts to 0..1023 and takes the counter modulo 4096.
    """

    COMMAND: ClassVar[str] = "I"
    STRUCT: ClassVar[struct.Struct] = struct.Struct("<6H")
    WIRE_BYTES: ClassVar[int] = 22

    accel_counts: tuple[int, int, int]
    gyro_counts: tuple[int, int, int]
    sample_counter: int = 0

    def pack(self) -> bytes:
        ax, ay, az = _ints(self.accel_counts, 3, (0, IMU_COUNT_MAX), "accel_counts")
        gx, gy, gz = _ints(self.gyro_counts, 3, (0, IMU_COUNT_MAX), "gyro_counts")
        counter = _wrap(self.sample_counter, IMU_COUNTER_MODULO, "sample_counter")
        return self.STRUCT.pack(ax | (counter & 0x3F) << 10, ay | (counter >> 6) << 10, az, gx, gy, gz)

    @classmethod
    def unpack(cls, payload: bytes) -> ImuSample:
        _need(payload, cls.STRUCT.size, cls)
        w = cls.STRUCT.unpack_from(payload)
        m = IMU_COUNT_MASK
        return cls(
            accel_counts=(w[0] & m, w[1] & m, w[2] & m),
            gyro_counts=(w[3] & m, w[4] & m, w[5] & m),
            sample_counter=(w[0] >> 10) | (w[1] >> 10) << 6,
        )

    def accel_m_s2(self, imu_cfg: ImuConfig) -> np.ndarray:
        """Specific force in body FRD, m/s^2, shape (3,): ``(count - zero_count) * accel_lsb_m_s2``."""
        return (np.asarray(self.accel_counts, dtype=float) - imu_cfg.zero_count) * imu_cfg.accel_lsb_m_s2

    def gyro_rad_s(self, imu_cfg: ImuConfig) -> np.ndarray:
        """Angular rate in body FRD, rad/s, shape (3,): ``(count - zero_count) * gyro_lsb_rad_s``."""
        return (np.asarray(self.gyro_counts, dtype=float) - imu_cfg.zero_count) * imu_cfg.gyro_lsb_rad_s

    @classmethod
    def from_si(
        cls,
        accel_m_s2: Iterable[float] | np.ndarray,
        gyro_rad_s: Iterable[float] | np.ndarray,
        imu_cfg: ImuConfig,
        counter: int,
    ) -> ImuSample:
        """Quantise SI values (body FRD; 3 specific-force values in m/s^2, 3 rates in rad/s, sequences or arrays)
        to counts: round to the nearest count, saturate to 0..1023 (the ADC's range), counter modulo 4096.
        Raises ``ProtocolError`` on NaN/inf or a wrong number of values."""
        zero = imu_cfg.zero_count
        a_lsb = imu_cfg.accel_lsb_m_s2
        g_lsb = imu_cfg.gyro_lsb_rad_s
        ax, ay, az = _three_floats(accel_m_s2, "accel_m_s2")
        gx, gy, gz = _three_floats(gyro_rad_s, "gyro_rad_s")

        def count(value: float) -> int:
            c = round(value) + zero
            return 0 if c < 0 else (IMU_COUNT_MAX if c > IMU_COUNT_MAX else c)

        return cls(
            accel_counts=(count(ax / a_lsb), count(ay / a_lsb), count(az / a_lsb)),
            gyro_counts=(count(gx / g_lsb), count(gy / g_lsb), count(gz / g_lsb)),
            sample_counter=_wrap(counter, IMU_COUNTER_MODULO, "counter"),
        )


SETPOINT_FLAG_ARMED = 0x01


@dataclass(frozen=True)
class AttitudeSetpoint:
    """``'s'`` (port 1, companion/bridge -> board, 100 Hz): attitude and thrust command, 10 bytes, ``<hhhHBB``.

    ==============  ======  =============================  ==============================================
    wire field      type    scaling                        dataclass field
    ==============  ======  =============================  ==============================================
    roll            int16   0.01 deg                       ``roll_rad`` (+-327.67 deg)
    pitch           int16   0.01 deg                       ``pitch_rad``
    yaw_rate        int16   0.1 deg/s                      ``yaw_rate_rad_s`` (+-3276.7 deg/s)
    thrust          uint16  fraction x 65535               ``thrust``: 0..1 of ``VehicleConfig.max_total_thrust_n``
    flags           uint8   bit0 armed, bits 1-7 zero      ``armed`` (clearing it disarms = motor cut)
    seq             uint8   rolling 0..255                 ``seq`` (acknowledged in ``BoardStatus.last_setpoint_seq``)
    ==============  ======  =============================  ==============================================

    Angles: body FRD ZYX Euler (``quadlink.frames``), positive roll = right side down, positive pitch = nose up,
    positive yaw rate = clockwise seen from above. Wire size: 10 bytes -> 4 base64 groups (2 zero pad bytes)
    -> 16 characters -> **22 bytes framed**; 100 Hz x 22 B = 2,200 B/s (19 % of 115200 8N1).
    ``pack`` rounds to the nearest LSB and saturates (thrust clamped to 0..1, angles/rate to int16), ``seq``
    modulo 256; NaN/inf raise ``ProtocolError``.
    """

    COMMAND: ClassVar[str] = "s"
    STRUCT: ClassVar[struct.Struct] = struct.Struct("<hhhHBB")

    roll_rad: float
    pitch_rad: float
    yaw_rate_rad_s: float
    thrust: float
    armed: bool
    seq: int = 0

    def pack(self) -> bytes:
        return self.STRUCT.pack(
            _scaled(self.roll_rad, CENTIDEG_RAD, INT16, "roll_rad"),
            _scaled(self.pitch_rad, CENTIDEG_RAD, INT16, "pitch_rad"),
            _scaled(self.yaw_rate_rad_s, DECIDEG_S_RAD_S, INT16, "yaw_rate_rad_s"),
            _scaled(self.thrust, 1.0 / THRUST_FULL_SCALE, UINT16, "thrust"),
            SETPOINT_FLAG_ARMED if self.armed else 0,
            _wrap(self.seq, 256, "seq"),
        )

    @classmethod
    def unpack(cls, payload: bytes) -> AttitudeSetpoint:
        _need(payload, cls.STRUCT.size, cls)
        roll, pitch, yaw_rate, thrust, flags, seq = cls.STRUCT.unpack_from(payload)
        return cls(
            roll_rad=roll * CENTIDEG_RAD,
            pitch_rad=pitch * CENTIDEG_RAD,
            yaw_rate_rad_s=yaw_rate * DECIDEG_S_RAD_S,
            thrust=thrust / THRUST_FULL_SCALE,
            armed=bool(flags & SETPOINT_FLAG_ARMED),
            seq=seq,
        )


FLIGHT_STATE_LANDED = 0
FLIGHT_STATE_FLYING = 1
FLIGHT_STATE_FAILSAFE_DESCEND = 2

STATUS_FLAG_ARMED = 0x01
STATUS_FLAG_FAILSAFE = 0x02

# BoardStatus.error_flags bits (uint16). One definition for firmware (SITL) and bridge.
ERROR_SETPOINT_TIMEOUT = 0x0001  # no valid 's' frame within the firmware's timeout (failsafe trigger)
ERROR_BATTERY_LOW = 0x0002  # battery below the warning threshold
ERROR_IMU_SATURATED = 0x0004  # an IMU channel hit 0 or 1023 since the last status
ERROR_RX_FRAMES_DROPPED = 0x0008  # the board dropped received frames (checksum/garbage) since the last status


@dataclass(frozen=True)
class BoardStatus:
    """``'S'`` (port 1, board -> companion, 10 Hz and on every arm-state change): 15 bytes, ``<BBHHIIB``.

    =================  ======  ================================================================================
    wire field         type    meaning
    =================  ======  ================================================================================
    flags              uint8   bit0 ``armed``, bit1 ``failsafe``, bits 2-7 zero
    flight_state       uint8   ``flight_state``: 0 landed, 1 flying, 2 failsafe descend
    battery_mv         uint16  battery voltage, mV (saturates at 0..65535)
    error_flags        uint16  ``ERROR_*`` bits (masked to 16 bits)
    board_time_ms      uint32  board time, ms (= 2 x imu_sample_count on the stack's firmware; wraps at 2**32)
    imu_sample_count   uint32  IMU samples emitted so far (sample k at board time k * 2 ms; wraps at 2**32)
    last_setpoint_seq  uint8   ``seq`` of the last valid ``'s'`` frame received (the setpoint acknowledgement)
    =================  ======  ================================================================================

    Wire size: 15 bytes -> 5 base64 groups -> 20 characters -> 26 bytes framed (10 Hz: 260 B/s).
    """

    COMMAND: ClassVar[str] = "S"
    STRUCT: ClassVar[struct.Struct] = struct.Struct("<BBHHIIB")

    armed: bool
    flight_state: int
    failsafe: bool
    battery_mv: int
    error_flags: int
    board_time_ms: int
    imu_sample_count: int
    last_setpoint_seq: int

    def pack(self) -> bytes:
        flags = (STATUS_FLAG_ARMED if self.armed else 0) | (STATUS_FLAG_FAILSAFE if self.failsafe else 0)
        return self.STRUCT.pack(
            flags,
            _sat_int(_finite(self.flight_state, "flight_state"), UINT8),
            _sat_int(_finite(self.battery_mv, "battery_mv"), UINT16),
            _wrap(self.error_flags, 0x10000, "error_flags"),
            _wrap(self.board_time_ms, 2**32, "board_time_ms"),
            _wrap(self.imu_sample_count, 2**32, "imu_sample_count"),
            _wrap(self.last_setpoint_seq, 256, "last_setpoint_seq"),
        )

    @classmethod
    def unpack(cls, payload: bytes) -> BoardStatus:
        _need(payload, cls.STRUCT.size, cls)
        flags, state, mv, errors, t_ms, n_imu, seq = cls.STRUCT.unpack_from(payload)
        return cls(
            armed=bool(flags & STATUS_FLAG_ARMED),
            flight_state=state,
            failsafe=bool(flags & STATUS_FLAG_FAILSAFE),
            battery_mv=mv,
            error_flags=errors,
            board_time_ms=t_ms,
            imu_sample_count=n_imu,
            last_setpoint_seq=seq,
        )


# --------------------------------------------------------------------------------------------------------------
# Dispatch
# --------------------------------------------------------------------------------------------------------------

Message = (
    VersionRequest | Version | DebugRequest | DebugData | DebugLabelRequest | DebugLabel | Data3DRequest | Data3D
    | ExternControl | ExternControlAck | MotorTest | ImuSample | AttitudeSetpoint | BoardStatus
)  # fmt: skip

MESSAGE_TYPES: dict[str, type[Message]] = {
    cls.COMMAND: cls
    for cls in (
        VersionRequest,
        Version,
        DebugRequest,
        DebugData,
        DebugLabelRequest,
        DebugLabel,
        Data3DRequest,
        Data3D,
        ExternControl,
        ExternControlAck,
        MotorTest,
        ImuSample,
        AttitudeSetpoint,
        BoardStatus,
    )
}


def decode_message(frame: Frame) -> Message | None:
    """The typed message a frame carries, by its command letter (address, port and direction do not matter).

    Returns ``None`` for an unknown letter or a payload too short for the letter's struct (logged at debug
    level); never raises for any :class:`Frame` the decoder produced.
    """
    cls = MESSAGE_TYPES.get(frame.command)
    if cls is None:
        logger.debug("no message type for MK command %r (address %d)", frame.command, frame.address)
        return None
    try:
        return cls.unpack(frame.payload)
    except ProtocolError as exc:
        logger.debug("dropping MK %r frame: %s", frame.command, exc)
        return None


def encode_message(msg: MkMessage, address: int = ADDR_FC) -> bytes:
    """The complete wire frame of ``msg`` for node ``address`` (default FlightCtrl)."""
    return encode_frame(address, msg.COMMAND, msg.pack())

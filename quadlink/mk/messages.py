"""Typed payloads of the MK frames the stack speaks (the one definition every side imports).

Each message is a frozen dataclass with a class attribute ``COMMAND`` (its frame letter), ``pack() -> bytes``
(the raw payload; :func:`encode_message` frames it) and ``@classmethod unpack(payload) -> message``.
All layouts are explicit little-endian :mod:`struct` formats (the AVR's byte order), stated in each docstring
as ``field: type, unit, scaling``. ``PROTOCOL.md`` beside this module documents the same on the wire.

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
  (port 2, board -> companion), ``s`` attitude/thrust setpoint (port 1, companion -> board), ``S`` board
  status and ``Z`` barometric altitude (port 1, board -> companion). Every letter means one message in both
  directions and on both ports, so :func:`decode_message` dispatches on the letter alone.
"""

from __future__ import annotations

import logging
import struct
from collections.abc import Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar

import numpy as np

from quadlink.errors import ProtocolError
from quadlink.mk.fields import (
    CENTIDEG_RAD,
    DECIDEG_S_RAD_S,
    IMU_COUNT_MASK,
    IMU_COUNT_MAX,
    IMU_COUNTER_MODULO,
    INT16,
    INT32,
    THRUST_FULL_SCALE,
    UINT8,
    UINT16,
    UINT32,
    MkMessage,
    finite,
    ints,
    need,
    sat_int,
    scaled,
    three_floats,
    wrap,
)
from quadlink.mk.flags import SetpointFlag, StatusFlag
from quadlink.mk.protocol import ADDR_FC, Frame, encode_frame
from quadlink.mk.standard import (
    Data3D,
    Data3DRequest,
    DebugData,
    DebugLabel,
    DebugLabelRequest,
    DebugRequest,
    ExternControl,
    ExternControlAck,
    MotorTest,
    Version,
    VersionRequest,
)

if TYPE_CHECKING:
    from quadlink.vehicle import ImuConfig

logger = logging.getLogger(__name__)

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
        ax, ay, az = ints(self.accel_counts, 3, (0, IMU_COUNT_MAX), "accel_counts")
        gx, gy, gz = ints(self.gyro_counts, 3, (0, IMU_COUNT_MAX), "gyro_counts")
        counter = wrap(self.sample_counter, IMU_COUNTER_MODULO, "sample_counter")
        return self.STRUCT.pack(ax | (counter & 0x3F) << 10, ay | (counter >> 6) << 10, az, gx, gy, gz)

    @classmethod
    def unpack(cls, payload: bytes) -> ImuSample:
        need(payload, cls.STRUCT.size, cls)
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
        ax, ay, az = three_floats(accel_m_s2, "accel_m_s2")
        gx, gy, gz = three_floats(gyro_rad_s, "gyro_rad_s")

        def count(value: float) -> int:
            c = round(value) + zero
            return 0 if c < 0 else (IMU_COUNT_MAX if c > IMU_COUNT_MAX else c)

        return cls(
            accel_counts=(count(ax / a_lsb), count(ay / a_lsb), count(az / a_lsb)),
            gyro_counts=(count(gx / g_lsb), count(gy / g_lsb), count(gz / g_lsb)),
            sample_counter=wrap(counter, IMU_COUNTER_MODULO, "counter"),
        )


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
            scaled(self.roll_rad, CENTIDEG_RAD, INT16, "roll_rad"),
            scaled(self.pitch_rad, CENTIDEG_RAD, INT16, "pitch_rad"),
            scaled(self.yaw_rate_rad_s, DECIDEG_S_RAD_S, INT16, "yaw_rate_rad_s"),
            scaled(self.thrust, 1.0 / THRUST_FULL_SCALE, UINT16, "thrust"),
            SetpointFlag.ARMED if self.armed else 0,
            wrap(self.seq, 256, "seq"),
        )

    @classmethod
    def unpack(cls, payload: bytes) -> AttitudeSetpoint:
        need(payload, cls.STRUCT.size, cls)
        roll, pitch, yaw_rate, thrust, flags, seq = cls.STRUCT.unpack_from(payload)
        return cls(
            roll_rad=roll * CENTIDEG_RAD,
            pitch_rad=pitch * CENTIDEG_RAD,
            yaw_rate_rad_s=yaw_rate * DECIDEG_S_RAD_S,
            thrust=thrust / THRUST_FULL_SCALE,
            armed=bool(flags & SetpointFlag.ARMED),
            seq=seq,
        )


@dataclass(frozen=True)
class BoardStatus:
    """``'S'`` (port 1, board -> companion, 10 Hz and on every arm-state change): 15 bytes, ``<BBHHIIB``.

    =================  ======  ================================================================================
    wire field         type    meaning
    =================  ======  ================================================================================
    flags              uint8   bit0 ``armed``, bit1 ``failsafe``, bits 2-7 zero
    flight_state       uint8   ``BoardFlightState``: 0 landed, 1 flying, 2 failsafe descend
    battery_mv         uint16  battery voltage, mV (saturates at 0..65535)
    error_flags        uint16  ``BoardError`` bits (masked to 16 bits)
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
        flags = (StatusFlag.ARMED if self.armed else 0) | (StatusFlag.FAILSAFE if self.failsafe else 0)
        return self.STRUCT.pack(
            flags,
            sat_int(finite(self.flight_state, "flight_state"), UINT8),
            sat_int(finite(self.battery_mv, "battery_mv"), UINT16),
            wrap(self.error_flags, 0x10000, "error_flags"),
            wrap(self.board_time_ms, 2**32, "board_time_ms"),
            wrap(self.imu_sample_count, 2**32, "imu_sample_count"),
            wrap(self.last_setpoint_seq, 256, "last_setpoint_seq"),
        )

    @classmethod
    def unpack(cls, payload: bytes) -> BoardStatus:
        need(payload, cls.STRUCT.size, cls)
        flags, state, mv, errors, t_ms, n_imu, seq = cls.STRUCT.unpack_from(payload)
        return cls(
            armed=bool(flags & StatusFlag.ARMED),
            flight_state=state,
            failsafe=bool(flags & StatusFlag.FAILSAFE),
            battery_mv=mv,
            error_flags=errors,
            board_time_ms=t_ms,
            imu_sample_count=n_imu,
            last_setpoint_seq=seq,
        )


@dataclass(frozen=True)
class BaroAltitude:
    """``'Z'`` (port 1, board -> bridge, 50 Hz): the board's barometric altitude, 12 bytes, ``<ihIBB``.

    =================  ======  ================================================================================
    wire field         type    meaning
    =================  ======  ================================================================================
    altitude_cm        int32   barometric altitude above the board's reference, cm, positive **up** (the
                               reference is the pressure the board averaged while disarmed, re-taken at arming)
    climb_cm_s         int16   the board's barometric climb rate, cm/s, positive up (saturates)
    pressure_pa        uint32  the board's static pressure estimate, Pa (MPX4115A through its amplifier)
    flags              uint8   bit0 ``valid`` (sensor in range, reference taken), bit1 ``saturated`` (the
                               amplified signal hit the ADC's rail in the window)
    seq                uint8   rolling 0..255, one per frame
    =================  ======  ================================================================================

    Wire size: 12 bytes -> 4 base64 groups -> 16 characters -> 22 bytes framed (50 Hz: 1,100 B/s, 9.5 % of
    port 1). The bridge fuses it with the IMU for the blind (companion-less) descent; the board uses the same
    estimate for its own failsafe's touchdown detection.

    ``altitude_cm`` and ``climb_cm_s`` are the output of the board's alpha-beta filter on the pressure's height
    (``firmware/src/baro.h``: alpha 2^-7, beta 2^-15 per 2 ms tick), not the height itself: the consumer that
    compares them with a height runs the same filter on it (``FILTER_ALPHA_1_S``, ``FILTER_BETA_1_S2``, its gains as
    rates: ``h += (climb + alpha r) dt``, ``climb += beta r dt``, ``r`` = height - h).
    """

    COMMAND: ClassVar[str] = "Z"
    FILTER_ALPHA_1_S: ClassVar[float] = 500.0 / 2 ** 7
    FILTER_BETA_1_S2: ClassVar[float] = 500.0 ** 2 / 2 ** 15
    STRUCT: ClassVar[struct.Struct] = struct.Struct("<ihIBB")
    FLAG_VALID: ClassVar[int] = 0x01
    FLAG_SATURATED: ClassVar[int] = 0x02

    altitude_m: float
    climb_m_s: float
    pressure_pa: float
    valid: bool = True
    saturated: bool = False
    seq: int = 0

    def pack(self) -> bytes:
        flags = (self.FLAG_VALID if self.valid else 0) | (self.FLAG_SATURATED if self.saturated else 0)
        return self.STRUCT.pack(
            scaled(self.altitude_m, 0.01, INT32, "altitude_m"),
            scaled(self.climb_m_s, 0.01, INT16, "climb_m_s"),
            sat_int(finite(self.pressure_pa, "pressure_pa"), UINT32),
            flags,
            wrap(self.seq, 256, "seq"),
        )

    @classmethod
    def unpack(cls, payload: bytes) -> BaroAltitude:
        need(payload, cls.STRUCT.size, cls)
        alt_cm, climb_cm_s, pa, flags, seq = cls.STRUCT.unpack_from(payload)
        return cls(altitude_m=alt_cm * 0.01, climb_m_s=climb_cm_s * 0.01, pressure_pa=float(pa),
                   valid=bool(flags & cls.FLAG_VALID), saturated=bool(flags & cls.FLAG_SATURATED), seq=seq)


# --------------------------------------------------------------------------------------------------------------
# Dispatch
# --------------------------------------------------------------------------------------------------------------

Message = (
    VersionRequest | Version | DebugRequest | DebugData | DebugLabelRequest | DebugLabel | Data3DRequest | Data3D
    | ExternControl | ExternControlAck | MotorTest | ImuSample | AttitudeSetpoint | BoardStatus | BaroAltitude
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
        BaroAltitude,
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

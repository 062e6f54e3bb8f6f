"""MK message payloads: golden vectors, struct round trips (hypothesis), saturation, wire sizes, dispatch."""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from quadlink.errors import ProtocolError
from quadlink.frames import GRAVITY_M_S2
from quadlink.mk.fields import CENTIDEG_RAD, DECIDEG_RAD, DECIDEG_S_RAD_S
from quadlink.mk.messages import (
    MESSAGE_TYPES,
    AttitudeSetpoint,
    BaroAltitude,
    BoardStatus,
    Data3D,
    Data3DRequest,
    DebugData,
    DebugLabel,
    DebugLabelRequest,
    DebugRequest,
    ExternControl,
    ExternControlAck,
    ImuSample,
    MotorTest,
    Version,
    VersionRequest,
    decode_message,
    encode_message,
)
from quadlink.mk.protocol import ADDR_ANY, ADDR_FC, Frame, FrameDecoder, decode_frame
from quadlink.vehicle import ImuConfig

IMU = ImuConfig()


def wire_round_trip(msg: object, address: int = ADDR_FC) -> object:
    """Encode to wire bytes, decode through the stream decoder and the dispatcher."""
    wire = encode_message(msg, address)  # type: ignore[arg-type]
    frames = FrameDecoder().feed(wire)
    assert len(frames) == 1 and frames[0].address == address
    return decode_message(frames[0])


# --- vectors from MK_PROTOCOL.md


def test_extern_control_vector() -> None:
    wire = b"#bb====>\\i=[===>mA=RS\r"
    msg = decode_message(decode_frame(wire))
    assert isinstance(msg, ExternControl)
    assert (msg.nick, msg.roll, msg.gas, msg.frame, msg.config) == (5, -5, 120, 7, 1)
    assert (msg.digital, msg.remote_buttons, msg.yaw, msg.height, msg.free) == ((0, 0), 0, 0, 0, 0)
    assert msg.pack() == bytes.fromhex("00000005fb007800000701")
    assert encode_message(msg) == wire
    assert encode_message(ExternControl(nick=5, roll=-5, gas=120, frame=7, config=1), ADDR_FC) == wire


def test_request_vectors() -> None:
    assert encode_message(VersionRequest(), ADDR_FC) == b"#bv@x\r"
    assert encode_message(VersionRequest(), 2) == b"#cv@y\r"
    assert encode_message(DebugRequest(10)) == b"#bd?]==D|\r"
    assert decode_message(decode_frame(b"#bd?]==D|\r")) == DebugRequest(10)
    assert decode_message(decode_frame(b"#av@w\r")) == VersionRequest()


def test_version_vector_and_captured_frames() -> None:
    v = Version(sw_major=0, sw_minor=84, proto_major=11, proto_minor=0, sw_patch=3)
    assert v.pack() == bytes.fromhex("00540b00030000000000")
    assert encode_message(v, ADDR_ANY) == b"#aV=BMH==I=========PS\r"
    fc = decode_message(decode_frame(b"#bV=BMH============PH\r"))
    assert fc == Version(0, 84, 11, 0, 0, (0, 0, 0, 0, 0))
    assert isinstance(fc, Version) and fc.version_str == "0.84a"
    nc = decode_message(decode_frame(b"#cV=>]H==A=========PY\r"))
    assert isinstance(nc, Version) and nc.version_str == "0.24b" and nc.proto_major == 11
    bad = FrameDecoder()
    assert bad.feed(b"#cV=>]H==Ac========PY\r") == [] and bad.stats.bad_checksum == 1


# --- wire sizes


def test_imu_sample_is_22_bytes_on_the_wire() -> None:
    for msg in [ImuSample((0, 0, 0), (0, 0, 0), 0), ImuSample((1023,) * 3, (1023,) * 3, 4095)]:  # type: ignore[arg-type]
        assert len(msg.pack()) == 12
        assert len(encode_message(msg)) == ImuSample.WIRE_BYTES == 22
    # link budget of port 2: 500 Hz x 22 B within 115200 8N1 (10 bits per byte)
    assert 500 * 22 == 11_000 <= 115_200 // 10
    assert 11_000 / 11_520 == pytest.approx(0.955, abs=0.0005)


def test_other_wire_sizes() -> None:
    assert len(encode_message(AttitudeSetpoint(0, 0, 0, 0, False, 0))) == 22
    assert len(encode_message(BoardStatus(False, 0, False, 0, 0, 0, 0, 0))) == 26
    assert len(Data3D(0, 0, 0).pack()) == 14
    assert len(DebugData().pack()) == 66
    assert len(ExternControl().pack()) == 11


# --- round trips

u8 = st.integers(0, 255)
i8 = st.integers(-128, 127)
i16 = st.integers(-32768, 32767)
count10 = st.integers(0, 1023)
angle = st.floats(-math.radians(327.0), math.radians(327.0), allow_nan=False)


@settings(deadline=None)
@given(count10, count10, count10, count10, count10, count10, st.integers(0, 4095))
def test_imu_round_trip(ax: int, ay: int, az: int, gx: int, gy: int, gz: int, counter: int) -> None:
    msg = ImuSample((ax, ay, az), (gx, gy, gz), counter)
    assert ImuSample.unpack(msg.pack()) == msg
    assert wire_round_trip(msg) == msg
    words = struct.unpack("<6H", msg.pack())
    # layout: low 10 bits = counts; counter low 6 bits in word 0, high 6 bits in word 1; rest reserved 0
    assert [w & 0x3FF for w in words] == [ax, ay, az, gx, gy, gz]
    assert words[0] >> 10 == counter & 0x3F and words[1] >> 10 == counter >> 6
    assert all(w >> 10 == 0 for w in words[2:])


def test_imu_ignores_reserved_bits() -> None:
    payload = struct.pack("<6H", 5 | 0xFC00, 6, 7 | 0xFC00, 8 | 0x8000, 9, 10 | 0x0400)
    assert ImuSample.unpack(payload) == ImuSample((5, 6, 7), (8, 9, 10), 63)


@settings(deadline=None)
@given(angle, angle, st.floats(-50.0, 50.0), st.floats(0.0, 1.0), st.booleans(), u8)
def test_setpoint_round_trip(roll: float, pitch: float, yaw_rate: float, thrust: float, armed: bool, seq: int) -> None:
    msg = AttitudeSetpoint(roll, pitch, yaw_rate, thrust, armed, seq)
    got = wire_round_trip(msg)
    assert isinstance(got, AttitudeSetpoint)
    # scaled fields within half an LSB (rounding), exact integers and flags
    assert abs(got.roll_rad - roll) <= 0.5 * CENTIDEG_RAD + 1e-12
    assert abs(got.pitch_rad - pitch) <= 0.5 * CENTIDEG_RAD + 1e-12
    assert abs(got.yaw_rate_rad_s - yaw_rate) <= 0.5 * DECIDEG_S_RAD_S + 1e-12
    assert abs(got.thrust - thrust) <= 0.5 / 65535 + 1e-12
    assert (got.armed, got.seq) == (armed, seq)
    assert AttitudeSetpoint.unpack(got.pack()) == got  # decoded values are exact fixed points


@settings(deadline=None)
@given(st.booleans(), st.integers(0, 2), st.booleans(), st.integers(0, 65535), st.integers(0, 65535),
       st.integers(0, 2**32 - 1), st.integers(0, 2**32 - 1), u8)  # fmt: skip
def test_status_round_trip(
    armed: bool, state: int, failsafe: bool, mv: int, errors: int, t_ms: int, n_imu: int, seq: int
) -> None:
    msg = BoardStatus(armed, state, failsafe, mv, errors, t_ms, n_imu, seq)
    assert wire_round_trip(msg) == msg


@settings(deadline=None)
@given(angle, angle, st.floats(-math.pi, math.pi * 0.999, allow_nan=False), st.tuples(u8, u8, u8))
def test_data3d_round_trip(roll: float, pitch: float, yaw: float, centroid: tuple[int, int, int]) -> None:
    msg = Data3D(roll, pitch, yaw, centroid)
    got = wire_round_trip(msg)
    assert isinstance(got, Data3D)
    assert abs(got.roll_rad - roll) <= 0.5 * DECIDEG_RAD + 1e-12
    assert abs(got.pitch_rad - pitch) <= 0.5 * DECIDEG_RAD + 1e-12
    assert abs(math.remainder(got.yaw_rad - yaw, 2 * math.pi)) <= 0.5 * DECIDEG_RAD + 1e-12
    assert -math.pi <= got.yaw_rad < math.pi
    assert got.centroid == centroid


def test_data3d_nick_is_pitch_and_heading_wraps() -> None:
    # wire order nick, roll, yaw: nick 100 = 10 deg pitch, roll -50 = -5 deg, stock heading 3590 = 359 deg -> -1 deg
    payload = struct.pack("<3h3B5B", 100, -50, 3590, 1, 2, 3, 0, 0, 0, 0, 0)
    msg = Data3D.unpack(payload)
    assert msg.pitch_rad == pytest.approx(math.radians(10.0))
    assert msg.roll_rad == pytest.approx(math.radians(-5.0))
    assert msg.yaw_rad == pytest.approx(math.radians(-1.0))
    assert msg.centroid == (1, 2, 3)
    assert struct.unpack_from("<3h", Data3D(0.0, 0.0, math.radians(270.0)).pack()) == (0, 0, -900)


@settings(deadline=None)
@given(st.builds(ExternControl, st.tuples(u8, u8), u8, i8, i8, i8, u8, i8, u8, u8, u8))
def test_extern_control_round_trip(msg: ExternControl) -> None:
    assert wire_round_trip(msg) == msg


@settings(deadline=None)
@given(st.tuples(u8, u8), st.lists(i16, min_size=32, max_size=32).map(tuple))
def test_debug_data_round_trip(status: tuple[int, int], analog: tuple[int, ...]) -> None:
    msg = DebugData(status, analog)
    assert wire_round_trip(msg) == msg


@settings(deadline=None)
@given(u8, u8, u8, u8, u8, st.tuples(u8, u8, u8, u8, u8))
def test_version_round_trip(a: int, b: int, c: int, d: int, e: int, hw: tuple[int, int, int, int, int]) -> None:
    msg = Version(a, b, c, d, e, hw)
    assert wire_round_trip(msg, ADDR_ANY) == msg


@settings(deadline=None)
@given(u8, st.text(st.characters(min_codepoint=33, max_codepoint=126), max_size=16))
def test_small_messages_round_trip(value: int, label: str) -> None:
    for msg in [DebugRequest(value), Data3DRequest(value), DebugLabelRequest(value), ExternControlAck(value),
                DebugLabel(value, label), MotorTest((value,) * 16), VersionRequest()]:  # fmt: skip
        assert wire_round_trip(msg) == msg


# --- saturation and bad values


def test_setpoint_saturates() -> None:
    hot = AttitudeSetpoint.unpack(AttitudeSetpoint(10.0, -10.0, 1e6, 1.7, True, 256 + 3).pack())
    assert hot.roll_rad == pytest.approx(32767 * CENTIDEG_RAD)
    assert hot.pitch_rad == pytest.approx(-32768 * CENTIDEG_RAD)
    assert hot.yaw_rate_rad_s == pytest.approx(32767 * DECIDEG_S_RAD_S)
    assert hot.thrust == 1.0 and hot.seq == 3
    cold = AttitudeSetpoint.unpack(AttitudeSetpoint(0.0, 0.0, -1e6, -0.3, False, -1).pack())
    assert cold.thrust == 0.0 and cold.seq == 255 and not cold.armed
    assert cold.yaw_rate_rad_s == pytest.approx(-32768 * DECIDEG_S_RAD_S)


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_values_raise(bad: float) -> None:
    with pytest.raises(ProtocolError, match="finite"):
        AttitudeSetpoint(0.0, 0.0, 0.0, bad, True, 0).pack()
    with pytest.raises(ProtocolError, match="finite"):
        AttitudeSetpoint(bad, 0.0, 0.0, 0.5, True, 0).pack()
    with pytest.raises(ProtocolError, match="finite"):
        Data3D(0.0, 0.0, bad).pack()
    with pytest.raises(ProtocolError, match="finite"):
        ImuSample.from_si((0.0, 0.0, bad), (0.0, 0.0, 0.0), IMU, 0)


def test_integer_fields_saturate_or_wrap() -> None:
    ext = ExternControl.unpack(ExternControl(nick=300, roll=-300, gas=-4, frame=999).pack())
    assert (ext.nick, ext.roll, ext.gas, ext.frame) == (127, -128, 0, 255)
    imu = ImuSample.unpack(ImuSample((-5, 2000, 512), (1024, 0, 1023), 4096 + 7).pack())
    assert imu == ImuSample((0, 1023, 512), (1023, 0, 1023), 7)
    st_ = BoardStatus.unpack(BoardStatus(True, 300, True, 70000, 0x1FFFF, 2**32 + 5, -1, 257).pack())
    assert (st_.flight_state, st_.battery_mv, st_.error_flags) == (255, 65535, 0xFFFF)
    assert (st_.board_time_ms, st_.imu_sample_count, st_.last_setpoint_seq) == (5, 2**32 - 1, 1)
    assert st_.armed and st_.failsafe
    with pytest.raises(ProtocolError, match="needs 3"):
        ImuSample((1, 2), (1, 2, 3), 0).pack()  # type: ignore[arg-type]


# --- IMU SI conversion


def test_imu_si_conversion_at_rest() -> None:
    # level at rest, FRD: specific force -g on z; zero rate
    sample = ImuSample.from_si((0.0, 0.0, -GRAVITY_M_S2), (0.0, 0.0, 0.0), IMU, counter=4097)
    expected_z = IMU.zero_count + round(-GRAVITY_M_S2 / IMU.accel_lsb_m_s2)
    assert sample.accel_counts == (512, 512, expected_z)
    assert sample.gyro_counts == (512, 512, 512) and sample.sample_counter == 1
    np.testing.assert_allclose(sample.accel_m_s2(IMU), [0.0, 0.0, -GRAVITY_M_S2], atol=0.5 * IMU.accel_lsb_m_s2)
    np.testing.assert_array_equal(sample.gyro_rad_s(IMU), np.zeros(3))


@settings(deadline=None)
@given(
    st.lists(st.floats(-15.0, 15.0), min_size=3, max_size=3),
    st.lists(st.floats(-4.0, 4.0), min_size=3, max_size=3),
    st.integers(0, 10**6),
)
def test_imu_from_si_quantises_within_half_lsb(accel: list[float], gyro: list[float], k: int) -> None:
    sample = ImuSample.from_si(np.array(accel), np.array(gyro), IMU, k)
    got = ImuSample.unpack(sample.pack())
    assert got == sample and got.sample_counter == k % 4096
    a_max = (1023 - IMU.zero_count) * IMU.accel_lsb_m_s2
    a_min = -IMU.zero_count * IMU.accel_lsb_m_s2
    g_max = (1023 - IMU.zero_count) * IMU.gyro_lsb_rad_s
    g_min = -IMU.zero_count * IMU.gyro_lsb_rad_s
    # saturated to the ADC range, otherwise within half a count
    np.testing.assert_allclose(got.accel_m_s2(IMU), np.clip(accel, a_min, a_max), atol=0.5 * IMU.accel_lsb_m_s2 + 1e-9)
    np.testing.assert_allclose(got.gyro_rad_s(IMU), np.clip(gyro, g_min, g_max), atol=0.5 * IMU.gyro_lsb_rad_s + 1e-9)


# --- dispatch


def test_dispatch_covers_every_letter_once() -> None:
    assert set(MESSAGE_TYPES) == set("vVdDaAcCbBtIsSZ")
    for letter, cls in MESSAGE_TYPES.items():
        assert cls.COMMAND == letter


def test_decode_message_is_address_independent() -> None:
    msg = AttitudeSetpoint(0.1, -0.1, 0.2, 0.5, True, 9)
    payload = msg.pack() + b"\x00\x00"  # what the frame decoder returns: whole groups
    decoded = {decode_message(Frame(addr, "s", payload)) for addr in (0, 1, 2, 3)}
    assert len(decoded) == 1


def test_decode_message_unknown_or_short_is_none() -> None:
    assert decode_message(Frame(1, "R", b"")) is None  # the reboot letter: never a message of ours
    assert decode_message(Frame(1, "x", b"abc")) is None
    assert decode_message(Frame(1, "I", bytes(9))) is None  # 12 bytes needed
    assert decode_message(Frame(1, "S", bytes(12))) is None  # 15 bytes needed
    with pytest.raises(ProtocolError, match="12 bytes"):
        ImuSample.unpack(bytes(9))


def test_messages_are_frozen() -> None:
    msg = AttitudeSetpoint(0.0, 0.0, 0.0, 0.5, True, 1)
    with pytest.raises(AttributeError):
        msg.thrust = 1.0  # type: ignore[misc]


# --- 'Z' barometric altitude


def test_baro_altitude_golden_payload_and_wire_size() -> None:
    msg = BaroAltitude(altitude_m=1.23, climb_m_s=-0.45, pressure_pa=101325.0, valid=True, saturated=True, seq=300)
    # altitude 123 cm int32, climb -45 cm/s int16, 101325 Pa uint32, flags valid|saturated, seq 300 mod 256
    assert msg.pack() == bytes([123, 0, 0, 0, 0xD3, 0xFF, 0xCD, 0x8B, 0x01, 0x00, 0x03, 44])
    assert len(encode_message(msg)) == 22  # 12 bytes -> 16 characters + 6 framing: 50 Hz is 9.5 % of port 1
    back = BaroAltitude.unpack(msg.pack())
    assert (back.altitude_m, back.climb_m_s, back.pressure_pa, back.valid, back.saturated, back.seq) == (
        1.23, -0.45, 101325.0, True, True, 44)


def test_baro_altitude_saturates_and_refuses_nan() -> None:
    far = BaroAltitude.unpack(BaroAltitude(1e9, -1e6, -5.0).pack())
    assert far.altitude_m == (2**31 - 1) * 0.01 and far.climb_m_s == -327.68 and far.pressure_pa == 0.0
    with pytest.raises(ProtocolError):
        BaroAltitude(float("nan"), 0.0, 101325.0).pack()

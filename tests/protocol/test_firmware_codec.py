"""The firmware's MK codec (C, host build) against quadlink's Python codec, in both directions.

Golden bytes come from ``quadlink.mk`` (the one definition of the wire format): every message the board
speaks must encode to the same bytes in C, every frame Python encodes must decode in C to the same payload,
and the C stream decoder must count exactly what ``FrameDecoder`` counts on hostile input (garbage, '#'
inside frames, overlong runs, bad checksums, invalid characters).
"""

from __future__ import annotations

import ctypes
import math

import pytest
from firmware_host import CDecoder, c_encode, u8
from fuzzing import FUZZ
from hypothesis import given
from hypothesis import strategies as st

from quadlink.mk.messages import (
    AttitudeSetpoint,
    BaroAltitude,
    BoardStatus,
    Data3D,
    DebugData,
    DebugLabel,
    ExternControlAck,
    ImuSample,
    Version,
    encode_message,
)
from quadlink.mk.protocol import DEFAULT_MAX_FRAME_LEN, FrameDecoder, encode_frame
from quadlink.mk.standard import Data3DRequest, DebugLabelRequest, DebugRequest, ExternControl, MotorTest

LETTERS = "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz"


def c_payload(lib: ctypes.CDLL, fn: str, *args: object) -> bytes:
    out = (ctypes.c_uint8 * 200)()
    n = getattr(lib, fn)(out, *args)
    return bytes(out[:n])


def test_max_frame_len_matches(firmware_lib: ctypes.CDLL) -> None:
    assert ctypes.c_int.in_dll(firmware_lib, "qlh_max_frame_len").value == DEFAULT_MAX_FRAME_LEN


def test_every_board_message_encodes_byte_identical(firmware_lib: ctypes.CDLL) -> None:
    lib = firmware_lib
    imu = ImuSample((1, 1023, 256), (0, 700, 512), sample_counter=4095)
    got = c_encode(lib, 1, "I", c_payload(lib, "qlh_pack_imu", (ctypes.c_uint16 * 3)(1, 1023, 256),
                                           (ctypes.c_uint16 * 3)(0, 700, 512), 4095))
    assert got == encode_message(imu) and len(got) == ImuSample.WIRE_BYTES

    status = BoardStatus(True, 2, True, 11_900, 0x000B, 123_456, 61_728, 201)
    got = c_encode(lib, 1, "S", c_payload(lib, "qlh_pack_status", 0x03, 2, 11_900, 0x000B, 123_456, 61_728, 201))
    assert got == encode_message(status)

    baro = BaroAltitude(altitude_m=-12.34, climb_m_s=-0.57, pressure_pa=101_325, valid=True, saturated=True, seq=9)
    got = c_encode(lib, 1, "Z", c_payload(lib, "qlh_pack_baro", -1234, -57, 101_325, 0x03, 9))
    assert got == encode_message(baro)

    sp = AttitudeSetpoint(roll_rad=math.radians(-12.5), pitch_rad=math.radians(3.0), yaw_rate_rad_s=math.radians(-45.0),
                          thrust=0.5, armed=True, seq=77)
    got = c_encode(lib, 1, "s", c_payload(lib, "qlh_pack_setpoint", -1250, 300, -450, 32768, 1, 77))
    assert got == encode_message(sp)

    version = Version(2, 1, 11, 0, 0, (1, 0, 0, 0, 0))
    got = c_encode(lib, 1, "V", c_payload(lib, "ql_pack_version", u8([2, 1, 11, 0, 0, 1, 0, 0, 0, 0])))
    assert got == encode_message(version)

    analog = tuple(range(-16, 16))
    got = c_encode(lib, 1, "D", c_payload(lib, "ql_pack_debug", u8([1, 2]), (ctypes.c_int16 * 32)(*analog)))
    assert got == encode_message(DebugData((1, 2), analog))

    for label in ("Roll 0.1deg", "", "A label that is far too long"):
        got = c_encode(lib, 1, "A", c_payload(lib, "ql_pack_label", 7, label.encode()))
        assert got == encode_message(DebugLabel(7, label))

    d3 = Data3D(roll_rad=math.radians(-1.5), pitch_rad=math.radians(10.0), yaw_rad=math.radians(-179.9),
                centroid=(1, 2, 3), reserve=(4, 5, 6, 7, 8))
    got = c_encode(lib, 1, "C", c_payload(lib, "qlh_pack_data3d", (ctypes.c_int16 * 3)(100, -15, -1799),
                                          u8([1, 2, 3]), u8([4, 5, 6, 7, 8])))
    assert got == encode_message(d3)

    assert c_encode(lib, 1, "B", c_payload(lib, "ql_pack_u8", 7)) == encode_message(ExternControlAck(7))
    assert c_encode(lib, 1, "v", b"") == b"#bv@x\r"  # PROTOCOL.md's example


def test_requests_python_sends_decode_in_c(firmware_lib: ctypes.CDLL) -> None:
    dec = CDecoder(firmware_lib)
    msgs = [DebugRequest(10), Data3DRequest(5), DebugLabelRequest(19), MotorTest(tuple(range(16))),
            ExternControl((0, 0), 0, 5, -5, 0, 120, 0, 0, 7, 1)]
    for msg in msgs:
        frames = dec.feed(encode_message(msg))
        payload = msg.pack()
        assert frames == [(1, msg.COMMAND, payload + bytes(-len(payload) % 3))]
    sp = AttitudeSetpoint(0.1, -0.2, 0.3, 0.75, True, 250)
    (_, _, payload), = dec.feed(encode_message(sp))
    out = (ctypes.c_int32 * 6)()
    assert firmware_lib.qlh_unpack_setpoint(u8(payload), len(payload), out) == 1
    assert list(out) == [round(math.degrees(0.1) * 100), round(math.degrees(-0.2) * 100),
                         round(math.degrees(0.3) * 10), round(0.75 * 65535), 1, 250]
    assert firmware_lib.qlh_unpack_setpoint(u8(payload[:9]), 9, out) == 0  # too short for the struct


@FUZZ
@given(address=st.integers(0, 25), command=st.sampled_from(LETTERS), payload=st.binary(max_size=159))
def test_any_frame_round_trips_both_ways(firmware_lib: ctypes.CDLL, address: int, command: str,
                                         payload: bytes) -> None:
    wire = c_encode(firmware_lib, address, command, payload)
    assert wire == encode_frame(address, command, payload)
    frames = CDecoder(firmware_lib).feed(wire)
    assert frames == [(address, command, payload + bytes(-len(payload) % 3))]


def test_encoder_refuses_what_python_refuses(firmware_lib: ctypes.CDLL) -> None:
    assert c_encode(firmware_lib, 1, "x", bytes(160)) == b""  # 222 bytes: exceeds the 220-byte buffer
    assert c_encode(firmware_lib, 26, "x", b"") == b""
    assert c_encode(firmware_lib, 1, "1", b"") == b""
    assert len(c_encode(firmware_lib, 1, "x", bytes(159))) == 218


# hostile streams: frames (valid, corrupted, overlong) and runs of the bytes that matter to the decoder
_frame = st.builds(encode_frame, st.integers(0, 25), st.sampled_from(LETTERS), st.binary(max_size=159))
_chunk = st.one_of(
    _frame,
    _frame.map(lambda f: f[:-3] + bytes([f[-3] ^ 1]) + f[-2:]),  # checksum off by one bit
    st.binary(min_size=1, max_size=40),
    st.lists(st.sampled_from(b"#\r=|a~bZ\x00\xff"), min_size=1, max_size=30).map(bytes),
    st.integers(200, 260).map(lambda n: b"#bx" + b"=" * n + b"\r"),  # around the 220-byte limit
    st.just(b"#bV=BMH============PH\r"),
    st.just(b"#cV=>]H==Ac========PY\r"),
)


@FUZZ
@pytest.mark.parametrize("batch", [0, 1, 7, 32, 255])  # byte by byte, and the batch path in chunks (main: 32)
@given(chunks=st.lists(_chunk, max_size=12))
def test_decoder_rules_match_python_on_hostile_streams(firmware_lib: ctypes.CDLL, batch: int,
                                                       chunks: list[bytes]) -> None:
    stream = b"".join(chunks)
    py = FrameDecoder()
    py_frames = [(f.address, f.command, f.payload) for f in py.feed(stream)]
    c = CDecoder(firmware_lib, batch)
    c_frames = c.feed(stream)
    assert c_frames == py_frames
    stats = c.stats()
    pending = stats.pop("pending_bytes")
    assert stats == py.stats.as_dict()
    assert pending == py.pending_bytes
    frame_bytes = sum(len(encode_frame(a, cmd, p)) for a, cmd, p in c_frames)
    assert stats["garbage_bytes"] + stats["dropped_bytes"] + frame_bytes + pending == len(stream)


@pytest.mark.parametrize("batch", [0, 32, 255])
@pytest.mark.parametrize("extra", [0, 1, 2])
def test_frame_length_limit(firmware_lib: ctypes.CDLL, extra: int, batch: int) -> None:
    """The largest valid frame (218 bytes, 53 groups) is accepted; 222 and 226 are overlong (over 220), and the
    decoder resynchronises on the next frame."""
    head = b"#bx" + b"=" * (212 + 4 * extra)
    crc = sum(head) % 4096
    frame = head + bytes((61 + crc // 64, 61 + crc % 64, 13))
    stream = frame + encode_frame(1, "v")
    c = CDecoder(firmware_lib, batch)
    frames = c.feed(stream)
    py = FrameDecoder()
    assert frames == [(f.address, f.command, f.payload) for f in py.feed(stream)]
    assert len(frames) == (2 if len(frame) <= 220 else 1)
    assert c.stats()["overlong"] == (0 if len(frame) <= 220 else 1)

"""The firmware's board core (``firmware/src/fc.c``, host build): what each port carries, tick by tick.

Port 2 carries only ``I`` (every tick, raw counts, 12-bit counter); port 1 answers requests as
``sim_sitl/board.py`` does (``v``, ``a``, ``b``, periodic ``d`` / ``c`` with the 4 s timeout), sends ``S`` at
10 Hz and on every arm change and ``Z`` at 50 Hz. Frames are decoded with quadlink's Python codec.
"""

from __future__ import annotations

import ctypes
from collections.abc import Iterator

import pytest
from firmware_host import CBoard

from quadlink.mk.flags import BoardError, BoardFlightState
from quadlink.mk.messages import (
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
from quadlink.mk.protocol import ADDR_NC, FrameDecoder
from sim_sitl.board import DEBUG_LABELS, SITL_VERSION

PORT1, PORT2 = 0, 1


def decode(data: bytes) -> list[object]:
    dec = FrameDecoder()
    msgs = [decode_message(f) for f in dec.feed(data)]
    assert dec.stats.frames_dropped == 0 and dec.stats.garbage_bytes == 0
    return msgs


def valid_image(lib: ctypes.CDLL) -> bytes:
    from firmware_host import blob

    p = blob(lib, "qlh_params_size")
    lib.ql_params_defaults(p)
    n = ctypes.c_int.in_dll(lib, "qlh_params_image_len").value
    out = (ctypes.c_uint8 * n)()
    lib.ql_params_store(p, out)
    return bytes(out)


@pytest.fixture
def board(firmware_lib: ctypes.CDLL) -> Iterator[CBoard]:
    b = CBoard(firmware_lib, valid_image(firmware_lib))
    yield b
    b.close()


def of(msgs: list[object], cls: type) -> list:
    return [m for m in msgs if isinstance(m, cls)]


def test_port2_carries_only_imu_samples_with_the_counter(board: CBoard) -> None:
    n = 4100  # past the 12-bit counter's wrap
    wire = b""
    for k in range(n):
        board.tick(accel=(k % 1024, 300, 256), gyro=(511, 512, (3 * k) % 1024))
        if k % 1000 == 999:
            wire += board.take(PORT2)
    msgs = decode(wire + board.take(PORT2))
    assert len(msgs) == n and all(isinstance(m, ImuSample) for m in msgs)
    for k, m in enumerate(msgs):
        assert m.sample_counter == k % 4096
        assert m.accel_counts == (k % 1024, 300, 256) and m.gyro_counts == (511, 512, (3 * k) % 1024)


def test_status_at_10_hz_and_on_arm_change(board: CBoard) -> None:
    for _ in range(500):
        board.tick()
    status = of(decode(board.take(PORT1)), BoardStatus)
    assert len(status) == 10
    assert [s.imu_sample_count for s in status] == [1 + 50 * i for i in range(10)]
    assert all(s.board_time_ms == 2 * s.imu_sample_count and not s.armed for s in status)
    board.rx(encode_message(AttitudeSetpoint(0.0, 0.0, 0.0, 0.5, True, seq=123)))
    board.tick()  # an S at once, not at the next 10 Hz slot
    (s,) = of(decode(board.take(PORT1)), BoardStatus)
    assert s.armed and s.last_setpoint_seq == 123 and s.flight_state == BoardFlightState.FLYING
    assert s.imu_sample_count == 501
    assert board.state()["armed"] == 1 and min(board.state()[f"m{i}"] for i in range(1, 5)) > 100
    board.rx(encode_message(AttitudeSetpoint(0.0, 0.0, 0.0, 0.5, False, seq=124)))
    board.tick()
    (s,) = of(decode(board.take(PORT1)), BoardStatus)
    assert not s.armed and s.last_setpoint_seq == 124
    assert [board.state()[f"m{i}"] for i in range(1, 5)] == [0, 0, 0, 0]


def test_baro_at_50_hz(board: CBoard) -> None:
    for _ in range(1000):
        board.tick(baro=600)
    baro = of(decode(board.take(PORT1)), BaroAltitude)
    assert len(baro) == 100
    assert [z.seq for z in baro] == list(range(100))
    assert not baro[0].valid and baro[-1].valid  # the reference is taken after 0.5 s
    assert baro[-1].pressure_pa == round(95_000 + 600 * 1000 / 92.16)
    assert baro[-1].altitude_m == pytest.approx(0.0, abs=0.02)


def test_version_labels_and_extern_control_ack(board: CBoard, firmware_lib: ctypes.CDLL) -> None:
    board.rx(encode_message(VersionRequest()))
    board.rx(encode_message(ExternControl((0, 0), 0, 5, -5, 0, 120, 0, 0, 7, 1)))
    for i in range(23):
        board.rx(encode_message(DebugLabelRequest(i)))
    msgs = decode(board.take(PORT1))
    assert of(msgs, Version) == [SITL_VERSION]
    assert of(msgs, ExternControlAck) == [ExternControlAck(7)]
    labels = [m.label for m in of(msgs, DebugLabel)]
    assert labels[:16] == list(DEBUG_LABELS)
    assert labels[16:21] == ["Busy cyc u16", "Busy max u16", "P2 drops", "P1 rx drops", "Late ticks"]
    assert labels[21:] == ["Analog21", "Analog22"]
    # without valid parameters in the EEPROM the board says so in the version's first error byte
    blank = CBoard(firmware_lib, bytes(200))
    blank.rx(encode_message(VersionRequest()))
    (v,) = of(decode(blank.take(PORT1)), Version)
    assert v.hardware_error[0] == 1 and blank.state()["params_ok"] == 0
    blank.close()


def test_requests_for_another_node_are_ignored(board: CBoard) -> None:
    board.rx(encode_message(VersionRequest(), address=ADDR_NC))
    board.rx(encode_message(AttitudeSetpoint(0.0, 0.0, 0.0, 0.5, True, seq=1), address=ADDR_NC))
    board.tick()
    msgs = decode(board.take(PORT1))
    assert not of(msgs, Version) and board.state()["armed"] == 0


def test_debug_stream_layout_interval_and_timeout(board: CBoard) -> None:
    for _ in range(300):
        board.tick()
    board.take(PORT1)
    board.rx(encode_message(DebugRequest(10)))  # every 100 ms
    board.rx(encode_message(AttitudeSetpoint(0.0, 0.0, 0.0, 0.5, True, seq=5)))
    board.lib.qlh_board_set_busy(board.ptr, 12345, 39999)
    for k in range(3000):
        if k % 5 == 0:  # 100 Hz setpoints
            board.rx(encode_message(AttitudeSetpoint(0.0, 0.0, 0.0, 0.5, True, seq=k & 0xFF)))
        board.tick(gyro=(500, 510, 520), accel=(512, 512, 250), battery=640)
    debug = of(decode(board.take(PORT1)), DebugData)
    # at once, then every 50 ticks until 4 s after the request; one telemetry frame per tick, so a D that
    # coincides with an S or a Z goes out a tick later (and the last one may fall past the 4 s)
    assert 2000 // 50 <= len(debug) <= 2000 // 50 + 1
    d = debug[-1]
    assert d.status == (1, BoardFlightState.FLYING)
    a = d.analog
    assert a[3] == 50 and a[9] == 1 and a[10] == BoardFlightState.FLYING
    assert a[8] == 1250  # 640 counts x 19.53 mV = 12.50 V, in 10 mV
    assert a[11] == 100  # setpoints in the last second
    assert a[12:16] == (500, 510, 520, 250)
    assert sum(a[4:8]) == pytest.approx(0.5 * 20.0 * 100, abs=8)  # motor thrusts, cN, sum to the collective
    assert a[16] == 12345 and a[17] & 0xFFFF == 39999  # cycles as uint16 bits in the int16 slots
    assert a[18:21] == (0, 0, 0)
    board.rx(encode_message(DebugRequest(0)))  # 0 stops at once
    board.rx(encode_message(DebugRequest(1)))
    board.rx(encode_message(DebugRequest(0)))
    for _ in range(100):
        board.tick()
    assert not of(decode(board.take(PORT1)), DebugData)


def test_data3d_stream(board: CBoard) -> None:
    board.rx(encode_message(Data3DRequest(2)))
    for _ in range(400):
        board.tick(accel=(512, 512 - 44, 256 + 4))  # rolled right about 9.8 deg
    frames = of(decode(board.take(PORT1)), Data3D)
    assert len(frames) == 40
    assert frames[-1].roll_rad == pytest.approx(0.171, abs=0.01)
    assert frames[-1].pitch_rad == pytest.approx(0.0, abs=0.005)


def test_motor_test_only_disarmed(board: CBoard) -> None:
    board.rx(encode_message(MotorTest((10, 20, 30, 40) + (0,) * 12)))
    board.tick()
    assert [board.state()[f"m{i}"] for i in range(1, 5)] == [10, 20, 30, 40]
    for _ in range(250):
        board.tick()
    assert [board.state()[f"m{i}"] for i in range(1, 5)] == [0, 0, 0, 0]  # 0.5 s after the last 't'
    board.rx(encode_message(AttitudeSetpoint(0.0, 0.0, 0.0, 0.1, True, seq=1)))
    board.rx(encode_message(MotorTest((200, 200, 200, 200) + (0,) * 12)))
    board.tick()
    assert max(board.state()[f"m{i}"] for i in range(1, 5)) < 100  # armed: the test is ignored


def test_a_full_ring_drops_whole_frames_and_counts_them(board: CBoard) -> None:
    board.set_room(PORT2, 21)  # one byte short of an I frame
    board.tick()
    assert board.take(PORT2) == b""
    assert board.state()["p2_tx_dropped"] == 1
    board.set_room(PORT2, -1)
    board.rx(encode_message(DebugRequest(1)))
    board.tick()
    (d,) = of(decode(board.take(PORT1)), DebugData)
    assert d.analog[18] == 1


def test_error_flags_battery_imu_and_rx_drops(board: CBoard) -> None:
    good = encode_message(AttitudeSetpoint(0.0, 0.0, 0.0, 0.0, False, seq=1))
    board.rx(good[:-3] + bytes([good[-3] ^ 1]) + good[-2:])  # a bad checksum
    for _ in range(200):  # the battery's verdict waits 64 ticks for its low-pass to settle
        board.tick(battery=500, accel=(512, 512, 1023))  # 9.77 V, an accelerometer at its rail
    status = of(decode(board.take(PORT1)), BoardStatus)
    flags = status[-1].error_flags
    assert flags & BoardError.BATTERY_LOW and flags & BoardError.IMU_SATURATED
    assert status[0].error_flags & BoardError.RX_FRAMES_DROPPED
    assert not flags & BoardError.RX_FRAMES_DROPPED  # reported once, since the last status
    assert status[-1].battery_mv == pytest.approx(9766, abs=1)
    assert board.state()["rx_frames_dropped"] == 1
    for _ in range(200):
        board.tick(battery=645)  # 12.6 V again (hysteresis 0.2 V)
    assert not of(decode(board.take(PORT1)), BoardStatus)[-1].error_flags & BoardError.BATTERY_LOW

"""The flight firmware (firmware/build/quadlink-fc.elf) in simavr, pins held as a board at rest on the floor.

No physics here (tests/sitl/test_avr_board_sitl.py flies it): the 500 Hz ``I`` stream, the setpoint-to-motor
latency, the failsafe on setpoint silence, parameters in EEPROM across a reset, and a hostile port 1. Times are
in cycles of the 20 MHz clock: one tick = 40,000 cycles, one byte on the wire = 1760.
"""

from __future__ import annotations

import os
import struct
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from avr_firmware import Rig, firmware_elf  # noqa: F401  (fixture)

from quadlink.mk.flags import BoardError
from quadlink.mk.messages import AttitudeSetpoint, BoardStatus, Version, VersionRequest, encode_message
from quadlink.mk.protocol import encode_frame

pytestmark = pytest.mark.timeout(600)

TICK = 40_000
BYTE = 1760


@pytest.fixture
def rig(firmware_elf: Path) -> Iterator[Rig]:  # noqa: F811
    r = Rig(firmware_elf)
    yield r
    r.close()


def fly(rig: Rig, seconds: float, thrust: float, armed: bool = True, start_seq: int = 0) -> int:
    """Setpoints at 100 Hz (one per 5 ticks) for ``seconds``; returns the next seq."""
    seq = start_seq
    for _ in range(round(seconds * 100)):
        rig.send(AttitudeSetpoint(0.0, 0.0, 0.0, thrust, armed, seq & 0xFF))
        seq += 1
        rig.run_ticks(5)
    return seq


def check_imu_stream(rig: Rig, seconds: float) -> None:
    s = rig.monitor.stats
    assert s.bad_frames == 0
    assert s.lost == 0, f"{s.lost} IMU samples lost"
    assert s.late == 0, f"{s.late} frames late (worst lag {s.max_lag_cycles} cycles)"
    assert s.first_cycle is not None
    rate_hz = (s.frames - 1) / ((s.last_cycle - s.first_cycle) / 20e6)
    assert rate_hz == pytest.approx(500.0, abs=0.05)
    assert s.frames >= seconds * 500 - 3


LOOP_BUDGET = 0.60  # the 500 Hz loop's worst case, share of its 40,000 cycles (benchmarks/bench_firmware.py)


def test_imu_stream_is_500_hz_with_no_lost_or_late_frame_disarmed_and_armed(rig: Rig) -> None:
    rig.run_s(3.0)
    fly(rig, 5.0, 0.4)  # armed: the whole attitude loop runs (on the floor: the pins do not move)
    check_imu_stream(rig, 8.0)
    worst = max(rig.loop.busy_cycles)
    assert worst < TICK, f"the loop overran its tick: {worst} cycles"


@pytest.mark.slow
def test_imu_stream_over_60_s_while_flying_the_setpoints(rig: Rig) -> None:
    fly(rig, 60.0, 0.4)
    check_imu_stream(rig, 60.0)
    busy = np.array(rig.loop.busy_cycles)
    assert busy.max() < TICK


def test_setpoint_to_motor_bytes_latency(rig: Rig) -> None:
    rig.run_s(0.5)
    seq = fly(rig, 1.0, 0.3)
    before = rig.mcu.motors().bytes
    assert all(b > 0 for b in before)
    rig.send(AttitudeSetpoint(0.0, 0.0, 0.0, 0.6, True, seq & 0xFF))
    for _ in range(10):
        rig.run_ticks(1)
        m = rig.mcu.motors()
        if sum(m.bytes) > 1.5 * sum(before):
            break
    else:
        pytest.fail(f"motor bytes never followed the thrust step: {before} -> {rig.mcu.motors().bytes}")
    received = rig.mcu.port1_last_received_cycle
    latency = max(m.last_cycle) - received
    # the frame is taken at the next tick's start, then flown and written within that tick's work
    assert 0 < latency <= TICK * (1 + LOOP_BUDGET), f"latency {latency} cycles"
    # ... and the bytes follow thrust x 4 motors / max: 0.6 of 4 x 5 N over 4 motors = 3 N = byte 153
    assert np.mean(m.bytes) == pytest.approx(0.6 * 255, abs=12)


def test_failsafe_on_setpoint_silence_descends_then_cuts_on_the_ground(rig: Rig) -> None:
    rig.run_s(0.5)
    fly(rig, 2.0, 0.55)
    flying = rig.mcu.motors().bytes
    assert all(b > 100 for b in flying) and rig.mcu.portb(1) == 1
    silence_cycle = rig.mcu.cycle
    rig.run_s(8.0)
    after = [(c, b) for c, b in rig.motor_log if c > silence_cycle]
    # still flying through the setpoint timeout (0.5 s) and the descent, never a cut in the air at once
    early = [b for c, b in after if c < silence_cycle + 0.45 * 20e6]
    assert all(min(b) > 0 for b in early)
    statuses = rig.messages(BoardStatus, since_cycle=silence_cycle)
    failsafe = [s for s in statuses if s.failsafe]
    assert failsafe, "no S frame reported the failsafe"
    assert all(s.error_flags & BoardError.SETPOINT_TIMEOUT for s in failsafe)
    descending = [b for c, b in after if 0 < min(b) and c > silence_cycle + 0.6 * 20e6]
    assert descending, "no descent phase with the motors running"
    # the descent asks for less than the hover-ish thrust it flew, then the board, on the ground, cuts
    assert np.mean(descending[0]) < np.mean(flying)
    assert after[-1][1] == (0, 0, 0, 0)
    assert rig.mcu.portb(1) == 0  # the LED: disarmed
    assert not statuses[-1].armed


PARAMS = struct.Struct("<H17fHf3ffB3f")  # firmware/src/params.h ql_params_t (AVR: no padding)
DEFAULTS = (1, 7.0, 16.0, 20.0, 0.15, 8.0, 4.0, 0.6, 3.5, 2.5, 20.0, 0.5, 0.15, 0.5, 0.3, 0.7, 1.1, 0.15, 10500,
            1.0, 0.0075, 0.0075, 0.013, 0.25, 1, 5.0, 0.08, 0.016)
BATTERY_LOW_MV = 18


def crc16_ccitt_false(data: bytes) -> int:
    crc = 0xFFFF
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) & 0xFFFF if crc & 0x8000 else (crc << 1) & 0xFFFF
    return crc


def test_eeprom_parameters_survive_a_reset(rig: Rig) -> None:
    rig.send(VersionRequest())
    rig.run_s(1.5)
    blank = rig.messages(Version)[-1]
    assert blank.hardware_error[0] == 1  # erased EEPROM: defaults, flagged
    assert not any(s.error_flags & BoardError.BATTERY_LOW for s in rig.messages(BoardStatus))

    values = list(DEFAULTS)
    values[BATTERY_LOW_MV] = 13000  # above the 12.6 V battery: the board must say so
    body = PARAMS.pack(*values)
    image = body + struct.pack("<H", crc16_ccitt_false(body))
    rig.mcu.set_eeprom(image + rig.mcu.eeprom()[len(image):])
    rig.mcu.reset()
    reset_cycle = rig.mcu.cycle
    rig.send(VersionRequest())
    rig.run_s(2.0)
    assert rig.mcu.eeprom()[:len(image)] == image  # the reset kept it (and the firmware did not overwrite it)
    version = rig.messages(Version, since_cycle=reset_cycle)[-1]
    assert version.hardware_error[0] == 0  # a valid image: loaded
    statuses = rig.messages(BoardStatus, since_cycle=reset_cycle)
    assert statuses and statuses[-1].error_flags & BoardError.BATTERY_LOW
    assert statuses[0].imu_sample_count < 100  # counted from the reset: it did restart

    image_bad = bytearray(image)
    image_bad[5] ^= 0x40  # a flipped bit: the CRC must catch it
    rig.mcu.set_eeprom(bytes(image_bad))
    rig.mcu.reset()
    bad_cycle = rig.mcu.cycle
    rig.send(VersionRequest())
    rig.run_s(1.5)
    assert rig.messages(Version, since_cycle=bad_cycle)[-1].hardware_error[0] == 1


def test_hostile_port1_never_disturbs_the_imu_stream(rig: Rig) -> None:
    rng = np.random.default_rng(int(os.environ.get("QUADLINK_SEED", "7")))
    good_v = encode_message(VersionRequest())
    bad_crc = bytearray(encode_message(AttitudeSetpoint(0.1, 0.0, 0.0, 0.9, True, 1)))
    bad_crc[-2] ^= 1
    overlong = b"#bs" + b"=" * 400 + b"\r"
    junk = [bytes(rng.integers(0, 256, 300, dtype=np.uint8)), bytes(bad_crc), overlong, b"#" * 50, b"\r" * 50,
            encode_frame(1, "s", b"\x00"), good_v]
    sent_v = 0
    for _ in range(60):  # 60 x 1/6 s = 10 s, each burst far more than the line carries in that time
        for chunk in junk:
            rig.mcu.send_port1(chunk)
        sent_v += 1
        rig.run_ticks(83)
    while rig.mcu.port1_pending:
        rig.run_ticks(50)
    rig.run_ticks(50)
    check_imu_stream(rig, rig.monitor.stats.frames / 500)
    assert rig.monitor.stats.frames >= 5000
    assert not rig.mcu.portb(1)  # the corrupt armed setpoint never armed it
    assert all(min(b) == 0 for _, b in rig.motor_log)
    versions = rig.messages(Version)
    assert len(versions) >= sent_v - 2  # the well-formed requests among the junk are still answered
    assert any(s.error_flags & BoardError.RX_FRAMES_DROPPED for s in rig.messages(BoardStatus))


SOAK_S = float(os.environ.get("QUADLINK_AVR_SOAK_S", "600"))  # issue 32: "a 10-minute simavr soak"


@pytest.mark.slow
@pytest.mark.timeout(3600)
def test_soak_10_min_imu_stream_and_loop_under_setpoints_and_hostile_port1(rig: Rig) -> None:
    """600 s of simulated time (QUADLINK_AVR_SOAK_S): armed, setpoints at 50 Hz (roll/pitch steps, so the loop's
    arithmetic moves), the IMU pins dithered every 20 ms, a ``v`` request now and then, and every 5 s one of the
    hostile port-1 bursts of the test above (garbage, a corrupt armed setpoint, an overlong frame, runs of ``#``
    and ``\\r``, a truncated frame) or a 2000-byte flood (0.18 s of the line, under the 0.5 s setpoint timeout).
    Asserts: no ``I`` sample lost or late over the whole run, 500 Hz, the loop's worst tick within 60 % of its
    budget, the board armed and flying the setpoints throughout (no failsafe), the junk counted as dropped."""
    rng = np.random.default_rng(int(os.environ.get("QUADLINK_SEED", "11")))
    bad_crc = bytearray(encode_message(AttitudeSetpoint(0.3, 0.0, 0.0, 0.9, True, 1)))
    bad_crc[-2] ^= 1
    good_frame = encode_message(AttitudeSetpoint(0.0, 0.0, 0.0, 0.4, True, 0))
    bursts = [lambda: bytes(rng.integers(0, 256, 300, dtype=np.uint8)), lambda: bytes(bad_crc),
              lambda: b"#bs" + b"=" * 400 + b"\r", lambda: b"#" * 50, lambda: b"\r" * 50,
              lambda: good_frame[:12], lambda: bytes(rng.integers(0, 256, 2000, dtype=np.uint8))]
    rig.run_s(1.0)  # still and disarmed: the gyro offsets
    start_cycle = rig.mcu.cycle
    steps = round(SOAK_S * 50)
    seq, v_sent, bursts_sent, motors_stopped = 0, 0, 0, 0
    for k in range(steps):
        phase = (k // 25) % 4  # a 0.5 s step each: roll +, roll -, pitch +, pitch -
        roll = (0.15, -0.15, 0.0, 0.0)[phase]
        pitch = (0.0, 0.0, 0.15, -0.15)[phase]
        rig.send(AttitudeSetpoint(roll, pitch, 0.0, 0.45, True, seq & 0xFF))
        seq += 1
        if k % 250 == 125:  # every 5 s, between two setpoints
            rig.mcu.send_port1(bursts[bursts_sent % len(bursts)]())
            bursts_sent += 1
        if k % 1500 == 700:  # every 30 s
            rig.send(VersionRequest())
            v_sent += 1
        for axis in range(3):  # the IMU's noise on the pins, +-3 counts around a level board
            rig.mcu.set_adc_count(axis, 512 + int(rng.integers(-3, 4)))
        rig.run_ticks(10)
        motors_stopped += min(rig.mcu.motors().bytes) == 0
    rig.run_ticks(50)
    seconds = (rig.mcu.cycle - start_cycle) / 20e6
    s = rig.monitor.stats
    worst = rig.loop.busy_max
    busy = np.array(rig.loop.busy_cycles)
    print(f"\nsoak {seconds:.1f} s simulated: I frames {s.frames}, lost {s.lost}, late {s.late}, bad {s.bad_frames}, "
          f"worst lag {s.max_lag_cycles} cycles; loop busy max {worst} cycles ({100 * worst / TICK:.1f} %), "
          f"p99 of the last {busy.size} {np.percentile(busy, 99):.0f}; hostile bursts {bursts_sent}, "
          f"v requests {v_sent}; motors stopped after {motors_stopped} of {steps} setpoints; "
          f"uart tx lost {rig.mcu.tx_lost(0)}/{rig.mcu.tx_lost(1)}, edges lost {rig.mcu.edges_lost}")
    check_imu_stream(rig, seconds)
    assert s.frames >= SOAK_S * 500
    assert rig.mcu.tx_lost(0) == rig.mcu.tx_lost(1) == 0 and rig.mcu.edges_lost == 0
    assert rig.loop.starts >= (SOAK_S + 1.0) * 500 - 2  # every tick ran (PB0 rose)
    assert worst <= LOOP_BUDGET * TICK, f"the loop's worst tick: {worst} cycles ({100 * worst / TICK:.1f} %)"
    # mobility: armed and flying the setpoints throughout, never in failsafe, every request answered
    assert motors_stopped == 0 and rig.mcu.portb(1) == 1
    statuses = rig.messages(BoardStatus, since_cycle=start_cycle)
    assert len(statuses) >= SOAK_S * 10 - 2
    assert all(st.armed and not st.failsafe for st in statuses[5:])
    assert not any(st.error_flags & BoardError.SETPOINT_TIMEOUT for st in statuses)
    assert len(rig.messages(Version, since_cycle=start_cycle)) == v_sent
    assert any(st.error_flags & BoardError.RX_FRAMES_DROPPED for st in statuses)

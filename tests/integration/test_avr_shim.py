"""The simavr shim (sim_sitl/avr/) on its test program (avr_fixture/echo.c): every pin of firmware/HARDWARE.md.

Cycle figures: 20 MHz; USART 115200 Bd with U2X and UBRR 21 = 176 cycles per bit, 1760 per 8N1 byte; the test
program's Timer1 ticks every 40,000 cycles.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from avr_firmware import echo_elf  # noqa: F401  (fixture)

from sim_sitl.avr.build import build, library_path
from sim_sitl.avr.sim import AvrSim, AvrSimError, mv_for_count

TICK = 40_000
BYTE = 1760
FRAME = 22  # the test program's frame on USART1: 'I', tick, ADC0 (2 bytes), 17 x '=', '\r'


def frames_of(data: bytes) -> list[bytes]:
    return [data[i:i + FRAME] for i in range(0, len(data) - FRAME + 1, FRAME)]


@pytest.fixture
def mcu(echo_elf: Path):  # noqa: F811
    with AvrSim(echo_elf) as sim:
        yield sim


def test_build_is_cached_by_source_hash() -> None:
    first = build()
    assert first == library_path() and first.is_file()
    mtime = first.stat().st_mtime_ns
    assert build() == first and first.stat().st_mtime_ns == mtime  # not rebuilt


def test_missing_elf_is_a_clear_error(tmp_path: Path) -> None:
    with pytest.raises(AvrSimError, match="no firmware ELF"):
        AvrSim(tmp_path / "nope.elf")
    bogus = tmp_path / "bogus.elf"
    bogus.write_bytes(b"not an elf")
    with pytest.raises(AvrSimError, match="cannot read"):
        AvrSim(bogus)


def test_500_hz_frames_leave_usart1_at_the_line_rate(mcu: AvrSim) -> None:
    mcu.set_adc_count(0, 300)
    mcu.run_until(TICK * 501)
    data, cycles = mcu.take_tx(1)
    assert mcu.cycles_per_byte(1) == BYTE  # 10 bits of 176 cycles (simavr 1.6 alone would count 11)
    frames = frames_of(data)
    # frame k is queued at tick k + 1 (the first compare match) a few ADC conversions in and takes 38,720 cycles
    assert len(frames) == 499
    assert all(f[:1] == b"I" and f[-1:] == b"\r" for f in frames)
    assert [f[1] for f in frames] == [k % 256 for k in range(499)]  # the tick counter: no frame missing
    assert all(int.from_bytes(f[2:4], "little") == 300 for f in frames)
    gaps = [b - a for a, b in zip(cycles, cycles[1:], strict=False)]
    assert min(gaps) >= BYTE  # never two bytes in one byte time
    in_frame = [g for i, g in enumerate(gaps) if (i + 1) % FRAME]
    # back to back inside a frame, but for the UDRE interrupt's latency: simavr 1.6's transmitter has no UDR
    # double buffer, so a byte starts when the ISR writes it, not when the previous one ends
    assert sorted(in_frame)[len(in_frame) // 2] == BYTE
    assert max(in_frame) <= BYTE + 64
    ends = cycles[FRAME - 1::FRAME]
    periods = {b - a for a, b in zip(ends, ends[1:], strict=False)}
    assert max(periods) - min(periods) <= 2 * BYTE  # the frames keep the tick (the ADC's wait varies)
    assert (ends[-1] - ends[0]) / (len(ends) - 1) == pytest.approx(TICK, abs=1)


def test_adc_reads_every_count_exactly(mcu: AvrSim) -> None:
    mcu.run_until(TICK)
    for count in (0, 1, 2, 255, 511, 512, 513, 700, 1022, 1023):
        mcu.set_adc_count(0, count)
        mcu.run_for(TICK)
        mcu.run_for(TICK)
        data, _ = mcu.take_tx(1)
        last = next(data[i:i + FRAME] for i in range(len(data) - FRAME, -1, -1)
                    if data[i] == ord("I") and data[i + FRAME - 1] == 0x0D)
        assert int.from_bytes(last[2:4], "little") == count, count
    assert mv_for_count(1023) == 5000 and mv_for_count(0) == 0


def test_adc_counts_at_once_read_as_each_channel_alone(mcu: AvrSim) -> None:
    """``set_adc_counts`` (one shim call per tick, the SITL's path) drives every channel as ``set_adc_count``
    does: ADC0 comes back in the frame, ADC1 / 4 in the motor bytes; counts outside 0..1023 are clamped."""
    mcu.run_until(TICK)
    for adc0, adc1 in ((0, 4), (513, 800), (1023, 1023), (-5, 2000)):
        mcu.set_adc_counts([adc0, adc1, 0, 0, 0, 0, 0, 0])
        mcu.run_for(2 * TICK)
        data, _ = mcu.take_tx(1)
        last = next(data[i:i + FRAME] for i in range(len(data) - FRAME, -1, -1)
                    if data[i] == ord("I") and data[i + FRAME - 1] == 0x0D)
        assert int.from_bytes(last[2:4], "little") == min(max(adc0, 0), 1023)
        assert mcu.motors().bytes == (max(min(max(adc1, 0), 1023) // 4, 1),) * 4
    with pytest.raises(ValueError):
        mcu.set_adc_counts([0] * 9)


def test_port1_bytes_arrive_at_the_line_rate_and_are_all_received(mcu: AvrSim) -> None:
    mcu.run_until(TICK)
    mcu.take_tx(0)
    start = mcu.cycle
    sent = bytes(range(0, 200, 2))  # even: the LED stays off
    assert mcu.send_port1(sent) == len(sent)
    mcu.run_for(BYTE * 10)
    assert 9 <= mcu.port1_fed <= 11  # ten byte times: about ten bytes, not all of them
    mcu.run_until(start + BYTE * (len(sent) + 20))
    echo, cycles = mcu.take_tx(0)
    assert echo == bytes(b + 1 for b in sent)
    assert cycles[0] - start >= 2 * BYTE  # received after its own byte time, echoed after another
    assert mcu.port1_pending == 0


def test_a_port1_flood_waits_in_the_queue_not_in_a_burst(mcu: AvrSim) -> None:
    flood = bytes(10_000)
    assert mcu.send_port1(flood) == len(flood)
    mcu.run_until(TICK * 100)  # 4,000,000 cycles = 2272 byte times
    assert abs(mcu.port1_fed - TICK * 100 / BYTE) < 60
    frames = frames_of(mcu.take_tx(1)[0])
    assert len(frames) == 98 and [f[1] for f in frames] == list(range(98))  # the 500 Hz output did not suffer


def test_bl_ctrl_slaves_take_one_byte_each_per_tick(mcu: AvrSim) -> None:
    mcu.set_adc_count(1, 800)
    mcu.run_until(TICK * 10 + TICK // 2)
    m = mcu.motors()
    assert m.bytes == (200,) * 4
    assert len(set(m.writes)) == 1 and 9 <= m.writes[0] <= 10
    assert m.last_cycle[0] < m.last_cycle[1] < m.last_cycle[2] < m.last_cycle[3]  # written in MK order
    assert mcu.twi_nacked == 0
    mcu.set_adc_count(1, 4)
    mcu.run_for(TICK)
    assert mcu.motors().bytes == (1,) * 4


def test_pb0_edges_time_the_loop_in_cycles(mcu: AvrSim) -> None:
    mcu.run_until(TICK * 50)
    edges = [e for e in mcu.take_edges() if e.pin == 0]
    rises = [e.cycle for e in edges if e.level == 1]
    falls = [e.cycle for e in edges if e.level == 0 and e.cycle > rises[0]]
    assert len(rises) == 49
    assert {b - a for a, b in zip(rises, rises[1:], strict=False)} == {TICK}
    busy = [f - r for r, f in zip(rises, falls, strict=False)]
    # two ADC conversions of 13 x 128 cycles each, plus the frame and four TWI writes: well inside the tick
    assert all(2 * 13 * 128 < b < TICK for b in busy)


def test_led_pin_follows_the_firmware(mcu: AvrSim) -> None:
    mcu.run_until(TICK)
    assert mcu.portb(1) == 0
    mcu.send_port1(b"\x01")
    mcu.run_for(TICK)
    assert mcu.portb(1) == 1
    led = [e for e in mcu.take_edges() if e.pin == 1]
    assert led[-1].level == 1


def test_eeprom_survives_a_reset_and_can_be_loaded(mcu: AvrSim) -> None:
    mcu.run_until(TICK)
    boot, _ = mcu.take_tx(0)
    assert boot == b"B\x00"  # an erased EEPROM (0xFF) + 1
    assert mcu.eeprom()[0] == 0
    cycle = mcu.cycle
    mcu.reset()
    mcu.run_for(TICK)
    assert mcu.take_tx(0)[0] == b"B\x01"
    assert mcu.cycle > cycle  # the cycle counter never goes back
    image = bytearray(mcu.eeprom())
    assert len(image) == 4096 and image[0] == 1
    image[0] = 41
    mcu.set_eeprom(bytes(image))
    mcu.reset()
    mcu.run_for(TICK)
    assert mcu.take_tx(0)[0] == b"B\x2a"
    assert mcu.eeprom()[0] == 42


def test_the_build_command_prints_the_library() -> None:
    import subprocess
    import sys

    proc = subprocess.run([sys.executable, "-m", "sim_sitl.avr.build"], capture_output=True, text=True, timeout=120,
                          check=False)
    assert proc.returncode == 0, proc.stderr
    assert Path(proc.stdout.strip()) == library_path()

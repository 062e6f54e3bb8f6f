"""The judges of the AVR board (sim_sitl/avr_board.py): the I-stream monitor and the PB0 loop timing, fed with
frames from the real codec (quadlink.mk) at chosen cycles."""

from __future__ import annotations

from quadlink.mk.messages import ImuSample, encode_message
from quadlink.mk.protocol import FrameDecoder
from sim_sitl.avr_board import ImuStreamMonitor, LoopTiming, frames_with_cycles

TICK = 40_000
BYTE = 1760


def stream(samples: list[tuple[int, int]]) -> tuple[bytes, list[int]]:
    """(sample counter, cycle of the frame's last byte) -> the wire's bytes and each byte's cycle."""
    data, cycles = bytearray(), []
    for counter, end in samples:
        frame = encode_message(ImuSample((512, 512, 256), (512, 512, 512), counter))
        data += frame
        cycles += [end - BYTE * (len(frame) - 1 - i) for i in range(len(frame))]
    return bytes(data), cycles


def test_a_perfect_stream_is_500_hz_with_nothing_lost_or_late() -> None:
    mon = ImuStreamMonitor(TICK, 2 * TICK)
    data, cycles = stream([(k % 4096, 50_000 + k * TICK) for k in range(5000)])  # the counter wraps
    for i in range(0, len(data), 97):  # in arbitrary pieces, as chunks cut them
        mon.feed(data[i:i + 97], cycles[i:i + 97])
    s = mon.stats
    assert (s.frames, s.lost, s.late, s.bad_frames) == (5000, 0, 0, 0)
    assert s.max_lag_cycles == 0
    assert s.last_cycle - s.first_cycle == 4999 * TICK


def test_gaps_count_as_lost_and_a_slipping_stream_as_late() -> None:
    mon = ImuStreamMonitor(TICK, 2 * TICK)
    samples = [(k, 50_000 + k * TICK) for k in range(10)] + [(k, 50_000 + k * TICK) for k in range(13, 20)]
    mon.feed(*stream(samples))
    assert mon.stats.lost == 3 and mon.stats.late == 0
    slow = ImuStreamMonitor(TICK, 2 * TICK)  # every sample, but 15 % apart too far: an overrunning loop
    slow.feed(*stream([(k, 50_000 + round(k * TICK * 1.15)) for k in range(100)]))
    assert slow.stats.lost == 0
    assert slow.stats.late > 80
    assert slow.stats.max_lag_cycles == round(99 * TICK * 0.15)


def test_frames_carry_the_cycle_of_their_last_byte() -> None:
    data, cycles = stream([(1, 100_000), (2, 140_000)])
    got = frames_with_cycles(FrameDecoder(), b"junk" + data, [0] * 4 + cycles)
    assert [c for _, c in got] == [100_000, 140_000]


def test_loop_timing_from_pb0_edges() -> None:
    loop = LoopTiming(keep=3)
    for k in range(5):
        loop.on_edge(k * TICK + 100, 1)
        loop.on_edge(k * TICK + 100 + 1000 * (k + 1), 0)
    loop.on_edge(9 * TICK, 0)  # a fall without a rise (reset, start-up) is not a loop
    assert loop.starts == 5
    assert list(loop.busy_cycles) == [3000, 4000, 5000]

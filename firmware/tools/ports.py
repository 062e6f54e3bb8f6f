#!/usr/bin/env python3
"""Summarise the port bytes simbench captured (decoded with quadlink's codec): frame counts, decoder drops, the
IMU counter's continuity, the 'S' history (arm / flight-state changes) and the last 'D'.

    PYTHONPATH=. python3 firmware/tools/ports.py firmware/build/simbench
"""

from __future__ import annotations

import sys
from collections import Counter

from quadlink.mk.messages import BoardStatus, DebugData, ImuSample, Version, decode_message
from quadlink.mk.protocol import FrameDecoder


def main() -> None:
    prefix = sys.argv[1]
    for port in (1, 2):
        data = open(f"{prefix}.port{port}", "rb").read()
        dec = FrameDecoder()
        msgs = [decode_message(f) for f in dec.feed(data)]
        print(f"port {port}: {len(data)} B, frames {dict(Counter(type(m).__name__ for m in msgs))}, "
              f"dropped {dec.stats.frames_dropped}, garbage {dec.stats.garbage_bytes}")
        imu = [m for m in msgs if isinstance(m, ImuSample)]
        if imu:
            gaps = sum(1 for a, b in zip(imu, imu[1:]) if (b.sample_counter - a.sample_counter) % 4096 != 1)
            print(f"  I: {len(imu)} samples, {gaps} counter gaps")
        status = [m for m in msgs if isinstance(m, BoardStatus)]
        if status:
            counts = [m.imu_sample_count for m in status]
            print(f"  S: {len(status)} frames, imu_sample_count {counts[0]} .. {counts[-1]}, "
                  f"{'monotonic (no reset)' if all(b > a for a, b in zip(counts, counts[1:])) else 'NOT monotonic'}")
        last = None
        for m in msgs:
            if isinstance(m, BoardStatus):
                key = (m.armed, m.failsafe, m.flight_state, m.error_flags)
                if key != last:
                    print(f"  S t={m.board_time_ms / 1000:.3f} s armed={m.armed} failsafe={m.failsafe} "
                          f"state={m.flight_state} errors=0x{m.error_flags:x} seq={m.last_setpoint_seq}")
                    last = key
        for m in msgs:
            if isinstance(m, Version):
                print(f"  V {m.version_str} protocol {m.proto_major}.{m.proto_minor} hardware_error {m.hardware_error}")
        debug = [m for m in msgs if isinstance(m, DebugData)]
        if debug:
            a = debug[-1].analog
            print(f"  last D analog[0..15]: {a[:16]}")
            print(f"  busy {a[16] & 0xFFFF} cycles, max {a[17] & 0xFFFF}, port-2 drops {a[18]}, port-1 rx drops "
                  f"{a[19]}, late ticks {a[20]}")


if __name__ == "__main__":
    main()

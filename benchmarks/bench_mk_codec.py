"""Speed of the MK frame codec (quadlink.mk.protocol / quadlink.mk.messages) against a naive reference.

Run: ``.venv/bin/python benchmarks/bench_mk_codec.py [--frames N]``

The reference is the straightforward port of MikroKopter's C code to Python: a per-byte receive state machine
(``uart.c``'s ISR: '#' starts, '\\r' ends, checksum over the buffer) and a per-group ``Decode64`` / ``AddCRC``
loop. Figures are microseconds per frame, measured on an IMU stream (22-byte 'I' frames, the bridge's hot path:
500 frames/s = 11 kB/s) fed in 64-byte chunks like serial reads, and on DebugData frames (66-byte payload).
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from quadlink.mk.messages import DebugData, ImuSample, decode_message, encode_message  # noqa: E402
from quadlink.mk.protocol import Frame, FrameDecoder, encode_frame  # noqa: E402

CHUNK_BYTES = 64
IMU_RATE_HZ = 500


# --- naive reference (per-byte Python, as in the MK firmware)


def naive_encode_frame(address: int, command: str, payload: bytes) -> bytes:
    out = bytearray(b"#")
    out.append(ord("a") + address)
    out.append(ord(command))
    data = bytes(payload) + bytes(-len(payload) % 3)
    for i in range(0, len(data), 3):
        a, b, c = data[i], data[i + 1], data[i + 2]
        out.append(61 + (a >> 2))
        out.append(61 + (((a & 0x03) << 4) | (b >> 4)))
        out.append(61 + (((b & 0x0F) << 2) | (c >> 6)))
        out.append(61 + (c & 0x3F))
    crc = 0
    for byte in out:
        crc += byte
    crc %= 4096
    out.append(61 + crc // 64)
    out.append(61 + crc % 64)
    out.append(13)
    return bytes(out)


class NaiveDecoder:
    """Per-byte state machine like the FlightCtrl receive ISR, with the same drop rules (no stats)."""

    def __init__(self, max_frame_len: int = 220) -> None:
        self.max_frame_len = max_frame_len
        self.buf = bytearray()
        self.in_frame = False

    def feed(self, data: bytes) -> list[Frame]:
        frames = []
        for byte in data:
            if byte == 0x23:  # '#'
                self.buf = bytearray(b"#")
                self.in_frame = True
            elif not self.in_frame:
                continue
            elif byte == 0x0D:  # '\r'
                self.in_frame = False
                frame = self._check(self.buf)
                if frame is not None:
                    frames.append(frame)
            else:
                self.buf.append(byte)
                if len(self.buf) >= self.max_frame_len:
                    self.in_frame = False
        return frames

    @staticmethod
    def _check(buf: bytearray) -> Frame | None:
        n = len(buf)
        if n < 5 or (n - 5) % 4:
            return None
        crc = 0
        for byte in buf[:-2]:
            crc += byte
        crc %= 4096
        if buf[-2] != 61 + crc // 64 or buf[-1] != 61 + crc % 64:
            return None
        payload = bytearray()
        for i in range(3, n - 2, 4):
            a, b, c, d = (x - 61 for x in buf[i : i + 4])
            if min(a, b, c, d) < 0 or max(a, b, c, d) > 63:
                return None
            payload.append((a << 2) | (b >> 4))
            payload.append(((b & 0x0F) << 4) | (c >> 2))
            payload.append(((c & 0x03) << 6) | d)
        return Frame(buf[1] - 0x61, chr(buf[2]), bytes(payload))


# --- measurement


def best_of(fn: Callable[[], object], repeats: int = 5) -> float:
    """Best wall time of ``repeats`` runs, s (the least disturbed by other processes on a shared machine)."""
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def chunks(stream: bytes) -> list[bytes]:
    return [stream[i : i + CHUNK_BYTES] for i in range(0, len(stream), CHUNK_BYTES)]


def decode_all(decoder_cls: Callable[[], FrameDecoder | NaiveDecoder], parts: list[bytes]) -> list[Frame]:
    decoder = decoder_cls()
    out: list[Frame] = []
    for part in parts:
        out += decoder.feed(part)
    return out


def report(label: str, fast_s: float, naive_s: float, n: int) -> None:
    fast_us = fast_s / n * 1e6
    naive_us = naive_s / n * 1e6
    print(
        f"  {label:<34} {fast_us:8.2f} us/frame   naive {naive_us:8.2f} us/frame   speed-up x{naive_us / fast_us:5.1f}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=5000, help="frames per measurement")
    n = parser.parse_args().frames

    imu_msgs = [ImuSample((k % 1024, (3 * k) % 1024, 300), (512, 511, (7 * k) % 1024), k) for k in range(n)]
    imu_payloads = [m.pack() for m in imu_msgs]
    imu_stream = b"".join(encode_frame(1, "I", p) for p in imu_payloads)
    dbg_payload = DebugData((1, 2), tuple(range(-16, 16))).pack()
    dbg_stream = b"".join(encode_frame(1, "D", dbg_payload) for _ in range(n))
    assert imu_stream == b"".join(naive_encode_frame(1, "I", p) for p in imu_payloads)
    imu_parts, dbg_parts = chunks(imu_stream), chunks(dbg_stream)
    assert decode_all(FrameDecoder, imu_parts) == decode_all(NaiveDecoder, imu_parts)

    print(f"MK codec, {n} frames per run, best of 5, Python {sys.version.split()[0]}")
    print("encode")
    report(
        "encode_frame  IMU 'I' (12 B)",
        best_of(lambda: [encode_frame(1, "I", p) for p in imu_payloads]),
        best_of(lambda: [naive_encode_frame(1, "I", p) for p in imu_payloads]),
        n,
    )
    report(
        "encode_frame  DebugData 'D' (66 B)",
        best_of(lambda: [encode_frame(1, "D", dbg_payload) for _ in range(n)]),
        best_of(lambda: [naive_encode_frame(1, "D", dbg_payload) for _ in range(n)]),
        n,
    )
    t_msg = best_of(lambda: [encode_message(m) for m in imu_msgs])
    print(f"  {'encode_message ImuSample (pack+frame)':<34} {t_msg / n * 1e6:8.2f} us/frame")
    print(f"decode ({CHUNK_BYTES}-byte chunks)")
    t_imu = best_of(lambda: decode_all(FrameDecoder, imu_parts))
    report("FrameDecoder  IMU 'I'", t_imu, best_of(lambda: decode_all(NaiveDecoder, imu_parts)), n)
    report(
        "FrameDecoder  DebugData 'D'",
        best_of(lambda: decode_all(FrameDecoder, dbg_parts)),
        best_of(lambda: decode_all(NaiveDecoder, dbg_parts)),
        n,
    )
    t_full = best_of(lambda: [decode_message(f) for f in decode_all(FrameDecoder, imu_parts)])
    print(f"  {'feed + decode_message ImuSample':<34} {t_full / n * 1e6:8.2f} us/frame")
    load = t_full / n * IMU_RATE_HZ
    print(f"IMU port at {IMU_RATE_HZ} Hz: feed + decode_message uses {100 * load:.2f} % of one core")


if __name__ == "__main__":
    main()

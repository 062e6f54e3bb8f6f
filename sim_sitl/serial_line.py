"""A UART transmitter paced at the baud rate (pure; time is an argument).

Frames are queued whole into a TX buffer of ``tx_buffer_bytes``; the wire takes them out at
``baud / bits_per_byte`` bytes per second (115200 8N1 = 11,520 B/s). A frame that does not fit in the
buffer when offered is dropped (as the firmware drops telemetry when its ring is full); a frame whose
first byte leaves more than ``late_after_s`` after it was offered is counted late. :meth:`drain`
returns the bytes that have completely left the wire by a given time, byte by byte, so a reader sees
exactly the arrival times of a real link.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass


@dataclass
class LineStats:
    frames_sent: int = 0
    frames_dropped: int = 0
    frames_late: int = 0
    bytes_sent: int = 0
    bytes_dropped: int = 0
    max_queue_bytes: int = 0


class SerialLine:
    def __init__(self, baud: int = 115200, bits_per_byte: int = 10, tx_buffer_bytes: int = 256,
                 late_after_s: float = 0.004) -> None:
        if baud <= 0 or bits_per_byte <= 0 or tx_buffer_bytes <= 0:
            raise ValueError("baud, bits_per_byte and tx_buffer_bytes must be positive")
        self.bytes_per_s = baud / bits_per_byte
        self.byte_time_s = 1.0 / self.bytes_per_s
        self.tx_buffer_bytes = tx_buffer_bytes
        self.late_after_s = late_after_s
        self.stats = LineStats()
        self._queue: deque[tuple[float, bytes]] = deque()  # (time its first byte starts, frame)
        self._sent_of_head = 0  # bytes of the head frame already drained
        self._wire_free_at_s = 0.0  # when the last queued byte will have left

    def queued_bytes(self, t_s: float) -> int:
        """Bytes still in the TX buffer at ``t_s`` (not yet on the wire)."""
        return max(0, int(round((self._wire_free_at_s - t_s) * self.bytes_per_s)))

    def offer(self, frame: bytes, t_s: float) -> bool:
        """Queue ``frame`` at time ``t_s``; False (and counted) if it does not fit in the TX buffer."""
        queued = self.queued_bytes(t_s)
        if queued + len(frame) > self.tx_buffer_bytes:
            self.stats.frames_dropped += 1
            self.stats.bytes_dropped += len(frame)
            return False
        start = max(t_s, self._wire_free_at_s)
        if start - t_s > self.late_after_s:
            self.stats.frames_late += 1
        self._queue.append((start, bytes(frame)))
        self._wire_free_at_s = start + len(frame) * self.byte_time_s
        self.stats.max_queue_bytes = max(self.stats.max_queue_bytes, queued + len(frame))
        return True

    def drain(self, t_s: float) -> bytes:
        """Bytes whose last bit has left the wire by ``t_s`` (and not returned before)."""
        out = bytearray()
        while self._queue:
            start, frame = self._queue[0]
            done = int((t_s - start) * self.bytes_per_s + 1e-9)
            if done <= self._sent_of_head:
                break
            done = min(done, len(frame))
            out += frame[self._sent_of_head:done]
            if done < len(frame):
                self._sent_of_head = done
                break
            self._queue.popleft()
            self._sent_of_head = 0
            self.stats.frames_sent += 1
        self.stats.bytes_sent += len(out)
        return bytes(out)

    def next_byte_time_s(self) -> float | None:
        """When the next byte will complete (None if idle)."""
        if not self._queue:
            return None
        start, _ = self._queue[0]
        return start + (self._sent_of_head + 1) * self.byte_time_s

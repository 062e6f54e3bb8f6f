"""STATUSTEXT longer than its 50-byte field, as MAVLink 2 chunks it (common.xml: ``id``, ``chunk_seq``).

A text that fits goes out as one message with ``id`` 0 ("the only chunk"). A longer one goes out as chunks of
50 bytes sharing a non-zero ``id``, ``chunk_seq`` counting from 0; the chunk that holds a NUL is the last, so a
text of exactly a multiple of 50 bytes ends with an empty chunk. QGroundControl and MAVSDK put the chunks back
together; a station that does not shows the first 50 bytes, as before.

:class:`StatusTextAssembler` is the receiving side (the ground station and the tests).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from quadlink.mavlink import mavlink

TEXT_BYTES = 50
MAX_CHUNKS = 5       # 250 bytes: longer texts are cut (ours are one or two chunks)


def statustext_messages(severity: int, text: str, chunk_id: int) -> list[Any]:
    """``text`` as STATUSTEXT messages; ``chunk_id`` (1..65535) names a chunked one (unused when it fits)."""
    data = text.replace("\0", "").encode("utf-8", "replace")[:TEXT_BYTES * MAX_CHUNKS]   # a NUL ends a text
    if len(data) <= TEXT_BYTES:
        return [mavlink.MAVLink_statustext_message(severity, data, 0, 0)]
    if not 1 <= chunk_id <= 0xFFFF:
        raise ValueError(f"chunk id {chunk_id} outside 1..65535")
    chunks = [data[i:i + TEXT_BYTES] for i in range(0, len(data), TEXT_BYTES)]
    if len(chunks[-1]) == TEXT_BYTES:
        chunks.append(b"")           # the NUL that ends the text
    return [mavlink.MAVLink_statustext_message(severity, c, chunk_id, seq) for seq, c in enumerate(chunks)]


class ChunkIds:
    """Chunk ids for one sender: 1..65535, then round again (0 means "not chunked")."""

    def __init__(self) -> None:
        self._last = 0

    def next(self) -> int:
        self._last = self._last % 0xFFFF + 1
        return self._last


def _text_of(msg: Any) -> bytes:
    raw = msg.text if isinstance(msg.text, bytes) else str(msg.text).encode("utf-8", "replace")
    return raw.split(b"\0", 1)[0]


@dataclass
class StatusTextAssembler:
    """Reassembles chunked STATUSTEXT per sender and id; :meth:`add` returns a complete text or None.

    A chunk missing from a sequence (lost on the link) gives the text with "..." in its place once the last chunk
    arrives; a sequence whose last chunk never comes is dropped after ``max_pending`` newer ones."""

    max_pending: int = 8
    _pending: dict[tuple[int, int, int], dict[int, bytes]] = field(default_factory=dict)

    def add(self, msg: Any) -> str | None:
        chunk_id = int(getattr(msg, "id", 0) or 0)
        data = _text_of(msg)
        if chunk_id == 0:
            return data.decode("utf-8", "replace")
        key = (msg.get_srcSystem(), msg.get_srcComponent(), chunk_id)
        parts = self._pending.setdefault(key, {})
        parts[int(msg.chunk_seq)] = data
        if len(data) == TEXT_BYTES and int(msg.chunk_seq) < MAX_CHUNKS - 1:
            while len(self._pending) > self.max_pending:
                self._pending.pop(next(iter(self._pending)))
            return None
        del self._pending[key]
        last = max(parts)
        text = b"".join(parts.get(i, b"...") for i in range(last + 1))
        return text.decode("utf-8", "replace")

"""STATUSTEXT over 50 bytes in MAVLink 2 chunks (quadlink/mavlink/statustext.py): packed and parsed by pymavlink
on the wire, reassembled by our assembler; the companion's and the bridge's senders use it (a failsafe's
"..., moving clear" was cut at 50 bytes, so no ground station ever showed it)."""

from __future__ import annotations

from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st

from quadlink.mavlink import mavlink
from quadlink.mavlink.statustext import ChunkIds, StatusTextAssembler, statustext_messages


def _wire(msgs: list[Any], src: tuple[int, int] = (1, 191)) -> list[Any]:
    """Packed by a sender's codec and parsed back by a receiver's (as a ground station reads them)."""
    tx, rx = mavlink.MAVLink(None, *src), mavlink.MAVLink(None, 255, 190)
    out = []
    for m in msgs:
        out.extend(rx.parse_buffer(m.pack(tx)) or [])
    return out


def test_a_short_text_is_one_message_with_id_zero() -> None:
    (m,) = _wire(statustext_messages(mavlink.MAV_SEVERITY_INFO, "Takeoff complete at 0.95 m", 7))
    assert (m.id, m.chunk_seq, m.text) == (0, 0, "Takeoff complete at 0.95 m")
    assert StatusTextAssembler().add(m) == "Takeoff complete at 0.95 m"


def test_the_failsafe_text_reaches_the_ground_station_whole() -> None:
    text = ("companion: no fresh command for 10 s: land refused: object below, 0.52 m tall, moving clear")
    msgs = _wire(statustext_messages(mavlink.MAV_SEVERITY_WARNING, text, 12))
    assert [(m.id, m.chunk_seq) for m in msgs] == [(12, 0), (12, 1)]
    asm = StatusTextAssembler()
    assert [asm.add(m) for m in msgs] == [None, text]


def test_exactly_fifty_bytes_times_two_ends_with_an_empty_chunk() -> None:
    text = "x" * 100
    msgs = _wire(statustext_messages(mavlink.MAV_SEVERITY_INFO, text, 3))
    assert [m.chunk_seq for m in msgs] == [0, 1, 2] and msgs[-1].text == ""
    asm = StatusTextAssembler()
    assert [asm.add(m) for m in msgs][-1] == text


def test_interleaved_senders_and_a_lost_chunk() -> None:
    a = _wire(statustext_messages(4, "a" * 60, 1), src=(1, 191))
    b = _wire(statustext_messages(4, "b" * 120, 1), src=(1, 1))      # same id, another component
    asm = StatusTextAssembler()
    got = [asm.add(m) for m in (a[0], b[0], b[2], a[1])]               # b's middle chunk lost
    assert got == [None, None, "b" * 50 + "..." + "b" * 20, "a" * 60]


def test_chunk_ids_are_never_zero_and_wrap() -> None:
    ids = ChunkIds()
    seen = [ids.next() for _ in range(0x10001)]
    assert min(seen) == 1 and max(seen) == 0xFFFF and seen[0xFFFF] == 1
    with pytest.raises(ValueError):
        statustext_messages(4, "y" * 80, 0)


@given(st.text(alphabet=st.characters(min_codepoint=1, max_codepoint=126), max_size=250))
def test_any_text_round_trips(text: str) -> None:
    msgs = _wire(statustext_messages(mavlink.MAV_SEVERITY_INFO, text, 99))
    asm = StatusTextAssembler()
    results = [asm.add(m) for m in msgs]
    assert results[:-1] == [None] * (len(msgs) - 1)
    assert results[-1] == text


@given(st.text(max_size=300))
def test_any_unicode_text_gives_one_text_at_its_last_chunk(text: str) -> None:
    """A NUL ends a MAVLink text and a chunk edge may split a UTF-8 character: never an exception, never a
    text left pending, at most 250 bytes."""
    msgs = _wire(statustext_messages(mavlink.MAV_SEVERITY_INFO, text, 99))
    asm = StatusTextAssembler()
    results = [asm.add(m) for m in msgs]
    assert results[-1] is not None and not asm._pending
    assert len(msgs) <= 6

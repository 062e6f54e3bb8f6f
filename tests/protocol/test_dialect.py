"""The quadlink MAVLink dialect: ids free in all.xml, custom messages round-trip, module up to date."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from quadlink.mavlink import mavlink
from quadlink.mavlink.generate import OUTPUT, generate

CUSTOM_IDS = {mid for mid in mavlink.mavlink_map if 53000 <= mid < 53010}


def test_custom_ids_do_not_collide_with_all_xml() -> None:
    from pymavlink.dialects.v20 import all as all_dialect

    assert CUSTOM_IDS == {mavlink.MAVLINK_MSG_ID_TELEOP_FEEDBACK, mavlink.MAVLINK_MSG_ID_COMMAND_STAMP}
    assert not CUSTOM_IDS & set(all_dialect.mavlink_map)


def test_dialect_includes_common() -> None:
    from pymavlink.dialects.v20 import common

    assert set(common.mavlink_map) <= set(mavlink.mavlink_map)
    for mid in common.mavlink_map:
        assert mavlink.mavlink_map[mid].crc_extra == common.mavlink_map[mid].crc_extra


finite = st.floats(min_value=-1e6, max_value=1e6, allow_nan=False, width=32)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**64 - 1), st.lists(finite, min_size=17, max_size=17), st.integers(0, 4), st.integers(0, 15))
def test_teleop_feedback_round_trip(time_usec: int, values: list[float], mode: int, flags: int) -> None:
    sender = mavlink.MAVLink(None, srcSystem=1, srcComponent=191)
    packet = sender.teleop_feedback_encode(time_usec, *values, mode, flags).pack(sender)
    assert packet[0] == 0xFD  # MAVLink 2
    receiver = mavlink.MAVLink(None)
    messages = receiver.parse_buffer(packet)
    assert messages is not None and len(messages) == 1
    msg = messages[0]
    assert msg.get_type() == "TELEOP_FEEDBACK" and msg.get_srcComponent() == 191
    names = msg.get_fieldnames()[1:18]
    for name, value in zip(names, values):
        assert math.isclose(getattr(msg, name), value, rel_tol=1e-6, abs_tol=1e-30)
    assert (msg.time_usec, msg.mode, msg.flags) == (time_usec, mode, flags)


def test_corrupt_packet_is_rejected_not_raised() -> None:
    sender = mavlink.MAVLink(None, srcSystem=1, srcComponent=191)
    packet = bytearray(sender.teleop_feedback_encode(1, *([0.5] * 17), 2, 3).pack(sender))
    packet[20] ^= 0xFF
    receiver = mavlink.MAVLink(None)
    receiver.robust_parsing = True
    messages = receiver.parse_buffer(bytes(packet)) or []
    assert all(m.get_type() == "BAD_DATA" for m in messages)


def test_generated_module_is_up_to_date(tmp_path: Path) -> None:
    fresh = generate(tmp_path / "quadlink.py")
    strip = lambda text: [l for l in text.splitlines() if "Generated from:" not in l and "generated on" not in l]
    assert strip(fresh.read_text()) == strip(OUTPUT.read_text()), "run: python -m quadlink.mavlink.generate"


def test_connection_helper_speaks_dialect_over_udp() -> None:
    from quadlink.mavlink.connection import open_mavlink

    receiver = open_mavlink("udpin:127.0.0.1:0", 1, 1)
    port = receiver.port.getsockname()[1]
    sender = open_mavlink(f"udpout:127.0.0.1:{port}", 1, 191)
    try:
        sender.mav.teleop_feedback_send(7, *([0.25] * 16), 1.5, 2, 1)
        msg = receiver.recv_match(type="TELEOP_FEEDBACK", blocking=True, timeout=2.0)
        assert msg is not None and msg.obstacle_distance == pytest.approx(1.5)
    finally:
        sender.close()
        receiver.close()


def test_bad_mavlink_url_is_a_clear_error() -> None:
    from quadlink.errors import LinkError
    from quadlink.mavlink.connection import open_mavlink

    with pytest.raises(LinkError, match="not a MAVLink URL"):
        open_mavlink("http://example")
    with pytest.raises(LinkError, match="cannot open"):
        open_mavlink("/dev/ttyNOSUCH:57600")

"""MAVLink 2 signing and the sender allowlist (issue 16), on pymavlink's real codec."""

from __future__ import annotations

import stat
from pathlib import Path

import pytest
from click.testing import CliRunner

from quadlink.cli import main
from quadlink.errors import ConfigError
from quadlink.mavlink import mavlink
from quadlink.mavlink.security import SenderAllowlist, enable_signing, read_key, signing_stats, write_key

NOW_S = 1_790_000_000.0


def codec(sysid: int, key: bytes | None = None, require: bool = True, t: float = NOW_S) -> mavlink.MAVLink:
    mav = mavlink.MAVLink(None, sysid, 190)
    mav.robust_parsing = True
    if key is not None:
        enable_signing(mav, key, require=require, unix_time_s=t)
    return mav


def heartbeat() -> mavlink.MAVLink_heartbeat_message:
    return mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3)


def received(receiver: mavlink.MAVLink, data: bytes) -> list[str]:
    return [m.get_type() for m in receiver.parse_buffer(data) or []]


def test_key_file_round_trip_and_permissions(tmp_path: Path) -> None:
    path = tmp_path / "keys" / "vehicle.key"
    key = write_key(path)
    assert read_key(path) == key and len(key) == 32
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    with pytest.raises(ConfigError, match="exists"):
        write_key(path)
    (tmp_path / "short.key").write_text("abcd\n")
    with pytest.raises(ConfigError, match="32 bytes"):
        read_key(tmp_path / "short.key")


def test_keygen_command_writes_a_usable_key(tmp_path: Path) -> None:
    result = CliRunner().invoke(main, ["keygen", str(tmp_path / "k")])
    assert result.exit_code == 0, result.output
    assert len(read_key(tmp_path / "k")) == 32


def test_signed_packets_pass_unsigned_and_wrong_key_are_refused() -> None:
    key, other = bytes(range(32)), bytes(32)
    vehicle = codec(1, key, require=True)
    good = _packed(codec(255, key), heartbeat())
    assert received(vehicle, good) == ["HEARTBEAT"]
    assert received(vehicle, _packed(codec(254), heartbeat())) == ["BAD_DATA"]
    assert received(vehicle, _packed(codec(253, other), heartbeat())) == ["BAD_DATA"]
    stats = signing_stats(vehicle)
    assert stats.good == 1 and stats.refused == 2


def test_replayed_packet_is_refused() -> None:
    key = bytes(range(32))
    vehicle, gcs = codec(1, key), codec(255, key)
    first = _packed(gcs, heartbeat())
    assert received(vehicle, first) == ["HEARTBEAT"]
    assert received(vehicle, first) == ["BAD_DATA"]  # same timestamp from the same stream
    assert received(vehicle, _packed(gcs, heartbeat())) == ["HEARTBEAT"]


def test_stream_from_far_in_the_past_is_refused() -> None:
    key = bytes(range(32))
    vehicle = codec(1, key, t=NOW_S)
    recorded = _packed(codec(255, key, t=NOW_S - 3600.0), heartbeat())  # an hour-old capture replayed
    assert received(vehicle, recorded) == ["BAD_DATA"]


def test_unsigned_accepted_when_signing_is_optional() -> None:
    key = bytes(range(32))
    vehicle = codec(1, key, require=False)
    assert received(vehicle, _packed(codec(255), heartbeat())) == ["HEARTBEAT"]


def _packed(mav: mavlink.MAVLink, msg: mavlink.MAVLink_message) -> bytes:
    return bytes(msg.pack(mav))


def _parsed(sender_sysid: int, msg: mavlink.MAVLink_message) -> mavlink.MAVLink_message:
    (out,) = codec(1).parse_buffer(_packed(codec(sender_sysid), msg))
    return out


def test_allowlist_blocks_state_changes_from_unknown_senders_only() -> None:
    disarm = mavlink.MAVLink_command_long_message(1, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 0, 21196,
                                                  0, 0, 0, 0, 0)
    read = mavlink.MAVLink_param_request_list_message(1, 1)
    allow = SenderAllowlist.of([1, 255])
    assert not allow.permits(_parsed(77, disarm))      # the forced disarm from sysid 77
    assert allow.permits(_parsed(255, disarm))
    assert allow.permits(_parsed(77, read))            # reading stays open
    assert not allow.permits(_parsed(77, mavlink.MAVLink_manual_control_message(1, 700, 0, 500, 0, 0)))
    assert SenderAllowlist.of(None).permits(_parsed(77, disarm))
    with pytest.raises(ConfigError):
        SenderAllowlist.of([0])

"""Connect-time services (issue 17): protocol version, empty mission lists, prompt FTP NAKs — decoded back
through pymavlink's real codec, as a ground station would read them."""

from __future__ import annotations

import struct

import pytest

from quadlink.mavlink import mavlink
from quadlink.mavlink.gcs_services import (
    FtpError,
    FtpOpcode,
    handle_ftp,
    handle_mission,
    protocol_version_message,
)


def over_the_wire(msg: mavlink.MAVLink_message, sysid: int = 255, compid: int = 190) -> mavlink.MAVLink_message:
    sender, receiver = mavlink.MAVLink(None, sysid, compid), mavlink.MAVLink(None, 1, 1)
    (out,) = receiver.parse_buffer(bytes(msg.pack(sender)))
    return out


def test_protocol_version_says_mavlink2_and_round_trips() -> None:
    msg = over_the_wire(protocol_version_message(), 1, 1)
    assert msg.get_type() == "PROTOCOL_VERSION"
    assert (msg.version, msg.min_version, msg.max_version) == (200, 200, 200)
    assert len(msg.spec_version_hash) == 8
    assert mavlink.MAVLink_protocol_version_message.crc_extra == 217  # upstream's definition


@pytest.mark.parametrize("mission_type", [mavlink.MAV_MISSION_TYPE_MISSION, mavlink.MAV_MISSION_TYPE_FENCE,
                                          mavlink.MAV_MISSION_TYPE_RALLY])
def test_every_mission_list_is_empty_with_its_type_echoed(mission_type: int) -> None:
    (reply,) = handle_mission(over_the_wire(mavlink.MAVLink_mission_request_list_message(1, 1, mission_type)))
    reply = over_the_wire(reply, 1, 1)
    assert reply.get_type() == "MISSION_COUNT"
    assert (reply.count, reply.mission_type, reply.target_system, reply.target_component) == (0, mission_type, 255,
                                                                                               190)


def test_uploads_are_refused_clears_acknowledged() -> None:
    (up,) = handle_mission(over_the_wire(mavlink.MAVLink_mission_count_message(1, 1, 3, 1)))
    assert (up.type, up.mission_type) == (mavlink.MAV_MISSION_UNSUPPORTED, 1)
    (empty,) = handle_mission(over_the_wire(mavlink.MAVLink_mission_count_message(1, 1, 0, 0)))
    assert empty.type == mavlink.MAV_MISSION_ACCEPTED
    (clear,) = handle_mission(over_the_wire(mavlink.MAVLink_mission_clear_all_message(1, 1, 2)))
    assert (clear.type, clear.mission_type) == (mavlink.MAV_MISSION_ACCEPTED, 2)
    (item,) = handle_mission(over_the_wire(mavlink.MAVLink_mission_request_int_message(1, 1, 0, 0)))
    assert item.type == mavlink.MAV_MISSION_INVALID_SEQUENCE
    assert handle_mission(over_the_wire(mavlink.MAVLink_heartbeat_message(6, 8, 0, 0, 0, 3))) == []


def ftp_request(opcode: int, seq: int = 7, session: int = 0, path: bytes = b"") -> mavlink.MAVLink_message:
    payload = struct.pack("<HBBBBBBI", seq, session, opcode, len(path), 0, 0, 0, 0) + path
    return over_the_wire(mavlink.MAVLink_file_transfer_protocol_message(0, 1, 1, list(payload.ljust(251, b"\0"))))


def decode_reply(msg: mavlink.MAVLink_message) -> tuple[int, int, int, int, bytes]:
    msg = over_the_wire(msg, 1, 1)
    seq, _session, opcode, size, req_opcode, _b, _p, _off = struct.unpack_from("<HBBBBBBI", bytes(msg.payload))
    return seq, opcode, req_opcode, msg.target_component, bytes(msg.payload)[12:12 + size]


def test_ftp_param_download_gets_an_immediate_file_not_found() -> None:
    # what MAVProxy asks first: OpenFileRO "@PARAM/param.pck?withdefaults=1"
    (reply,) = handle_ftp(ftp_request(FtpOpcode.OPEN_FILE_RO, path=b"@PARAM/param.pck?withdefaults=1"), 1, 1)
    seq, opcode, req, target_comp, data = decode_reply(reply)
    assert (seq, opcode, req, target_comp, data) == (8, FtpOpcode.NAK, FtpOpcode.OPEN_FILE_RO, 190,
                                                     bytes([FtpError.FILE_NOT_FOUND]))


def test_ftp_session_resets_are_acked_and_unknown_opcodes_naked() -> None:
    (reset,) = handle_ftp(ftp_request(FtpOpcode.RESET_SESSIONS), 1, 1)
    assert decode_reply(reset)[1] == FtpOpcode.ACK
    (odd,) = handle_ftp(ftp_request(99), 1, 1)
    assert decode_reply(odd)[1:3] == (FtpOpcode.NAK, 99) and decode_reply(odd)[4] == bytes([FtpError.UNKNOWN_COMMAND])
    assert handle_ftp(ftp_request(FtpOpcode.OPEN_FILE_RO), 2, 1) == []  # for another system

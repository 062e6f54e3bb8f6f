"""The small MAVLink services every ground station probes on connect, answered honestly (pure codecs).

* **Protocol version** (MAV_CMD_REQUEST_PROTOCOL_VERSION, MAV_CMD_REQUEST_MESSAGE 300): this stack speaks
  MAVLink 2 only, so PROTOCOL_VERSION says 200 / 200 / 200. Without it QGroundControl stays on MAVLink 1.
* **Mission protocol** for mission, fence and rally (QGroundControl downloads all three on every connect):
  the vehicle has no absolute position and flies no missions, so every list is empty (MISSION_COUNT 0 with
  the requested ``mission_type`` echoed), an upload is refused with MAV_MISSION_UNSUPPORTED (an empty one,
  which is how some clients clear, is accepted), a clear is acknowledged, and an item request is
  MAV_MISSION_INVALID_SEQUENCE (there are no items).
* **MAVLink FTP** (FILE_TRANSFER_PROTOCOL): no file system is served. Every request gets its NAK at once
  (a missing file for opens and listings, an invalid session for reads, an unknown command otherwise;
  sessions reset and terminate are ACKed), so MAVProxy and QGroundControl fall back to the parameter
  protocol immediately instead of timing out.

Each ``handle_*`` function takes the decoded request and returns the messages to send back (addressed to
the requester); the caller owns the link.
"""

from __future__ import annotations

import hashlib
import struct
from dataclasses import dataclass
from typing import Any

from quadlink.mavlink import mavlink

MAVLINK_VERSION = 200


def _hash8(text: str) -> bytes:
    return hashlib.sha1(text.encode()).digest()[:8]


def protocol_version_message(spec: str = "quadlink.xml", library: str = "pymavlink") -> Any:
    """PROTOCOL_VERSION: MAVLink 2 only. The hashes identify the dialect and the library (8 bytes each)."""
    return mavlink.MAVLink_protocol_version_message(MAVLINK_VERSION, MAVLINK_VERSION, MAVLINK_VERSION,
                                                    list(_hash8(spec)), list(_hash8(library)))


# --- mission protocol -------------------------------------------------------------------------------------

MISSION_TYPES = (mavlink.MAV_MISSION_TYPE_MISSION, mavlink.MAV_MISSION_TYPE_FENCE, mavlink.MAV_MISSION_TYPE_RALLY,
                 mavlink.MAV_MISSION_TYPE_ALL)


def handle_mission(msg: Any) -> list[Any]:
    """Replies to one mission-protocol message (see the module doc); [] for anything else."""
    kind = msg.get_type()
    src_sys, src_comp = msg.get_srcSystem(), msg.get_srcComponent()
    mission_type = int(getattr(msg, "mission_type", mavlink.MAV_MISSION_TYPE_MISSION))

    def ack(result: int) -> list[Any]:
        return [mavlink.MAVLink_mission_ack_message(src_sys, src_comp, result, mission_type)]

    if kind == "MISSION_REQUEST_LIST":
        if mission_type not in MISSION_TYPES[:3]:
            return ack(mavlink.MAV_MISSION_INVALID)
        return [mavlink.MAVLink_mission_count_message(src_sys, src_comp, 0, mission_type)]
    if kind == "MISSION_COUNT":
        return ack(mavlink.MAV_MISSION_ACCEPTED if int(msg.count) == 0 else mavlink.MAV_MISSION_UNSUPPORTED)
    if kind == "MISSION_CLEAR_ALL":
        return ack(mavlink.MAV_MISSION_ACCEPTED if mission_type in MISSION_TYPES else mavlink.MAV_MISSION_INVALID)
    if kind in ("MISSION_REQUEST_INT", "MISSION_REQUEST"):
        return ack(mavlink.MAV_MISSION_INVALID_SEQUENCE)
    if kind in ("MISSION_ITEM_INT", "MISSION_ITEM"):
        return ack(mavlink.MAV_MISSION_UNSUPPORTED)
    return []


# --- MAVLink FTP ------------------------------------------------------------------------------------------

class FtpOpcode:
    """MAVLink FTP opcodes (mavlink.io, services/ftp)."""

    NONE = 0
    TERMINATE_SESSION = 1
    RESET_SESSIONS = 2
    LIST_DIRECTORY = 3
    OPEN_FILE_RO = 4
    READ_FILE = 5
    CREATE_FILE = 6
    WRITE_FILE = 7
    REMOVE_FILE = 8
    CREATE_DIRECTORY = 9
    REMOVE_DIRECTORY = 10
    OPEN_FILE_WO = 11
    TRUNCATE_FILE = 12
    RENAME = 13
    CALC_FILE_CRC32 = 14
    BURST_READ_FILE = 15
    ACK = 128
    NAK = 129


class FtpError:
    """MAVLink FTP NAK error codes."""

    FAIL = 1
    INVALID_SESSION = 4
    UNKNOWN_COMMAND = 7
    FILE_PROTECTED = 9
    FILE_NOT_FOUND = 10


#: seq u16, session u8, opcode u8, size u8, req_opcode u8, burst_complete u8, padding u8, offset u32
_FTP_HEADER = struct.Struct("<HBBBBBBI")
FTP_PAYLOAD_BYTES = 251

_NAK_FOR = {
    FtpOpcode.LIST_DIRECTORY: FtpError.FILE_NOT_FOUND,
    FtpOpcode.OPEN_FILE_RO: FtpError.FILE_NOT_FOUND,
    FtpOpcode.CALC_FILE_CRC32: FtpError.FILE_NOT_FOUND,
    FtpOpcode.REMOVE_FILE: FtpError.FILE_NOT_FOUND,
    FtpOpcode.REMOVE_DIRECTORY: FtpError.FILE_NOT_FOUND,
    FtpOpcode.RENAME: FtpError.FILE_NOT_FOUND,
    FtpOpcode.TRUNCATE_FILE: FtpError.FILE_NOT_FOUND,
    FtpOpcode.READ_FILE: FtpError.INVALID_SESSION,
    FtpOpcode.BURST_READ_FILE: FtpError.INVALID_SESSION,
    FtpOpcode.WRITE_FILE: FtpError.INVALID_SESSION,
    FtpOpcode.CREATE_FILE: FtpError.FILE_PROTECTED,
    FtpOpcode.OPEN_FILE_WO: FtpError.FILE_PROTECTED,
    FtpOpcode.CREATE_DIRECTORY: FtpError.FILE_PROTECTED,
}


@dataclass(frozen=True)
class FtpHeader:
    seq: int
    session: int
    opcode: int
    size: int
    req_opcode: int
    offset: int

    @classmethod
    def unpack(cls, payload: bytes) -> FtpHeader:
        seq, session, opcode, size, req_opcode, _burst, _pad, offset = _FTP_HEADER.unpack_from(payload)
        return cls(seq, session, opcode, size, req_opcode, offset)


def ftp_reply_payload(request: FtpHeader, opcode: int, data: bytes = b"") -> list[int]:
    head = _FTP_HEADER.pack((request.seq + 1) & 0xFFFF, request.session, opcode, len(data), request.opcode, 0, 0,
                            request.offset)
    body = head + data
    return list(body + bytes(FTP_PAYLOAD_BYTES - len(body)))


def handle_ftp(msg: Any, own_system: int, own_component: int) -> list[Any]:
    """The ACK or NAK for one FILE_TRANSFER_PROTOCOL request addressed to us; [] if not ours or malformed."""
    if msg.get_type() != "FILE_TRANSFER_PROTOCOL":
        return []
    if msg.target_system not in (0, own_system) or msg.target_component not in (0, own_component):
        return []
    payload = bytes(msg.payload)
    if len(payload) < _FTP_HEADER.size:
        return []
    request = FtpHeader.unpack(payload)
    if request.opcode in (FtpOpcode.ACK, FtpOpcode.NAK):
        return []  # a reply, not a request
    if request.opcode in (FtpOpcode.TERMINATE_SESSION, FtpOpcode.RESET_SESSIONS, FtpOpcode.NONE):
        reply = ftp_reply_payload(request, FtpOpcode.ACK)
    else:
        error = _NAK_FOR.get(request.opcode, FtpError.UNKNOWN_COMMAND)
        reply = ftp_reply_payload(request, FtpOpcode.NAK, bytes([error]))
    return [mavlink.MAVLink_file_transfer_protocol_message(0, msg.get_srcSystem(), msg.get_srcComponent(), reply)]

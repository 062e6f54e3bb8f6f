"""The companion's autopilot-link reader: the HIGHRES_IMU fast path decodes exactly what the codec does and
leaves everything else (bad CRC, signed frames, other messages, partial and joined chunks) to the codec."""

from __future__ import annotations

import math

import pytest

from companion.link_reader import CodecReader, decode_highres_imu_v2
from quadlink.mavlink import mavlink


def _imu(time_usec: int = 123_456_789, gyro_z: float = 0.3, temperature: float = 20.0, seq: int = 7,
         **extra: float) -> bytes:
    enc = mavlink.MAVLink(None, srcSystem=3, srcComponent=1)
    enc.seq = seq
    fields = dict(xacc=0.1, yacc=-0.2, zacc=-9.81, xgyro=0.01, ygyro=-0.02, zgyro=gyro_z, xmag=0.0, ymag=0.0,
                  zmag=0.0, abs_pressure=0.0, diff_pressure=0.0, pressure_alt=0.0, temperature=temperature,
                  fields_updated=0x3F, id=0)
    fields.update(extra)
    return bytes(mavlink.MAVLink_highres_imu_message(time_usec, *fields.values()).pack(enc))


class _ChunkLink:
    """A link whose ``recv`` hands out the given byte chunks in order."""

    def __init__(self, chunks: list[bytes]) -> None:
        self.chunks = list(chunks)

    def recv(self, n: int = 0) -> bytes:
        return self.chunks.pop(0) if self.chunks else b""

    def write(self, buf: bytes) -> int:
        return len(buf)

    def close(self) -> None:
        pass


def test_fast_path_matches_the_codec_field_for_field() -> None:
    for buf in (_imu(), _imu(time_usec=2**63 - 5, gyro_z=-1.25, seq=255), _imu(temperature=0.0, id=0)):
        fast = decode_highres_imu_v2(buf)
        ref = mavlink.MAVLink(None).parse_buffer(buf)[0]
        assert fast is not None
        assert fast.to_dict() == ref.to_dict()
        assert fast.get_msgbuf() == ref.get_msgbuf()
        assert vars(fast.get_header()) == vars(ref.get_header())
        assert fast.get_type() == "HIGHRES_IMU" and fast.get_srcSystem() == 3 and fast.get_crc() == ref.get_crc()


def test_trailing_zero_truncation_is_undone() -> None:
    buf = _imu(temperature=0.0)   # MAVLink 2 trims the zero tail: temperature, fields... stay
    assert buf[1] < mavlink.MAVLink_highres_imu_message.unpacker.size
    msg = decode_highres_imu_v2(buf)
    assert msg is not None and msg.temperature == 0.0 and msg.id == 0 and math.isclose(msg.zacc, -9.81, rel_tol=1e-6)


def test_other_input_is_left_to_the_codec() -> None:
    good = _imu()
    bad_crc = good[:-1] + bytes([good[-1] ^ 0x55])
    assert decode_highres_imu_v2(bad_crc) is None
    assert decode_highres_imu_v2(good + good) is None          # two frames in one chunk
    assert decode_highres_imu_v2(good[:-3]) is None            # cut short
    signed = bytearray(good)
    signed[2] = mavlink.MAVLINK_IFLAG_SIGNED
    assert decode_highres_imu_v2(bytes(signed)) is None
    hb = mavlink.MAVLink_heartbeat_message(2, 12, 0, 0, 3, 3).pack(mavlink.MAVLink(None, 1, 1))
    assert decode_highres_imu_v2(bytes(hb)) is None
    assert decode_highres_imu_v2(b"") is None and decode_highres_imu_v2(b"\xfd\x00") is None


def test_reader_decodes_every_kind_of_chunk_in_order() -> None:
    a, b, c = _imu(seq=1, gyro_z=0.1), _imu(seq=2, gyro_z=0.2), _imu(seq=3, gyro_z=0.3)
    hb = bytes(mavlink.MAVLink_heartbeat_message(2, 12, 0, 0, 3, 3).pack(mavlink.MAVLink(None, 1, 1)))
    bad = a[:-1] + bytes([a[-1] ^ 0xFF])
    # whole datagrams, a partial frame split over two reads (must not take the fast path on its tail),
    # two frames joined, a corrupt one, then a good one again
    link = _ChunkLink([a, b[:20], b[20:], hb + c, bad, c])
    reader = CodecReader(link)
    got = []
    while (m := reader.recv_msg()) is not None:
        got.append(m)
    kinds = [m.get_type() for m in got]
    assert kinds == ["HIGHRES_IMU", "HIGHRES_IMU", "HEARTBEAT", "HIGHRES_IMU", "BAD_DATA", "HIGHRES_IMU"]
    assert [round(m.zgyro, 3) for m in got if m.get_type() == "HIGHRES_IMU"] == [0.1, 0.2, 0.3, 0.3]
    assert reader.fast_decoded == 2   # the first and the last datagram


@pytest.mark.parametrize("payload_len", [0, 1, 63, 255])
def test_wrong_length_field_is_rejected(payload_len: int) -> None:
    good = bytearray(_imu())
    good[1] = payload_len
    assert decode_highres_imu_v2(bytes(good)) is None

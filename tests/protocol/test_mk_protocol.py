"""MK frame codec: golden vectors from MK_PROTOCOL.md, real captured frames, property tests of the stream decoder."""

from __future__ import annotations

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from quadlink.errors import ProtocolError
from quadlink.mk.protocol import (
    ADDR_ANY,
    ADDR_FC,
    ADDR_MAX,
    DEFAULT_MAX_FRAME_LEN,
    Frame,
    FrameDecoder,
    checksum_chars,
    decode_frame,
    encode_frame,
    mk_b64decode,
    mk_b64encode,
)

# (address, command, payload, frame) from /work/shared/MK_PROTOCOL.md "Vectors"
VECTORS = [
    (1, "v", b"", b"#bv@x\r"),
    (2, "v", b"", b"#cv@y\r"),
    (1, "d", bytes.fromhex("0a"), b"#bd?]==D|\r"),
    (1, "b", bytes.fromhex("00000005fb007800000701"), b"#bb====>\\i=[===>mA=RS\r"),
    (0, "V", bytes.fromhex("00540b00030000000000"), b"#aV=BMH==I=========PS\r"),
]

# Frames captured by a public ground-station project's tests (MK_PROTOCOL.md), '\r' added.
CAPTURED_OK = [
    (b"#av@w\r", 0, "v", b""),
    (b"#bV=BMH============PH\r", 1, "V", bytes([0, 84, 11]) + bytes(9)),  # FC 0.84a, protocol 11
    (b"#cV=>]H==A=========PY\r", 2, "V", bytes([0, 24, 11, 0, 1]) + bytes(7)),  # NC 0.24b
]
CAPTURED_BAD_CHECKSUM = b"#cV=>]H==Ac========PY\r"


def padded(payload: bytes) -> bytes:
    """What the decoder returns for ``payload``: whole 3-byte groups, zero padded."""
    return payload + bytes(-len(payload) % 3)


def reference_b64(payload: bytes) -> bytes:
    """The encoding written out exactly as MK_PROTOCOL.md states it (the oracle for the fast codec)."""
    data = padded(payload)
    out = bytearray()
    for i in range(0, len(data), 3):
        a, b, c = data[i : i + 3]
        out += bytes(
            (
                61 + (a >> 2),
                61 + (((a & 0x03) << 4) | (b >> 4)),
                61 + (((b & 0x0F) << 2) | (c >> 6)),
                61 + (c & 0x3F),
            )
        )
    return bytes(out)


def reference_frame(address: int, command: str, payload: bytes) -> bytes:
    head = b"#" + bytes((ord("a") + address, ord(command))) + reference_b64(payload)
    crc = sum(head) % 4096
    return head + bytes((61 + crc // 64, 61 + crc % 64)) + b"\r"


def raw_frame(address_char: int, command_char: int, chars: bytes) -> bytes:
    """A frame with arbitrary (possibly invalid) content but a correct checksum."""
    head = bytes((0x23, address_char, command_char)) + chars
    return head + checksum_chars(head) + b"\r"


frames_st = st.builds(
    Frame,
    address=st.integers(0, ADDR_MAX),
    command=st.sampled_from("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ"),
    payload=st.binary(max_size=60).map(padded),
)


# --- vectors


@pytest.mark.parametrize("address,command,payload,frame", VECTORS)
def test_vectors_encode(address: int, command: str, payload: bytes, frame: bytes) -> None:
    assert encode_frame(address, command, payload) == frame


@pytest.mark.parametrize("address,command,payload,frame", VECTORS)
def test_vectors_decode(address: int, command: str, payload: bytes, frame: bytes) -> None:
    decoder = FrameDecoder()
    assert decoder.feed(frame) == [Frame(address, command, padded(payload))]
    assert decode_frame(frame) == Frame(address, command, padded(payload))
    assert decoder.stats.frames_ok == 1 and decoder.stats.frames_dropped == 0


@pytest.mark.parametrize("wire,address,command,payload", CAPTURED_OK)
def test_captured_frames_decode(wire: bytes, address: int, command: str, payload: bytes) -> None:
    decoder = FrameDecoder()
    assert decoder.feed(wire) == [Frame(address, command, payload)]
    # re-encoding the decoded frame reproduces the captured bytes exactly
    assert encode_frame(address, command, payload) == wire


def test_captured_bad_checksum_is_rejected() -> None:
    decoder = FrameDecoder()
    assert decoder.feed(CAPTURED_BAD_CHECKSUM) == []
    assert decoder.stats.bad_checksum == 1
    assert decoder.stats.frames_ok == 0
    assert decoder.stats.dropped_bytes == len(CAPTURED_BAD_CHECKSUM)
    with pytest.raises(ProtocolError, match="bad_checksum"):
        decode_frame(CAPTURED_BAD_CHECKSUM)
    # the good frames around it still come through
    good = [w for w, *_ in CAPTURED_OK]
    stream = good[0] + CAPTURED_BAD_CHECKSUM + good[1] + good[2]
    decoder = FrameDecoder()
    assert [f.encode() for f in decoder.feed(stream)] == good
    assert decoder.stats.bad_checksum == 1


def test_version_request_all_addresses_match_reference() -> None:
    for address in range(ADDR_MAX + 1):
        assert encode_frame(address, "v", b"") == reference_frame(address, "v", b"")


# --- base64


@settings(deadline=None)
@given(st.binary(max_size=200))
def test_b64_matches_spec_formula_and_round_trips(payload: bytes) -> None:
    chars = mk_b64encode(payload)
    assert chars == reference_b64(payload)
    assert len(chars) == 4 * ((len(payload) + 2) // 3)
    assert all(61 <= c <= 124 for c in chars)
    assert mk_b64decode(chars) == padded(payload)


def test_b64_groups() -> None:
    assert mk_b64encode(b"") == b""
    assert mk_b64encode(b"\x00") == b"===="
    assert mk_b64encode(b"\xff\xff\xff") == b"||||"
    assert mk_b64decode(b"||||") == b"\xff\xff\xff"


@pytest.mark.parametrize("chars", [b"===", b"=====", b"===~", b"==#=", b"<==="])
def test_b64_decode_rejects_bad_input(chars: bytes) -> None:
    with pytest.raises(ProtocolError):
        mk_b64decode(chars)


@settings(deadline=None)
@given(frames_st)
def test_encode_frame_matches_reference(frame: Frame) -> None:
    wire = encode_frame(frame.address, frame.command, frame.payload)
    assert wire == reference_frame(frame.address, frame.command, frame.payload)
    assert wire.count(b"#") == 1 and wire.count(b"\r") == 1
    assert decode_frame(wire) == frame


# --- encode misuse


@pytest.mark.parametrize("address", [-1, ADDR_MAX + 1, 97, True, 1.0, "b", None])
def test_encode_rejects_bad_address(address: object) -> None:
    with pytest.raises(ProtocolError, match="address"):
        encode_frame(address, "v", b"")  # type: ignore[arg-type]


@pytest.mark.parametrize("command", ["", "vv", "1", "#", "=", "\r", "é", "Ω", b"v", 118, None])
def test_encode_rejects_bad_command(command: object) -> None:
    with pytest.raises(ProtocolError, match="command"):
        encode_frame(ADDR_FC, command, b"")  # type: ignore[arg-type]


def test_encode_rejects_bad_payload_and_oversize() -> None:
    with pytest.raises(ProtocolError, match="bytes"):
        encode_frame(ADDR_FC, "v", "text")  # type: ignore[arg-type]
    # 159 payload bytes = 53 groups = 218-byte frame: the largest that fits the 220-byte receive buffer
    assert len(encode_frame(ADDR_FC, "D", bytes(159))) == 218
    with pytest.raises(ProtocolError, match="220"):
        encode_frame(ADDR_FC, "D", bytes(160))
    assert encode_frame(ADDR_FC, "v", bytearray(b"\x01")) == encode_frame(ADDR_FC, "v", b"\x01")


# --- stream


def assert_accounted(decoder: FrameDecoder, frames: list[Frame], fed: int) -> None:
    """Every byte fed is garbage, part of a dropped frame, part of a returned frame, or pending."""
    s = decoder.stats
    ok_bytes = sum(len(f.encode()) for f in frames)
    assert s.garbage_bytes + s.dropped_bytes + ok_bytes + decoder.pending_bytes == fed
    assert s.frames_ok == len(frames)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(frames_st, max_size=12), st.data())
def test_stream_random_chunking(frames: list[Frame], data: st.DataObject) -> None:
    stream = b"".join(f.encode() for f in frames)
    cuts = sorted(data.draw(st.lists(st.integers(0, len(stream)), max_size=20)))
    decoder = FrameDecoder()
    out: list[Frame] = []
    for a, b in zip([0, *cuts], [*cuts, len(stream)]):
        out += decoder.feed(stream[a:b])
    assert out == frames
    assert decoder.stats.frames_dropped == 0 and decoder.stats.garbage_bytes == 0
    assert decoder.pending_bytes == 0
    assert_accounted(decoder, out, len(stream))


@pytest.mark.parametrize("address,command,payload,frame", VECTORS)
def test_split_at_every_byte(address: int, command: str, payload: bytes, frame: bytes) -> None:
    for cut in range(len(frame) + 1):
        decoder = FrameDecoder()
        first = decoder.feed(frame[:cut])
        second = decoder.feed(frame[cut:])
        assert first + second == [Frame(address, command, padded(payload))]
        assert (first == []) == (cut < len(frame))


def test_byte_by_byte_stream() -> None:
    stream = b"".join(v[3] for v in VECTORS) * 3
    decoder = FrameDecoder()
    out = [f for i in range(len(stream)) for f in decoder.feed(stream[i : i + 1])]
    assert [f.encode() for f in out] == [v[3] for v in VECTORS] * 3


garbage_st = st.lists(st.sampled_from([b"#", b"\r", b"=", b"a", b"\x00", b"\xff", b"|"]) | st.binary(max_size=8)).map(
    b"".join
)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.tuples(garbage_st, frames_st), max_size=10), garbage_st, st.data())
def test_garbage_between_frames(pairs: list[tuple[bytes, Frame]], tail: bytes, data: st.DataObject) -> None:
    stream = b"".join(g + f.encode() for g, f in pairs) + tail
    cuts = sorted(data.draw(st.lists(st.integers(0, len(stream)), max_size=10)))
    decoder = FrameDecoder()
    out: list[Frame] = []
    for a, b in zip([0, *cuts], [*cuts, len(stream)]):
        out += decoder.feed(stream[a:b])  # must never raise
    expected = [f for _, f in pairs]
    # every valid frame is found, in order (garbage could, in principle, hold extra valid frames)
    it = iter(out)
    assert all(any(got == want for got in it) for want in expected)
    if all(b"#" not in g for g, _ in pairs):
        assert out == expected
    assert_accounted(decoder, out, len(stream))


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=600), st.integers(6, 300))
def test_feed_never_raises(noise: bytes, max_len: int) -> None:
    decoder = FrameDecoder(max_frame_len=max_len)
    out = decoder.feed(noise) + decoder.feed(noise[::-1])
    assert_accounted(decoder, out, 2 * len(noise))
    # and the decoder still works afterwards: a frame after a '\r' (ends any overlong run) and a '#' resync
    after = decoder.feed(b"\r" + VECTORS[0][3])
    assert after == [Frame(1, "v", b"")]


def test_feed_accepts_bytearray_and_memoryview() -> None:
    decoder = FrameDecoder()
    assert decoder.feed(bytearray(VECTORS[0][3])) == [Frame(1, "v", b"")]
    assert decoder.feed(memoryview(VECTORS[1][3])) == [Frame(2, "v", b"")]


def test_truncated_frame_resyncs_on_hash() -> None:
    good = VECTORS[2][3]
    decoder = FrameDecoder()
    out = decoder.feed(good[:5] + good + b"xyz" + good)
    assert out == [Frame(1, "d", b"\x0a\x00\x00")] * 2
    s = decoder.stats
    assert (s.truncated, s.garbage_bytes, s.dropped_bytes) == (1, 3, 5)


# --- limits


def test_overlong_frames() -> None:
    longest = encode_frame(ADDR_FC, "D", bytes(range(159)))  # 218 bytes: fits the default 220
    assert len(longest) == 218
    assert FrameDecoder().feed(longest) == [decode_frame(longest)]

    tight = FrameDecoder(max_frame_len=217)
    follow = VECTORS[0][3]
    assert tight.feed(longest + follow) == [Frame(1, "v", b"")]
    assert tight.stats.overlong == 1 and tight.stats.dropped_bytes == len(longest)

    exact = FrameDecoder(max_frame_len=218)
    assert len(exact.feed(longest)) == 1

    # a frame longer than the buffer (built by hand: encode_frame refuses it) and a never-ending one
    huge = raw_frame(ord("b"), ord("D"), mk_b64encode(bytes(300)))
    decoder = FrameDecoder()
    assert decoder.feed(huge + follow) == [Frame(1, "v", b"")]
    assert decoder.stats.overlong == 1
    assert FrameDecoder(max_frame_len=600).feed(huge) == [Frame(1, "D", bytes(300))]


def test_overlong_across_feeds_then_recovers() -> None:
    decoder = FrameDecoder()
    fed = 0
    out: list[Frame] = []
    for chunk in [b"#bD", b"=" * 150, b"=" * 150, b"=" * 150, b"\r", b"junk", VECTORS[0][3]]:
        out += decoder.feed(chunk)
        fed += len(chunk)
    assert out == [Frame(1, "v", b"")]
    s = decoder.stats
    assert (s.overlong, s.garbage_bytes, s.frames_ok) == (1, 4, 1)
    assert_accounted(decoder, out, fed)
    # an overlong run ended by a '#' instead of '\r'
    decoder = FrameDecoder()
    out = decoder.feed(b"#" + b"A" * 500) + decoder.feed(b"B" * 100 + VECTORS[1][3])
    assert out == [Frame(2, "v", b"")] and decoder.stats.overlong == 1
    assert_accounted(decoder, out, 601 + len(VECTORS[1][3]))


def test_default_max_frame_len_is_flightctrl_buffer() -> None:
    assert DEFAULT_MAX_FRAME_LEN == 220
    assert FrameDecoder().max_frame_len == 220
    with pytest.raises(ProtocolError):
        FrameDecoder(max_frame_len=5)


@pytest.mark.parametrize(
    "wire,counter",
    [
        (raw_frame(ord("b"), ord("D"), b"=~=="), "invalid_chars"),  # data char above '|'
        (raw_frame(ord("b"), ord("D"), b"=<=="), "invalid_chars"),  # data char below '='
        (raw_frame(ord("b"), ord("D"), b"====\x00\x00\x00\x00"), "invalid_chars"),
        (raw_frame(ord("{"), ord("v"), b""), "invalid_chars"),  # address beyond 'z'
        (raw_frame(ord("A"), ord("v"), b""), "invalid_chars"),  # address below 'a'
        (raw_frame(ord("b"), ord("1"), b""), "invalid_chars"),  # command not a letter
        (raw_frame(ord("b"), ord("="), b""), "invalid_chars"),
        (b"#bv@\x01\r", "invalid_chars"),  # checksum char out of range
        (raw_frame(ord("b"), ord("D"), b"==="), "malformed"),  # not whole groups
        (raw_frame(ord("b"), ord("D"), b"====="), "malformed"),
        (b"#bv@\r", "malformed"),  # too short
        (b"#\r", "malformed"),
        (b"#bv@y\r", "bad_checksum"),
        (b"#bd?]==D}\r", "invalid_chars"),
        (b"#bd?]==D{\r", "bad_checksum"),
    ],
)
def test_rejected_frames_counted(wire: bytes, counter: str) -> None:
    decoder = FrameDecoder()
    follow = VECTORS[3][3]
    out = decoder.feed(wire + follow)
    assert out == [decode_frame(follow)]
    stats = decoder.stats.as_dict()
    assert stats[counter] == 1
    assert decoder.stats.frames_dropped == 1
    assert stats["dropped_bytes"] == len(wire)
    with pytest.raises(ProtocolError, match=counter):
        decode_frame(wire)


def test_constants() -> None:
    assert (ADDR_ANY, ADDR_FC) == (0, 1)
    assert encode_frame(ADDR_FC, "v")[1:2] == b"b"

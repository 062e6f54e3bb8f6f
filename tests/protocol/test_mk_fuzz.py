"""Property tests: the MK stream decoder and message dispatch survive any bytes, in any chunking.

Properties: ``FrameDecoder.feed`` and ``decode_message`` never raise; the decoder's buffer stays bounded;
valid frames hidden in garbage are all found, in order, with their typed messages intact; every decoded
message re-encodes to a frame that decodes to the same message.
Marked ``fuzz``; budget: ``QUADLINK_FUZZ_EXAMPLES`` (``scripts/fuzz.sh`` soaks).
"""

from __future__ import annotations

import math

import pytest
from fuzzing import FUZZ
from hypothesis import given
from hypothesis import strategies as st

from quadlink.mk.messages import MESSAGE_TYPES, AttitudeSetpoint, BoardStatus, ImuSample, decode_message, encode_message
from quadlink.mk.protocol import DEFAULT_MAX_FRAME_LEN, Frame, FrameDecoder

_letters = st.sampled_from(sorted(MESSAGE_TYPES) + ["x", "Z"])
_hostile_bytes = st.one_of(st.binary(max_size=400),
                           st.lists(st.sampled_from([b"#", b"\r", b"#a", b"=", b"|", b"\x00", b"\xff", b"#aS===\r"]),
                                    max_size=60).map(b"".join))

pytestmark = pytest.mark.fuzz


def _chunks(data: bytes, cuts: list[int]) -> list[bytes]:
    points = sorted({min(c, len(data)) for c in cuts})
    out, last = [], 0
    for p in points + [len(data)]:
        out.append(data[last:p])
        last = p
    return out


@FUZZ
@given(_hostile_bytes, st.lists(st.integers(0, 400), max_size=8))
def test_decoder_never_raises_and_stays_bounded(data, cuts):
    decoder = FrameDecoder()
    for chunk in _chunks(data, cuts):
        for frame in decoder.feed(chunk):
            assert isinstance(frame, Frame)
            decoded = decode_message(frame)  # None or a typed message, never an exception
            assert decoded is None or type(decoded) is MESSAGE_TYPES[frame.command]
        assert decoder.pending_bytes <= DEFAULT_MAX_FRAME_LEN


_finite = st.floats(-10.0, 10.0, allow_nan=False)
_messages = st.one_of(
    st.builds(AttitudeSetpoint, _finite, _finite, _finite, st.floats(0.0, 1.0), st.booleans(), st.integers(0, 255)),
    st.builds(BoardStatus, st.booleans(), st.integers(0, 2), st.booleans(), st.integers(0, 65535),
              st.integers(0, 0xFFFF), st.integers(0, 2**32 - 1), st.integers(0, 2**32 - 1), st.integers(0, 255)),
    st.builds(ImuSample, st.tuples(*[st.integers(0, 1023)] * 3), st.tuples(*[st.integers(0, 1023)] * 3),
              st.integers(0, 4095)),
)


@FUZZ
@given(st.lists(st.tuples(_hostile_bytes, _messages), max_size=6), st.lists(st.integers(0, 3000), max_size=10))
def test_valid_frames_in_garbage_are_all_found(pairs, cuts):
    # garbage ends with '\r' so it can not swallow the next frame's start (a torn frame is dropped, by design)
    stream = b"".join(junk.replace(b"#", b"") + b"\r" + encode_message(m) for junk, m in pairs)
    decoder = FrameDecoder()
    got = [decode_message(f) for chunk in _chunks(stream, cuts) for f in decoder.feed(chunk)]
    expected = [m for _, m in pairs]
    assert len(got) == len(expected)
    for g, m in zip(got, expected, strict=True):
        assert type(g) is type(m)
        # the wire quantizes (0.01 deg, thrust / 65535): one more round trip is exact
        assert decode_message(next(iter(FrameDecoder().feed(encode_message(g))))) == g
        if isinstance(m, AttitudeSetpoint):
            assert isinstance(g, AttitudeSetpoint) and math.isclose(g.thrust, m.thrust, abs_tol=1e-4)
        else:
            assert g == m

"""Shared helpers of the property (fuzz) tests: example budget and MAVLink message strategies.

CI runs a bounded number of examples (the ``quadlink`` hypothesis profile of ``tests/conftest.py``); a soak
is one command: ``QUADLINK_FUZZ_EXAMPLES=20000 scripts/fuzz.sh -k "bridge or mk"``.

Messages are generated from pymavlink's own field tables (types, array lengths), packed by a real codec
and parsed back, so a handler sees exactly what the wire can carry.
"""

from __future__ import annotations

from typing import Any

from hypothesis import settings
from hypothesis import strategies as st

from quadlink.mavlink import mavlink

# the example count comes from the "quadlink" hypothesis profile (tests/conftest.py, QUADLINK_FUZZ_EXAMPLES);
# small CI runs are derandomized so a failure reproduces, soaks explore
FUZZ = settings(derandomize=settings.default.max_examples <= 500)

_INT_RANGES = {"int8_t": (-2**7, 2**7 - 1), "uint8_t": (0, 2**8 - 1), "int16_t": (-2**15, 2**15 - 1),
               "uint16_t": (0, 2**16 - 1), "int32_t": (-2**31, 2**31 - 1), "uint32_t": (0, 2**32 - 1),
               "int64_t": (-2**63, 2**63 - 1), "uint64_t": (0, 2**64 - 1)}

# floats a hostile sender picks: specials, huge, tiny, and ordinary values
hostile_floats = st.one_of(
    st.sampled_from([0.0, -0.0, 1.0, -1.0, float("nan"), float("inf"), float("-inf"), 3.4e38, -3.4e38, 1e-40,
                     21196.0, 0.5]),
    st.floats(width=32, allow_nan=True, allow_infinity=True))


def _field(ftype: str, length: int, name: str, overrides: dict[str, Any]) -> st.SearchStrategy[Any]:
    if name in overrides:
        return overrides[name]
    if ftype == "char":
        return st.text(alphabet=st.characters(min_codepoint=32, max_codepoint=126), max_size=length or 1)
    if ftype in ("float", "double"):
        one = hostile_floats
    else:
        lo, hi = _INT_RANGES[ftype]
        one = st.one_of(st.sampled_from([lo, hi, 0, 1]), st.integers(lo, hi))
    if length:
        return st.lists(one, min_size=length, max_size=length)
    return one


def message_strategy(cls: type, **overrides: st.SearchStrategy[Any]) -> st.SearchStrategy[Any]:
    """A strategy for instances of pymavlink message class ``cls`` (fields by name can be overridden)."""
    lengths = dict(zip(cls.ordered_fieldnames, cls.array_lengths, strict=True))
    fields = [_field(ftype, lengths[name], name, overrides) for name, ftype in zip(cls.fieldnames, cls.fieldtypes,
                                                                                   strict=True)]
    return st.tuples(*fields).map(lambda values: cls(*values))


def over_the_wire(codec: Any, message: Any) -> Any:
    """``message`` packed by ``codec`` and parsed back (what a receiver gets), or None if it cannot pack."""
    try:
        data = message.pack(codec)
    except Exception:  # noqa: BLE001 - struct.error, OverflowError, ...: the sender could not send it either
        return None
    return mavlink.MAVLink(None, 0, 0).decode(bytearray(data))

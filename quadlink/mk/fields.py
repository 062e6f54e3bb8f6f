"""Field encodings shared by the MK message structs: LSB scalings, integer ranges, saturation and checks.

``pack`` never raises on a finite out-of-range value (it saturates); a NaN or infinite float raises
``ProtocolError`` (see :mod:`quadlink.mk.messages` for the conventions).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import ClassVar, Protocol

import numpy as np

from quadlink.errors import ProtocolError

DECIDEG_RAD = math.radians(0.1)  # one LSB of a 0.1-degree angle, rad
CENTIDEG_RAD = math.radians(0.01)  # one LSB of a 0.01-degree angle, rad
DECIDEG_S_RAD_S = math.radians(0.1)  # one LSB of a 0.1 deg/s rate, rad/s
THRUST_FULL_SCALE = 65535  # uint16 thrust count for fraction 1.0

IMU_COUNT_MAX = 1023  # 10-bit ADC
IMU_COUNT_MASK = 0x3FF
IMU_COUNTER_MODULO = 4096  # 12-bit rolling sample counter

INT8 = (-128, 127)
UINT8 = (0, 255)
INT16 = (-32768, 32767)
UINT16 = (0, 65535)
INT32 = (-(2**31), 2**31 - 1)
UINT32 = (0, 2**32 - 1)


class MkMessage(Protocol):
    """What every message class provides."""

    COMMAND: ClassVar[str]

    def pack(self) -> bytes: ...


def finite(value: float, name: str) -> float:
    value = float(value)
    if not math.isfinite(value):
        raise ProtocolError(f"{name} must be finite, got {value!r}")
    return value


def sat_int(value: float, bounds: tuple[int, int]) -> int:
    """Round to the nearest integer and clamp to ``bounds`` (inclusive)."""
    lo, hi = bounds
    return max(lo, min(hi, round(value)))


def scaled(value: float, lsb: float, bounds: tuple[int, int], name: str) -> int:
    """``value / lsb`` rounded and saturated to ``bounds``; ProtocolError if not finite."""
    return sat_int(finite(value, name) / lsb, bounds)


def wrap(value: int, modulo: int, name: str) -> int:
    """A rolling counter modulo ``modulo``; ProtocolError if not a finite number."""
    return int(finite(value, name)) % modulo


def need(payload: bytes, size: int, cls: type) -> None:
    if len(payload) < size:
        raise ProtocolError(f"{cls.__name__} payload needs {size} bytes, got {len(payload)}")


def ints(values: Iterable[float], n: int, bounds: tuple[int, int], name: str) -> tuple[int, ...]:
    """``n`` values rounded and saturated to ``bounds`` (fast path for in-range ints: the common case)."""
    lo, hi = bounds
    out = tuple(
        (v if lo <= v <= hi else (lo if v < lo else hi)) if type(v) is int else sat_int(finite(v, name), bounds)
        for v in values
    )
    if len(out) != n:
        raise ProtocolError(f"{name} needs {n} values, got {len(out)}")
    return out


def three_floats(values: Iterable[float] | np.ndarray, name: str) -> tuple[float, float, float]:
    """Three finite floats from a sequence or array (plain Python: numpy is slow on 3 elements)."""
    seq: Iterable[float] = values.tolist() if isinstance(values, np.ndarray) else values
    try:
        x, y, z = (float(v) for v in seq)
    except (TypeError, ValueError) as exc:
        raise ProtocolError(f"{name} needs 3 numbers, got {values!r}") from exc
    if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
        raise ProtocolError(f"{name} values must be finite, got {values!r}")
    return x, y, z

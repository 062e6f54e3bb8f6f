"""Property test: the bridge's vertical estimate stays finite and inside its limits whatever the board sends.

The ``Z`` frame's altitude is an int32 of cm (±21,474 km) with a validity flag; the accelerometer's vertical
reading is bounded by its 10-bit counts; the odometry's height can be anything a MAVLink float carries. In any
order, with the estimate pinned or flying: the height stays finite and >= 0, the vertical speed finite and inside
the climb and descent limits. Marked ``fuzz``; budget: ``QUADLINK_FUZZ_EXAMPLES`` (``scripts/fuzz.sh`` soaks).
"""

from __future__ import annotations

import math

import pytest
from fuzzing import FUZZ
from hypothesis import given
from hypothesis import strategies as st

from firmware_bridge.vertical_estimator import VerticalEstimator

pytestmark = pytest.mark.fuzz

INT32 = (-(2 ** 31), 2 ** 31 - 1)
ACCEL_RANGE_M_S2 = 40.0   # beyond the 10-bit accelerometer's ±4 g
MAX_CLIMB_M_S, MAX_DESCENT_M_S = 1.5, 1.0

_baro = st.tuples(st.just("baro"), st.integers(*INT32), st.booleans())
_imu = st.tuples(st.just("imu"), st.floats(0.0, 0.1), st.floats(-ACCEL_RANGE_M_S2, ACCEL_RANGE_M_S2),
                 st.floats(0.0, 1.0), st.booleans(), st.integers(1, 200))
_align = st.tuples(st.just("align"), st.floats(allow_nan=True, allow_infinity=True, width=32),
                   st.floats(allow_nan=True, allow_infinity=True, width=32))
_reset = st.just(("reset",))
EVENTS = st.lists(st.one_of(_baro, _imu, _align, _reset), min_size=1, max_size=40)


@FUZZ
@given(EVENTS)
def test_any_board_input_keeps_the_vertical_estimate_finite_and_bounded(events):
    est = VerticalEstimator(0.5, MAX_CLIMB_M_S, MAX_DESCENT_M_S)
    for event in events:
        kind = event[0]
        if kind == "baro":
            est.on_baro(event[1] * 0.01, event[2])
        elif kind == "imu":
            _, dt_s, a_z, thrust, on_ground, repeat = event
            for _ in range(repeat):
                est.update(dt_s, a_z, thrust, on_ground)
        elif kind == "align":
            est.align(event[1], event[2])
        else:
            est.reset_ground()
        e = est.estimate
        assert math.isfinite(e.height_m) and e.height_m >= 0.0, event
        assert math.isfinite(e.vz_m_s) and -MAX_CLIMB_M_S <= e.vz_m_s <= MAX_DESCENT_M_S, event
        assert math.isfinite(e.accel_bias_m_s2), event

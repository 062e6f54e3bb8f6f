"""companion.height: the odometry's height held to the floor the camera sees (campaign flight 28, CI's climb)."""

from __future__ import annotations

import math

import pytest

from companion.height import HeightEstimator, HeightParams

TAKEOFF_M = 0.1


def _fly(est: HeightEstimator, true_heights_m: list[float], odo_error_m: float, floor_every: int = 1,
         dt_s: float = 1 / 30) -> list[float | None]:
    """Frames of a climb whose odometry reads ``odo_error_m`` low; the floor is seen every ``floor_every``-th."""
    out = []
    for k, h in enumerate(true_heights_m):
        floor = h + TAKEOFF_M if k % floor_every == 0 else None
        out.append(est.update(k * dt_s, h - odo_error_m, floor))
    return out


def test_an_odometry_that_started_in_the_air_is_corrected_by_the_floor() -> None:
    est = HeightEstimator(HeightParams(TAKEOFF_M, 0.5))
    climb = [0.2 + 0.02 * k for k in range(120)]            # 0.2 -> 2.6 m in 4 s
    heights = _fly(est, climb, odo_error_m=0.2)
    assert heights[0] == pytest.approx(climb[0])             # the first floor seen sets the offset
    assert heights[-1] == pytest.approx(climb[-1], abs=1e-9)


def test_drift_is_followed_with_the_time_constant() -> None:
    est = HeightEstimator(HeightParams(TAKEOFF_M, 0.5))
    est.update(0.0, 1.0, 1.0 + TAKEOFF_M)                    # agree
    # the odometry jumps 0.2 m low (a restart): after one time constant ~63 % of it is taken back
    h = None
    for k in range(1, 16):
        h = est.update(k / 30, 0.8, 1.0 + TAKEOFF_M)
    assert h is not None and 1.0 - 0.2 * math.exp(-1.0) - 0.02 < h < 1.0 - 0.2 * math.exp(-1.0) + 0.02


def test_a_box_top_seen_without_the_floor_is_not_the_floor_and_a_deeper_floor_is() -> None:
    """Campaign 7, flight 8 re-flown: turning on the spot 0.6 m over a 1.37 m box, the camera saw only its top;
    the height fell 1.3 m within 0.5 s and the autopilot landed on the box. A surface more than 0.25 m above
    the floor tracked is a top; one deeper than it is the floor (the tracked one was a top)."""
    est = HeightEstimator(HeightParams(TAKEOFF_M, 0.5))
    t = 0.0
    for _ in range(30):                                      # hovering at 1.9 m (body), floor in view
        t += 1 / 30
        est.update(t, 1.9 - TAKEOFF_M, 1.9)
    for _ in range(90):                                      # 3 s of the box top alone: 0.53 m below
        t += 1 / 30
        h = est.update(t, 1.9 - TAKEOFF_M, 0.53)
    assert h == pytest.approx(1.9 - TAKEOFF_M, abs=1e-6)
    assert not est.verified(t + 2.0)                         # the floor was not seen all that time
    h = est.update(t + 1 / 30, 1.9 - TAKEOFF_M, 1.9 - 0.2)   # a 0.2 m rise (drift, or a rug): filtered in
    assert 1.9 - TAKEOFF_M - 0.2 < h < 1.9 - TAKEOFF_M
    # taken off beside a desk whose top it took for the floor: the real floor, 0.7 m deeper, is taken at once
    est = HeightEstimator(HeightParams(TAKEOFF_M, 0.5))
    est.update(0.0, 0.5, 0.5 + TAKEOFF_M - 0.7)
    assert est.update(0.1, 0.5, 0.5 + TAKEOFF_M) == pytest.approx(0.5)


def test_without_the_floor_the_offset_is_kept_and_the_odometry_moves_the_height() -> None:
    est = HeightEstimator(HeightParams(TAKEOFF_M, 0.5))
    est.update(0.0, 0.8, 1.0 + TAKEOFF_M)                    # offset +0.2
    assert est.update(0.1, 1.5, None) == pytest.approx(1.7)


def test_odometry_lost_the_floor_alone_or_nothing() -> None:
    est = HeightEstimator(HeightParams(TAKEOFF_M, 0.5))
    assert est.update(0.0, None, None) is None
    assert est.update(0.1, None, 1.3 + TAKEOFF_M) == pytest.approx(1.3)
    assert est.update(0.2, float("nan"), float("inf")) is None


def test_time_constant_zero_is_the_odometry_alone() -> None:
    est = HeightEstimator(HeightParams(TAKEOFF_M, 0.0))
    assert est.update(0.0, 0.5, 2.0) == pytest.approx(0.5)
    assert est.update(0.1, None, 2.0) is None


def test_the_height_is_verified_for_a_while_after_the_floor_was_seen() -> None:
    est = HeightEstimator(HeightParams(TAKEOFF_M, 0.5, fix_max_age_s=4.0))
    est.update(0.0, 1.0, None)
    assert not est.verified(0.0)                              # never seen the floor
    est.update(1.0, 1.0, 1.0 + TAKEOFF_M)
    assert est.verified(1.0) and est.verified(5.0) and not est.verified(5.1)
    assert HeightEstimator(HeightParams(TAKEOFF_M, 0.0)).verified(0.0) is False   # no height at all
    off = HeightEstimator(HeightParams(TAKEOFF_M, 0.0))
    off.update(0.0, 1.0, None)
    assert off.verified(100.0)                                # the floor not used: the odometry's is the height


def test_the_height_may_drift_while_the_floor_is_out_of_view_and_the_ceiling_keeps_that_too() -> None:
    """Falsify seed 4 on 601b29b: at 1.9 m in a 2.4 m room the floor was out of range for 7 s; the odometry's height
    rose 1.5 cm while the vehicle rose 5 cm. The bound grows at drift_m_s from the last floor seen, up to 0.3 m,
    and starts again when the floor is back; the room's ceiling limit (not the fence) keeps it."""
    from companion.height import MAX_UNCERTAINTY_M
    from companion.vertical_limits import VerticalParams, ceiling_height_m, vertical_limits

    est = HeightEstimator(HeightParams(TAKEOFF_M, 0.5, drift_m_s=0.01))
    assert est.uncertainty_m(0.0) == 0.0                     # nothing learnt yet
    est.update(0.0, 1.8, 1.8 + TAKEOFF_M)
    assert est.uncertainty_m(0.0) == 0.0
    for k in range(1, 211):                                  # 7 s without the floor
        est.update(k / 30, 1.8, None)
    assert est.uncertainty_m(7.0) == pytest.approx(0.07)
    assert est.uncertainty_m(100.0) == MAX_UNCERTAINTY_M
    est.update(7.0 + 1 / 30, 1.8, 1.8 + TAKEOFF_M)           # the floor again
    assert est.uncertainty_m(7.0 + 1 / 30) == 0.0
    room = VerticalParams(max_height_m=3.0, room_height_m=2.47, room_height_error_m=0.1)
    assert ceiling_height_m(room, 0.07) == pytest.approx(2.47 - 0.1 - 0.45 - 0.07)
    fence = VerticalParams(max_height_m=1.5, room_height_m=None)
    assert ceiling_height_m(fence, 0.07) == 1.5               # a fence is counted from take-off: no floor in it
    # at the limit with the floor long gone: sent down, not up
    at_limit = vertical_limits(ceiling_height_m(room), 0.0, room, True, 0.07)
    assert at_limit.max_climb_m_s < 0.0
    assert HeightEstimator(HeightParams(TAKEOFF_M, 0.0)).uncertainty_m(50.0) == 0.0

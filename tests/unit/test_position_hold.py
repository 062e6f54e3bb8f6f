"""companion.position_hold: where the reference stops the vehicle (blocked, or nothing commanded), it holds."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.position_hold import PositionHold, PositionHoldParams, h_to_world, world_to_h
from companion.reference import ReferenceOutput


def _ref(vx: float = 0.0, vy: float = 0.0, constrained: bool = True) -> ReferenceOutput:
    z = np.zeros(3)
    return ReferenceOutput(np.array([vx, vy, 0.0]), 0.0, np.array([0.3, 0.0, 0.0]), z, 0.0, 0.0, 0.0, constrained)


def test_world_and_h_are_inverse_rotations() -> None:
    e = np.array([0.3, -0.2])
    for yaw in (0.0, 0.7, -2.5, math.pi):
        np.testing.assert_allclose(h_to_world(world_to_h(e, yaw), yaw), e, atol=1e-12)
    # heading east (yaw 90 deg): north is on the vehicle's left (H y < 0)
    np.testing.assert_allclose(world_to_h(np.array([1.0, 0.0]), math.pi / 2), [0.0, -1.0], atol=1e-12)


def test_a_moving_reference_passes_untouched() -> None:
    hold = PositionHold()
    ref = _ref(0.3, 0.0, constrained=False)
    assert hold.step(0.0, ref, [0.0, 0.0, -1.0], 0.0, True, True) is ref
    assert not hold.holding


def test_nothing_commanded_holds_too() -> None:
    """A script that stopped, an operator who let go, HOLD: the zero reference holds the place (PX4's position mode
    with centred sticks), not only a reference the safety layer cut."""
    hold = PositionHold()
    hold.step(0.0, _ref(constrained=False), [0.0, 0.0, -1.0], 0.0, True, True)
    out = hold.step(0.1, _ref(constrained=False), [0.05, 0.0, -1.0], 0.0, True, True)
    np.testing.assert_allclose(out.v_ref_h_m_s[:2], [-0.05, 0.0], atol=1e-12)


def test_a_blocked_command_anchors_and_the_creep_is_pulled_back() -> None:
    hold = PositionHold(PositionHoldParams(gain_per_s=1.0, max_speed_m_s=0.15))
    assert hold.step(0.0, _ref(), [1.0, 2.0, -1.0], 0.0, True, True).v_ref_h_m_s[0] == 0.0
    assert hold.holding
    np.testing.assert_allclose(hold.anchor_w_m, [1.0, 2.0])
    # crept 5 cm north, heading east: back is south, the vehicle's right (+y in H)
    out = hold.step(0.1, _ref(), [1.05, 2.0, -1.0], math.pi / 2, True, True)
    np.testing.assert_allclose(out.v_ref_h_m_s, [0.0, 0.05, 0.0], atol=1e-12)


def test_the_correction_is_limited() -> None:
    hold = PositionHold(PositionHoldParams(gain_per_s=1.0, max_speed_m_s=0.15, max_offset_m=0.5))
    hold.step(0.0, _ref(), [0.0, 0.0, -1.0], 0.0, True, True)
    out = hold.step(0.1, _ref(), [0.4, 0.0, -1.0], 0.0, True, True)
    np.testing.assert_allclose(out.v_ref_h_m_s, [-0.15, 0.0, 0.0], atol=1e-12)


def test_far_from_the_anchor_it_re_anchors() -> None:
    hold = PositionHold(PositionHoldParams(max_offset_m=0.5))
    hold.step(0.0, _ref(), [0.0, 0.0, -1.0], 0.0, True, True)
    out = hold.step(0.1, _ref(), [0.8, 0.0, -1.0], 0.0, True, True)   # an odometry reset, or a gust
    np.testing.assert_allclose(out.v_ref_h_m_s, 0.0)
    np.testing.assert_allclose(hold.anchor_w_m, [0.8, 0.0])


@pytest.mark.parametrize("why", ["released", "odometry", "not in control"])
def test_it_lets_go(why: str) -> None:
    hold = PositionHold(PositionHoldParams(release_above_m_s=0.05))
    hold.step(0.0, _ref(), [0.0, 0.0, -1.0], 0.0, True, True)
    ref = {"released": _ref(0.1)}.get(why, _ref())
    out = hold.step(0.1, ref, [0.1, 0.0, -1.0], 0.0, why != "odometry", why != "not in control")
    assert out is ref
    assert not hold.holding


def test_a_slow_way_out_is_followed_not_fought() -> None:
    """Inside the safe distance the layer sends the vehicle out slowly (k (d_safe - d), ~1 cm/s near it): the anchor
    moves with that reference, so a vehicle that follows it gets no correction against it."""
    hold = PositionHold(PositionHoldParams(engage_below_m_s=0.02, release_above_m_s=0.05))
    p = np.zeros(3)
    for k in range(101):
        out = hold.step(0.1 * k, _ref(-0.015), p, 0.0, True, True)
        p = p + np.array([-0.015 * 0.1, 0.0, 0.0])
    assert hold.holding
    np.testing.assert_allclose(out.v_ref_h_m_s[:2], [-0.015, 0.0], atol=2e-3)


def test_non_finite_input_is_no_hold() -> None:
    hold = PositionHold()
    ref = _ref()
    assert hold.step(0.0, ref, [math.nan, 0.0, -1.0], 0.0, True, True) is ref
    assert hold.step(0.1, ref, [0.0, 0.0, -1.0], math.nan, True, True) is ref
    assert hold.step(0.2, ref, None, 0.0, True, True) is ref
    assert not hold.holding


def _creep(hold: PositionHold | None, seconds: float = 10.0, creep_m_s: float = 0.05) -> float:
    """A velocity loop that follows its reference with a steady error of ``creep_m_s`` (the corner push's 3-6 cm/s
    toward the wall), the reference 0 (blocked), 30 Hz: the farthest the vehicle gets from where it was blocked."""
    dt, p, far = 1.0 / 30.0, np.zeros(3), 0.0
    for k in range(int(seconds / dt)):
        ref = _ref()
        if hold is not None:
            ref = hold.step(k * dt, ref, p, 0.3, True, True)
        v_h = np.asarray(ref.v_ref_h_m_s)[:2] + np.array([creep_m_s, 0.0])
        p[:2] = p[:2] + dt * h_to_world(v_h, 0.3)
        far = max(far, float(np.linalg.norm(p[:2])))
    return far


def test_the_hold_bounds_the_creep_a_zero_velocity_lets_grow() -> None:
    assert _creep(None) > 0.45                          # 5 cm/s for 10 s
    assert _creep(PositionHold(PositionHoldParams(gain_per_s=1.0))) < 0.06   # the offset creep / gain, 5 cm

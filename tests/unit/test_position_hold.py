"""companion.position_hold: where the reference stops the vehicle (blocked, or nothing commanded), it holds."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from companion.position_hold import PositionHold, PositionHoldParams, h_to_world, world_to_h
from companion.reference import ReferenceOutput


def _ref(vx: float = 0.0, vy: float = 0.0, constrained: bool = True) -> ReferenceOutput:
    z = np.zeros(3)
    return ReferenceOutput(np.array([vx, vy, 0.0]), 0.0, np.array([0.3, 0.0, 0.0]), z, 0.0, 0.0, 0.0, constrained)


def _idle(vx: float = 0.0, vy: float = 0.0) -> ReferenceOutput:
    """A reference with nothing commanded (the operator's handle centred, HOLD): what is left is the repulsion's."""
    return dataclasses.replace(_ref(vx, vy), v_operator_h_m_s=np.zeros(3))


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


def _turning_drift(release_idle_above_m_s: float, seconds: float = 4.0) -> float:
    """A vehicle turning on the spot at 0.7 rad/s (a failsafe landing's look round) whose velocity loop errs by 0.1 m/s
    fixed in the body (a tilt bias, turning with it: no integrator follows it), while the repulsion asks 0.06 m/s
    east (world): the farthest the vehicle gets from where that reference alone would take it, 30 Hz."""
    hold = PositionHold(PositionHoldParams(release_idle_above_m_s=release_idle_above_m_s))
    dt, p, p_ref, far = 1.0 / 30.0, np.zeros(3), np.zeros(2), 0.0
    for k in range(int(seconds / dt)):
        yaw = 0.7 * k * dt
        v_rep_w = np.array([0.0, 0.06]) if k * dt > 0.5 else np.zeros(2)   # it begins once the hold is anchored
        ref = hold.step(k * dt, _idle(*world_to_h(v_rep_w, yaw)), p, yaw, True, True)
        v_w = h_to_world(np.asarray(ref.v_ref_h_m_s)[:2] + np.array([0.1, 0.0]), yaw)
        p[:2] += dt * v_w
        p_ref += dt * v_rep_w
        far = max(far, float(np.linalg.norm(p[:2] - p_ref)))
    return far


def test_a_slow_repulsion_keeps_the_hold_while_the_vehicle_turns() -> None:
    """Falsification seed 12, trial 32: a failsafe landing's look round (0.7 rad/s) over unseen ground met a 0.06 m/s
    repulsion; the hold let go at 0.05 m/s and the vehicle, its loop erring in the turning body, drifted 0.25 m in
    2 s toward a specular doorway's side the camera did not see (0.339 m). With nothing commanded, a reference slower
    than the hold's own correction keeps it, the anchor moving with the reference (0.55 m, re-flown)."""
    kept, control = _turning_drift(PositionHoldParams().release_idle_above_m_s), _turning_drift(0.05)
    assert control > 0.2, control            # the control: let go, the turning error carries the vehicle off
    assert kept < 0.5 * control, (kept, control)


def test_a_command_still_lets_go_at_the_lower_bound() -> None:
    """While something is commanded (an operator's push the layer cut), the hold lets go above
    ``release_above_m_s`` as before: the law's slow approach is the operator's, not a drift to hold against."""
    hold = PositionHold(PositionHoldParams(release_above_m_s=0.05, release_idle_above_m_s=0.15))
    hold.step(0.0, _ref(), [0.0, 0.0, -1.0], 0.0, True, True)
    pushed = dataclasses.replace(_ref(0.1), v_operator_h_m_s=np.array([0.5, 0.0, 0.0]))
    assert hold.step(0.1, pushed, [0.0, 0.0, -1.0], 0.0, True, True) is pushed and not hold.holding
    hold.step(0.2, _idle(), [0.0, 0.0, -1.0], 0.0, True, True)
    hold.step(0.3, _idle(0.1), [0.0, 0.0, -1.0], 0.0, True, True)
    assert hold.holding   # the same 0.1 m/s with nothing commanded (a repulsion) keeps it

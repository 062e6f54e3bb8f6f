"""Minimum-snap trajectories (quadlink.trajectory.minsnap): waypoints, continuity, end conditions, optimality."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import null_space

from quadlink.trajectory import minimum_snap
from quadlink.trajectory.minsnap import (
    N_COEF,
    MinSnapTrajectory,
    TrajectoryError,
    _constraints,
    allocate_times_proportional,
    snap_cost_matrix,
)

# paper 003, "Autonomous Navigation": P1..P4 (P4 = P1), local NED, m; a 9 s oval at up to 1 m/s
OVAL_NED_M = np.array([[-1.0, -1.5, -1.2], [0.0, -0.5, -1.2], [0.0, 0.5, -1.2], [-1.0, -1.5, -1.2]])
OVAL_DURATIONS_S = (3.0, 1.7, 4.3)  # configs/trajectories/oval.yaml

SQUIGGLE = np.array([[0.0, 0.0, 0.0], [1.0, 0.5, -0.2], [1.5, 2.0, -0.5], [0.5, 2.5, -0.3], [-0.5, 1.0, 0.0]])


def test_passes_through_the_waypoints_exactly() -> None:
    tr = minimum_snap(SQUIGGLE, [1.0, 1.5, 0.8, 2.0])
    for t, w in zip(tr.knots_s, SQUIGGLE):
        np.testing.assert_allclose(tr.sample(t).p_m, w, atol=1e-9)


@pytest.mark.parametrize("k", range(1, 7))
def test_derivatives_up_to_the_sixth_are_continuous_at_the_joints(k: int) -> None:
    """1..4 are constraints; 5 and 6 come out of the optimum (Euler-Lagrange), so they are a real check."""
    tr = minimum_snap(SQUIGGLE, [1.0, 1.5, 0.8, 2.0])
    for i in range(1, tr.segments):
        left = tr.segment_derivative(i - 1, 1.0, k)
        right = tr.segment_derivative(i, 0.0, k)
        scale = max(1.0, float(np.abs(left).max()))
        np.testing.assert_allclose(left, right, atol=1e-7 * scale)
    # and numerically: a finite difference across the joint matches the one just inside a segment
    eps = 1e-4
    t = tr.knots_s[2]
    fd_across = (tr.derivative(t + eps, k - 1) - tr.derivative(t - eps, k - 1)) / (2 * eps)
    np.testing.assert_allclose(fd_across, tr.derivative(t, k), rtol=1e-3, atol=1e-3)


def test_seventh_derivative_is_not_continuous_so_the_check_above_can_fail() -> None:
    tr = minimum_snap(SQUIGGLE, [1.0, 1.5, 0.8, 2.0])
    jumps = [np.abs(tr.segment_derivative(i - 1, 1.0, 7) - tr.segment_derivative(i, 0.0, 7)).max()
             for i in range(1, tr.segments)]
    assert max(jumps) > 1e-2


def test_rest_to_rest_end_conditions() -> None:
    tr = minimum_snap(SQUIGGLE, [1.0, 1.5, 0.8, 2.0])
    for t in (0.0, tr.duration_s):
        for k in (1, 2, 3):
            np.testing.assert_allclose(tr.derivative(t, k), 0.0, atol=1e-9)
    # outside the time range it holds the end points at rest
    np.testing.assert_allclose(tr.sample(-1.0).p_m, SQUIGGLE[0], atol=1e-9)
    np.testing.assert_allclose(tr.sample(tr.duration_s + 5.0).p_m, SQUIGGLE[-1], atol=1e-9)
    np.testing.assert_allclose(tr.sample(tr.duration_s + 5.0).v_m_s, 0.0, atol=1e-9)


def test_prescribed_waypoint_velocities_are_met() -> None:
    v_mid = np.array([0.3, 0.8, 0.0])
    v_end = np.array([0.2, 0.0, 0.1])
    vel = [None, None, v_mid, None, v_end]
    tr = minimum_snap(SQUIGGLE, [1.0, 1.5, 0.8, 2.0], velocities_m_s=vel)
    np.testing.assert_allclose(tr.derivative(tr.knots_s[2], 1), v_mid, atol=1e-9)
    np.testing.assert_allclose(tr.segment_derivative(1, 1.0, 1), v_mid, atol=1e-9)  # both sides of the joint
    np.testing.assert_allclose(tr.derivative(tr.duration_s, 1), v_end, atol=1e-9)
    for t, w in zip(tr.knots_s, SQUIGGLE):
        np.testing.assert_allclose(tr.sample(t).p_m, w, atol=1e-9)
    # constraining a velocity costs snap
    free = minimum_snap(SQUIGGLE, [1.0, 1.5, 0.8, 2.0])
    assert tr.snap_cost() > free.snap_cost()


def test_snap_cost_is_lower_than_any_perturbed_feasible_trajectory() -> None:
    T = np.array([1.0, 1.5, 0.8, 2.0])
    tr = minimum_snap(SQUIGGLE, T)
    A, b = _constraints(T, SQUIGGLE, [None] * len(SQUIGGLE))
    N = null_space(A)  # every feasible trajectory is the optimum plus N z
    assert N.shape[1] == 2 * len(T) - 2
    c_opt = tr.coeffs.reshape(-1, 3)
    rng = np.random.default_rng(7)
    for _ in range(20):
        dc = N @ rng.normal(scale=0.05, size=(N.shape[1], 3))
        alt = MinSnapTrajectory(T, (c_opt + dc).reshape(len(T), N_COEF, 3))
        np.testing.assert_allclose(A @ (c_opt + dc), b, atol=1e-9)  # feasible: same waypoints and conditions
        assert alt.snap_cost() > tr.snap_cost()
    # the cost matrix integrates the snap: compare with a quadrature of one segment
    s = np.linspace(0.0, 1.0, 20001)
    c = rng.normal(size=N_COEF)
    snap = sum(c[n] * n * (n - 1) * (n - 2) * (n - 3) * s ** (n - 4) for n in range(4, N_COEF))
    assert c @ snap_cost_matrix() @ c == pytest.approx(np.trapezoid(snap**2, s), rel=1e-6)


def test_papers_oval_peaks_at_most_one_metre_per_second_over_nine_seconds() -> None:
    tr = minimum_snap(OVAL_NED_M, OVAL_DURATIONS_S)
    assert tr.duration_s == pytest.approx(9.0)
    peak = tr.peak_speed_m_s(step_s=0.002)
    assert 0.9 <= peak <= 1.0  # "the velocity reaches values of 1 m/s"
    np.testing.assert_allclose(tr.sample(9.0).p_m, OVAL_NED_M[0], atol=1e-9)  # closes at P1
    # it is an oval, not the triangle P1 P2 P3: the path leaves the chords between the waypoints
    mid = tr.sample(tr.knots_s[2] + 0.5 * OVAL_DURATIONS_S[2]).p_m
    chord = OVAL_NED_M[3, :2] - OVAL_NED_M[2, :2]
    rel = mid[:2] - OVAL_NED_M[2, :2]
    off = abs(chord[0] * rel[1] - chord[1] * rel[0]) / np.linalg.norm(chord)
    assert off > 0.1
    # altitude stays at -1.2 m (all waypoints share it)
    zs = [tr.sample(t).p_m[2] for t in np.linspace(0, 9, 91)]
    np.testing.assert_allclose(zs, -1.2, atol=1e-9)


def test_proportional_allocation_and_bad_input() -> None:
    T = allocate_times_proportional(OVAL_NED_M, 9.0)
    assert T.sum() == pytest.approx(9.0)
    d = np.linalg.norm(np.diff(OVAL_NED_M, axis=0), axis=1)
    np.testing.assert_allclose(T / d, T[0] / d[0])
    tr = minimum_snap(OVAL_NED_M, total_duration_s=9.0)
    np.testing.assert_allclose(tr.durations_s, T)
    with pytest.raises(TrajectoryError):
        minimum_snap(OVAL_NED_M, [1.0, 2.0])
    with pytest.raises(TrajectoryError):
        minimum_snap(OVAL_NED_M, [1.0, -2.0, 3.0])
    with pytest.raises(TrajectoryError):
        minimum_snap(OVAL_NED_M[:1], [1.0])
    with pytest.raises(TrajectoryError):
        minimum_snap(OVAL_NED_M, [1.0, 2.0, 3.0], velocities_m_s=[None, [0.0, 1.0], None, None])
    with pytest.raises(TrajectoryError):
        allocate_times_proportional(np.array([[0.0, 0.0], [0.0, 0.0]]), 3.0)

"""Minimum-snap trajectories through waypoints, solved as an equality-constrained QP (pure, numpy only).

Paper 003 ("Autonomous Navigation", after Mellinger & Kumar 2011, its ref. [24]): the moment M is an
algebraic function of the snap, so the trajectory minimises

    min  integral_{t0}^{tf} || d^4 x_d / dt^4 ||^2 dt                       (the paper's snap cost)

over piecewise polynomials, one 7th-order polynomial per segment and per axis, subject to equality
constraints: the waypoint positions (and optional waypoint velocities), continuity of the derivatives
at the interior waypoints, and the end conditions (rest-to-rest: velocity, acceleration and jerk zero at
both ends unless a velocity is given there). The axes are independent (same constraint matrix, one
right-hand side per axis) and the QP is solved exactly through its KKT system.

Continuity: the QP imposes continuity of the derivatives 1..4 (velocity to snap) at every interior
waypoint; the optimum is then C^6 there by itself (the Euler-Lagrange conditions of the snap cost make
the derivative 7-j continuous wherever derivative j is free, j = 1..3), which ``tests/test_trajectory_minsnap.py``
checks numerically. Imposing 5 and 6 as constraints too would leave no freedom at all and make waypoint
velocity constraints infeasible; at a waypoint with a prescribed velocity the 6th derivative may jump.

Each segment is parametrised in normalised time s = (t - t_i) / T_i in [0, 1] (better conditioned than
raw time: the cost of segment i is T_i^-7 * integral_0^1 (d^4 p / ds^4)^2 ds and the k-th time
derivative is T_i^-k d^k p / ds^k).

Frames and units: whatever frame the waypoints are given in (quadlink uses local NED, metres, seconds);
the generator does not rotate anything.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

ORDER = 7  # polynomial degree per segment
N_COEF = ORDER + 1
SNAP = 4  # the derivative whose squared integral is minimised
CONTINUITY_ORDER = 4  # derivatives 1..4 are equality constraints at interior waypoints (see module doc)
END_DERIVATIVES = 3  # rest-to-rest: velocity, acceleration and jerk fixed at both ends

__all__ = ["MinSnapTrajectory", "TrajectorySample", "allocate_times_proportional", "minimum_snap",
           "snap_cost_matrix", "TrajectoryError"]


class TrajectoryError(ValueError):
    """Waypoints, times or constraints that do not define a trajectory."""


@dataclass(frozen=True)
class TrajectorySample:
    """The desired flat output at time ``t_s`` (frame of the waypoints, SI units)."""

    t_s: float
    p_m: NDArray[np.float64]
    v_m_s: NDArray[np.float64]
    a_m_s2: NDArray[np.float64]
    j_m_s3: NDArray[np.float64]


def _falling(n: int, k: int) -> float:
    """n (n-1) ... (n-k+1): the factor of d^k/ds^k s^n."""
    out = 1.0
    for i in range(k):
        out *= n - i
    return out


def _derivative_row(s: float, k: int) -> NDArray[np.float64]:
    """Row r with r @ c = d^k/ds^k sum_n c_n s^n at s (coefficients in increasing power)."""
    row = np.zeros(N_COEF)
    for n in range(k, N_COEF):
        row[n] = _falling(n, k) * (s ** (n - k) if n > k else 1.0)
    return row


def snap_cost_matrix() -> NDArray[np.float64]:
    """Q with c^T Q c = integral_0^1 (d^4 p / ds^4)^2 ds for one normalised segment."""
    Q = np.zeros((N_COEF, N_COEF))
    for i in range(SNAP, N_COEF):
        for j in range(SNAP, N_COEF):
            Q[i, j] = _falling(i, SNAP) * _falling(j, SNAP) / (i + j - 2 * SNAP + 1)
    return Q


def allocate_times_proportional(waypoints_m: ArrayLike, total_duration_s: float) -> NDArray[np.float64]:
    """Segment durations proportional to the straight-line distance between waypoints, summing to the total."""
    w = np.asarray(waypoints_m, dtype=float)
    if w.ndim != 2 or w.shape[0] < 2:
        raise TrajectoryError("need at least two waypoints (an N x D array)")
    if not (math.isfinite(total_duration_s) and total_duration_s > 0.0):
        raise TrajectoryError(f"total duration must be positive, got {total_duration_s}")
    d = np.linalg.norm(np.diff(w, axis=0), axis=1)
    if np.any(d <= 0.0):
        raise TrajectoryError("consecutive waypoints must differ (a zero-length segment has no time share)")
    return np.asarray(total_duration_s * d / d.sum(), dtype=float)


class MinSnapTrajectory:
    """Piecewise 7th-order polynomials; ``sample(t)`` gives position, velocity, acceleration and jerk.

    Before the start and after the end the trajectory holds its end points (with the end velocity, zero
    unless one was prescribed, and zero acceleration/jerk beyond the ends).
    """

    def __init__(self, durations_s: NDArray[np.float64], coeffs: NDArray[np.float64]) -> None:
        self.durations_s = np.asarray(durations_s, dtype=float)
        self.coeffs = np.asarray(coeffs, dtype=float)  # (segments, N_COEF, dims), normalised time
        self.knots_s = np.concatenate([[0.0], np.cumsum(self.durations_s)])

    @property
    def duration_s(self) -> float:
        return float(self.knots_s[-1])

    @property
    def segments(self) -> int:
        return len(self.durations_s)

    def derivative(self, t_s: float, k: int) -> NDArray[np.float64]:
        """The k-th time derivative (k = 0..7) at t, inside [0, duration]; clamped outside."""
        t = min(max(float(t_s), 0.0), self.duration_s)
        i = int(np.searchsorted(self.knots_s, t, side="right") - 1)
        i = min(max(i, 0), self.segments - 1)
        return self.segment_derivative(i, (t - self.knots_s[i]) / self.durations_s[i], k)

    def segment_derivative(self, segment: int, s: float, k: int) -> NDArray[np.float64]:
        """The k-th time derivative of one segment at normalised time s (for continuity checks at joints)."""
        T = self.durations_s[segment]
        return np.asarray(_derivative_row(s, k) @ self.coeffs[segment] / T**k, dtype=float)

    def sample(self, t_s: float) -> TrajectorySample:
        t = float(t_s)
        inside = 0.0 <= t <= self.duration_s
        p = self.derivative(t, 0)
        v = self.derivative(t, 1)
        if inside:
            a, j = self.derivative(t, 2), self.derivative(t, 3)
        else:
            a = j = np.zeros_like(p)
            p = p + v * (t - min(max(t, 0.0), self.duration_s))  # an end velocity keeps moving (rest: holds)
        return TrajectorySample(t, p, v, a, j)

    def snap_cost(self) -> float:
        """integral ||d^4 x / dt^4||^2 dt over the whole trajectory (all axes)."""
        Q = snap_cost_matrix()
        return float(sum(np.trace(c.T @ Q @ c) / T**7 for c, T in zip(self.coeffs, self.durations_s)))

    def peak_speed_m_s(self, step_s: float = 0.005) -> float:
        ts = np.arange(0.0, self.duration_s + step_s, step_s)
        return float(max(np.linalg.norm(self.derivative(t, 1)) for t in ts))


def _constraints(durations_s: NDArray[np.float64], waypoints: NDArray[np.float64],
                 velocities: Sequence[ArrayLike | None]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """A c = b for all segments (c stacks the segments' normalised coefficients), one column of b per axis."""
    n_seg = len(durations_s)
    dims = waypoints.shape[1]
    rows: list[NDArray[np.float64]] = []
    rhs: list[NDArray[np.float64]] = []

    def add(entries: list[tuple[int, NDArray[np.float64]]], value: NDArray[np.float64]) -> None:
        row = np.zeros(n_seg * N_COEF)
        for seg, r in entries:
            row[seg * N_COEF:(seg + 1) * N_COEF] += r
        rows.append(row)
        rhs.append(np.asarray(value, dtype=float))

    zero = np.zeros(dims)
    for i in range(n_seg):
        add([(i, _derivative_row(0.0, 0))], waypoints[i])  # segment i starts at waypoint i
        add([(i, _derivative_row(1.0, 0))], waypoints[i + 1])  # ... and ends at waypoint i + 1
    for i in range(1, n_seg):  # interior waypoint i joins segment i-1 (s = 1) and segment i (s = 0)
        Tl, Tr = durations_s[i - 1], durations_s[i]
        for k in range(1, CONTINUITY_ORDER + 1):
            add([(i - 1, _derivative_row(1.0, k) / Tl**k), (i, -_derivative_row(0.0, k) / Tr**k)], zero)
        if velocities[i] is not None:
            add([(i, _derivative_row(0.0, 1) / Tr)], np.asarray(velocities[i], dtype=float))
    for seg, s, w in ((0, 0.0, 0), (n_seg - 1, 1.0, n_seg)):
        T = durations_s[seg]
        v_end = velocities[w]
        add([(seg, _derivative_row(s, 1) / T)], zero if v_end is None else np.asarray(v_end, dtype=float))
        for k in range(2, END_DERIVATIVES + 1):
            add([(seg, _derivative_row(s, k) / T**k)], zero)
    return np.array(rows), np.array(rhs)


def minimum_snap(waypoints_m: ArrayLike, durations_s: ArrayLike | None = None, *,
                 total_duration_s: float | None = None,
                 velocities_m_s: Sequence[ArrayLike | None] | None = None) -> MinSnapTrajectory:
    """The minimum-snap trajectory through ``waypoints_m`` (N x D, N >= 2).

    Time allocation: ``durations_s`` (N - 1 segment durations), or ``total_duration_s`` shared in proportion
    to the segments' lengths (:func:`allocate_times_proportional`). ``velocities_m_s``: N entries, None where
    the velocity is free (interior) or zero (the two ends, rest-to-rest); a vector where it is prescribed.
    """
    w = np.asarray(waypoints_m, dtype=float)
    if w.ndim != 2 or w.shape[0] < 2 or not np.all(np.isfinite(w)):
        raise TrajectoryError("waypoints must be a finite N x D array with N >= 2")
    if durations_s is None:
        if total_duration_s is None:
            raise TrajectoryError("give the segment durations or a total duration")
        T = allocate_times_proportional(w, total_duration_s)
    else:
        T = np.asarray(durations_s, dtype=float).reshape(-1)
    if len(T) != w.shape[0] - 1 or not np.all(np.isfinite(T)) or np.any(T <= 0.0):
        raise TrajectoryError(f"need {w.shape[0] - 1} positive finite segment durations, got {T.tolist()}")
    vel: list[ArrayLike | None] = [None] * w.shape[0] if velocities_m_s is None else list(velocities_m_s)
    if len(vel) != w.shape[0]:
        raise TrajectoryError(f"velocities: one entry (or None) per waypoint, got {len(vel)} for {w.shape[0]}")
    for v in vel:
        if v is not None and (np.shape(v) != (w.shape[1],) or not np.all(np.isfinite(v))):
            raise TrajectoryError(f"a waypoint velocity must be a finite {w.shape[1]}-vector, got {v!r}")

    A, b = _constraints(T, w, vel)
    n = len(T) * N_COEF
    Q = np.zeros((n, n))
    Qs = snap_cost_matrix()
    for i, Ti in enumerate(T):
        Q[i * N_COEF:(i + 1) * N_COEF, i * N_COEF:(i + 1) * N_COEF] = Qs / Ti**7
    # KKT of min c^T Q c s.t. A c = b:  [2Q A^T; A 0] [c; lambda] = [0; b]
    m = A.shape[0]
    K = np.block([[2.0 * Q, A.T], [A, np.zeros((m, m))]])
    rhs = np.vstack([np.zeros((n, w.shape[1])), b])
    try:
        sol = np.linalg.solve(K, rhs)
    except np.linalg.LinAlgError as exc:
        raise TrajectoryError(f"the constraints are inconsistent or redundant: {exc}") from exc
    if not np.allclose(A @ sol[:n], b, atol=1e-8 * max(1.0, float(np.abs(b).max()))):
        raise TrajectoryError("the KKT solve did not satisfy the constraints (ill-conditioned times?)")
    coeffs = sol[:n].reshape(len(T), N_COEF, w.shape[1])
    return MinSnapTrajectory(T, coeffs)

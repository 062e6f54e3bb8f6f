"""companion.frame_step: the unknown-sector rule for a scripted command versus the operator's (issue 14)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from companion.frame_step import NO_SCAN, frame_step
from companion.operator_input import OperatorInput
from companion.reference_params import ReferenceParams

# the camera looks along +x of H (optical z = body x): eq. (2) moves the operator along it
R_QC_FORWARD = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


@dataclass
class _Out:
    """The fields of perception's output that frame_step reads."""

    sectors: NDArray[np.float64]
    obstacle_points_h_m: NDArray[np.float64] | None = None
    odometry_ok: bool = True
    position_m: NDArray[np.float64] = field(default_factory=lambda: np.array([0.0, 0.0, -1.0]))
    v_h_m_s: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    obstacle_ages_s: NDArray[np.float64] | None = None
    obstacle_open_top: NDArray[np.bool_] | None = None


def _front_seen_only() -> _Out:
    """72 sectors: the front half (|azimuth| < 90 deg) seen and free, the back never seen."""
    az = np.arange(72) * 5.0
    az = (az + 180.0) % 360.0 - 180.0
    return _Out(np.where(np.abs(az) < 90.0, np.inf, np.nan))


def test_a_script_never_flies_toward_where_the_map_has_not_looked() -> None:
    params = ReferenceParams()
    out = _front_seen_only()
    back = frame_step(out, OperatorInput(), R_QC_FORWARD, NO_SCAN, params, True, True,
                      v_command_h_m_s=np.array([-0.4, 0.0, 0.0]))
    assert np.allclose(back.ref.v_ref_h_m_s[:2], 0.0) and back.ref.constrained
    ahead = frame_step(out, OperatorInput(), R_QC_FORWARD, NO_SCAN, params, True, True,
                       v_command_h_m_s=np.array([0.4, 0.1, 0.0]))
    np.testing.assert_allclose(ahead.ref.v_ref_h_m_s, [0.4, 0.1, 0.0])
    # a climb is not horizontal motion: allowed toward nothing horizontal
    up = frame_step(out, OperatorInput(), R_QC_FORWARD, NO_SCAN, params, True, True,
                    v_command_h_m_s=np.array([0.0, 0.0, -0.2]))
    assert up.ref.v_ref_h_m_s[2] < 0.0


def test_the_operator_keeps_cp_go_no_data_while_the_data_are_fresh() -> None:
    """The operator moves along the camera's axis (eq. 2): with fresh data and allow_unknown_when_fresh its push is
    not zeroed by sectors it has not seen; without allow_unknown_when_fresh it is."""
    params = ReferenceParams()
    out = _Out(np.full(72, np.nan))   # nothing seen yet
    push = OperatorInput(qx=1.0)
    free = frame_step(out, push, R_QC_FORWARD, NO_SCAN, params, True, True)
    assert free.ref.v_ref_h_m_s[0] == math.copysign(params.k_v_m_s, 1.0)
    blocked = frame_step(out, push, R_QC_FORWARD, NO_SCAN, params, True, False)
    assert np.allclose(blocked.ref.v_ref_h_m_s[:2], 0.0)


def test_the_operator_backing_up_goes_only_where_the_map_has_looked() -> None:
    """Campaign flight 25: a pulled-back handle reverses away from the camera (eq. 2 with q_x < 0), into sectors
    never seen: refused; forward is not."""
    params = ReferenceParams()
    out = _front_seen_only()
    back = frame_step(out, OperatorInput(qx=-0.8), R_QC_FORWARD, NO_SCAN, params, True, True)
    assert np.allclose(back.ref.v_ref_h_m_s[:2], 0.0) and back.ref.constrained
    ahead = frame_step(out, OperatorInput(qx=0.8), R_QC_FORWARD, NO_SCAN, params, True, True)
    assert ahead.ref.v_ref_h_m_s[0] > 0.4
    seen_behind = frame_step(_Out(np.full(72, np.inf)), OperatorInput(qx=-0.8), R_QC_FORWARD, NO_SCAN, params,
                             True, True)
    assert seen_behind.ref.v_ref_h_m_s[0] < -0.4     # where the map has looked (all free), it reverses


def _wall_ahead(distance_m: float, age_s: float) -> _Out:
    """A wall across +x at ``distance_m``, sampled every 0.1 m at the vehicle's height band, all seen ``age_s``
    ago; every sector seen and free elsewhere."""
    y = np.arange(-1.0, 1.01, 0.1)
    points = np.column_stack([np.full_like(y, distance_m), y, np.full_like(y, 0.2)])
    return _Out(np.full(72, np.inf), points, obstacle_ages_s=np.full(len(y), age_s))


def test_a_wall_remembered_long_counts_as_nearer_by_the_odometrys_drift() -> None:
    """Issue 14 (the real-time corner push): the vehicle rests by a wall the camera no longer sees while a velocity
    bias carries it on; a point seen 10 s ago counts as map_drift_m_s x 10 s nearer. Pushed at a wall 0.5 m
    ahead (outside the 0.45 m safe distance), seen just now, the vehicle still closes in; seen 10 s ago, the wall
    counts as 0.40 m: no push toward it gets through, and it backs away."""
    params = ReferenceParams()
    assert params.map_drift_m_s == 0.01
    push = OperatorInput(qx=1.0)
    fresh = frame_step(_wall_ahead(0.5, 0.0), push, R_QC_FORWARD, NO_SCAN, params, True, True)
    old = frame_step(_wall_ahead(0.5, 10.0), push, R_QC_FORWARD, NO_SCAN, params, True, True)
    assert fresh.ref.v_ref_h_m_s[0] > 0.0
    assert old.ref.v_ref_h_m_s[0] < 0.0
    assert old.nearest is not None and math.isclose(old.nearest[1], 0.5 - 0.1, abs_tol=0.03)
    off = frame_step(_wall_ahead(0.5, 10.0), push, R_QC_FORWARD, NO_SCAN,
                     ReferenceParams(map_drift_m_s=0.0), True, True)
    np.testing.assert_allclose(off.ref.v_ref_h_m_s, fresh.ref.v_ref_h_m_s)

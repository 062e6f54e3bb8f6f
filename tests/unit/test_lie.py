"""quadlink.lie: property tests of the SO(3)/SE(3) maps against their definitions and scipy."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from quadlink.lie import (
    angle_between_rad,
    inv_T,
    make_T,
    pose_error,
    rotation_angle_rad,
    skew,
    so3_exp,
    so3_exp_batch,
    so3_log,
    so3_log_batch,
    vee,
)

coord = st.floats(min_value=-1.0, max_value=1.0, allow_nan=False)
axes = st.tuples(coord, coord, coord).map(np.array).filter(lambda v: np.linalg.norm(v) > 1e-3)
angles = st.floats(min_value=0.0, max_value=math.pi, allow_nan=False)
rotvecs = st.builds(lambda n, a: n / np.linalg.norm(n) * a, axes, angles)
translations = st.tuples(*(st.floats(min_value=-10, max_value=10, allow_nan=False),) * 3).map(np.array)


def _R(w: np.ndarray) -> np.ndarray:
    return Rotation.from_rotvec(w).as_matrix()  # independent reference


@given(rotvecs)
def test_exp_matches_scipy_and_is_a_rotation(w: np.ndarray) -> None:
    R = so3_exp(w)
    np.testing.assert_allclose(R, _R(w), atol=1e-12)
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)


@given(rotvecs)
def test_log_exp_round_trip(w: np.ndarray) -> None:
    theta = float(np.linalg.norm(w))
    assume(theta < math.pi - 1e-9)  # at exactly pi, w and -w are the same rotation
    np.testing.assert_allclose(so3_log(so3_exp(w)), w, atol=1e-9)


@given(rotvecs)
def test_exp_log_round_trip_including_pi(w: np.ndarray) -> None:
    R = _R(w)
    np.testing.assert_allclose(so3_exp(so3_log(R)), R, atol=1e-9)
    assert float(np.linalg.norm(so3_log(R))) <= math.pi + 1e-12


@pytest.mark.parametrize("theta", [1e-12, 1e-8, 1e-5, math.pi - 1e-2, math.pi - 1e-4, math.pi - 1e-7, math.pi])
def test_log_is_accurate_at_the_singular_ends(theta: float) -> None:
    n = np.array([0.3, -0.5, 0.8])
    n /= np.linalg.norm(n)
    R = _R(n * theta)
    w = so3_log(R)
    assert float(np.linalg.norm(w)) == pytest.approx(theta, rel=1e-7, abs=1e-15)
    if theta < math.pi:
        np.testing.assert_allclose(w / np.linalg.norm(w), n, atol=1e-6)
    else:  # pi: either sign is the same rotation
        assert abs(float(w @ n) / theta) == pytest.approx(1.0)


@given(rotvecs, rotvecs)
def test_angle_between_is_symmetric_and_the_geodesic(w1: np.ndarray, w2: np.ndarray) -> None:
    R1, R2 = _R(w1), _R(w2)
    a = angle_between_rad(R1, R2)
    assert a == pytest.approx(angle_between_rad(R2, R1), abs=1e-12)
    assert a == pytest.approx(float(np.linalg.norm((Rotation.from_matrix(R1).inv() * Rotation.from_matrix(R2))
                                                   .as_rotvec())), abs=1e-9)
    assert 0.0 <= a <= math.pi + 1e-12
    # invariant under a common rotation on either side
    Q = _R(np.array([0.1, 0.2, -0.3]))
    assert angle_between_rad(Q @ R1, Q @ R2) == pytest.approx(a, abs=1e-9)


def test_rotation_angle_keeps_its_digits_near_zero() -> None:
    R = _R(np.array([0.0, 0.0, 1e-9]))
    assert rotation_angle_rad(R) == pytest.approx(1e-9, rel=1e-6)  # acos of the trace would give 0 or 2e-8


@given(st.lists(rotvecs, min_size=1, max_size=8))
def test_batch_maps_agree_with_the_scalar_ones(ws: list[np.ndarray]) -> None:
    w = np.array(ws)
    Rs = so3_exp_batch(w)
    np.testing.assert_allclose(Rs, np.array([so3_exp(x) for x in ws]), atol=1e-12)
    np.testing.assert_allclose(so3_exp_batch(so3_log_batch(Rs)), Rs, atol=1e-9)


@given(rotvecs, translations)
def test_inv_T_is_the_inverse(w: np.ndarray, t: np.ndarray) -> None:
    T = make_T(_R(w), t)
    np.testing.assert_allclose(inv_T(T) @ T, np.eye(4), atol=1e-9)
    np.testing.assert_allclose(inv_T(T), np.linalg.inv(T), atol=1e-9)


@given(st.tuples(coord, coord, coord).map(np.array), st.tuples(coord, coord, coord).map(np.array))
def test_skew_is_the_cross_product_and_vee_inverts_it(v: np.ndarray, u: np.ndarray) -> None:
    np.testing.assert_allclose(skew(v) @ u, np.cross(v, u), atol=1e-15)
    np.testing.assert_allclose(vee(skew(v)), v)


def test_pose_error_and_the_test_helper(assert_poses_close) -> None:  # noqa: ANN001
    T1 = make_T(_R(np.array([0.0, 0.0, 0.3])), np.array([1.0, 2.0, 3.0]))
    T2 = make_T(_R(np.array([0.0, 0.0, 0.3 + 1e-3])), np.array([1.0, 2.0, 3.002]))
    d_m, d_rad = pose_error(T1, T2)
    assert d_m == pytest.approx(0.002) and d_rad == pytest.approx(1e-3)
    assert_poses_close(T1, T2, atol_m=0.003, atol_rad=2e-3)
    with pytest.raises(AssertionError, match="rotation"):
        assert_poses_close(T1, T2, atol_m=0.003, atol_rad=5e-4)
    with pytest.raises(AssertionError, match="translation"):
        assert_poses_close(T1, T2, atol_m=0.001, atol_rad=2e-3)
    # a sign flip of the whole quaternion is the same pose: element-wise checks on quaternions miss this
    R = _R(np.array([math.pi - 1e-9, 0.0, 0.0]))
    assert_poses_close(make_T(R, np.zeros(3)), make_T(_R(np.array([-(math.pi - 1e-9), 0.0, 0.0])), np.zeros(3)),
                       atol_m=1e-9, atol_rad=1e-6)

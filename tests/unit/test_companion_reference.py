"""Reference velocity, pan-scan and identification against analytic cases (paper 000, eqs. 2-8)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.avoidance import (
    limit_speed_toward_obstacles,
    remove_toward_close_obstacles,
    remove_toward_unknown,
    repulsion_velocity,
)
from companion.obstacle_points import nearest_obstacle
from companion.operator_input import OperatorInput, camera_yaw_rad, operator_from_manual_control
from companion.pan_scan import PanScanParams, PanScanState, pan_scan, swing_amplitude_rad
from companion.reference import reference_velocity
from companion.reference_params import ReferenceParams
from quadlink.analysis.yaw_identification import (
    IdentificationError,
    fit_sinusoid,
    identify_first_order,
    identify_from_log,
)
from quadlink.frames import Ry, Rz
from quadlink.vehicle import CameraConfig

NO_SCAN = PanScanState(0.0, 0.0, False)
# camera looking straight ahead: optical z -> body x, optical x -> body y, optical y -> body z
R_QC_FORWARD = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


def test_manual_control_mapping_qgc_ranges() -> None:
    op = operator_from_manual_control(1000, -500, 500)
    assert (op.qx, op.qy, op.qz) == pytest.approx((1.0, -0.5, 0.0))
    assert operator_from_manual_control(0, 0, 1000).qz == pytest.approx(1.0)
    assert operator_from_manual_control(0, 0, 0).qz == pytest.approx(-1.0)
    # deadband removes small offsets and rescales so full deflection stays full
    op = operator_from_manual_control(20, 1000, 510, deadband=0.05)
    assert (op.qx, op.qy, op.qz) == pytest.approx((0.0, 1.0, 0.0))


def test_camera_yaw_of_default_mount_is_45_deg_right() -> None:
    assert camera_yaw_rad(CameraConfig().R_qc_matrix) == pytest.approx(math.radians(45.0), abs=1e-9)
    assert camera_yaw_rad(R_QC_FORWARD) == pytest.approx(0.0)
    # a camera yawed by 30 deg left of a pitched-down forward mount
    R = Rz(math.radians(-30.0)) @ Ry(math.radians(-20.0)) @ R_QC_FORWARD
    assert camera_yaw_rad(R) == pytest.approx(math.radians(-30.0), abs=1e-9)


def test_operator_forward_moves_along_alpha_and_climb_is_minus_z() -> None:
    params = ReferenceParams(k_v_m_s=0.5, k_climb_m_s=0.3, k_psi_rad_s=0.7)
    R = CameraConfig().R_qc_matrix
    out = reference_velocity(OperatorInput(qx=1.0, qy=0.5, qz=1.0), R, NO_SCAN, None, params)
    a = math.radians(45.0)
    assert out.v_ref_h_m_s == pytest.approx([0.5 * math.cos(a), 0.5 * math.sin(a), -0.3])  # eq. (2)
    assert out.yaw_rate_ref_rad_s == pytest.approx(0.35)  # eq. (3), NED: handle right -> turn right
    assert out.alpha_rad == pytest.approx(a)
    # no motion orthogonal to alpha (paper: "no motion command ... orthogonal to alpha")
    assert np.dot(out.v_operator_h_m_s[:2], [-math.sin(a), math.cos(a)]) == pytest.approx(0.0, abs=1e-12)


def test_obstacle_straight_ahead_repels_along_minus_x_with_potential_gradient() -> None:
    for combine in ("weighted", "sum"):   # one point: both combinations are the potential's gradient
        params = ReferenceParams(repulsion_gain_m3_s=0.2, influence_distance_m=1.0, max_repulsion_m_s=10.0,
                                 horizontal_only=False, combine=combine)  # type: ignore[arg-type]
        for d in (0.3, 0.5, 0.8):
            v = repulsion_velocity([[d, 0.0, 0.0]], params)
            expected = 0.2 * (1.0 / d - 1.0) / d**2  # -dU/dd of U = eta/2 (1/d - 1/d0)^2
            assert v == pytest.approx([-expected, 0.0, 0.0], rel=1e-12)
        # outside the influence distance: nothing
        assert repulsion_velocity([[1.2, 0.0, 0.0]], params) == pytest.approx([0.0, 0.0, 0.0])


def test_plain_sum_superposes_the_points() -> None:
    params = ReferenceParams(repulsion_gain_m3_s=0.2, influence_distance_m=1.0, max_repulsion_m_s=10.0,
                             horizontal_only=False, combine="sum")
    # two symmetric points: lateral parts cancel, forward parts add
    d, y = 0.6, 0.2
    v = repulsion_velocity([[d, y, 0.0], [d, -y, 0.0]], params)
    r = math.hypot(d, y)
    assert v == pytest.approx([-2 * 0.2 * (1 / r - 1) / r**2 * d / r, 0.0, 0.0], rel=1e-12)


def test_weighted_sum_does_not_grow_with_the_sampling_of_a_surface() -> None:
    params = ReferenceParams(repulsion_gain_m3_s=0.2, influence_distance_m=1.0, max_repulsion_m_s=10.0,
                             horizontal_only=False)
    one = repulsion_velocity([[0.5, 0.0, 0.0]], params)
    # the same point as 5 particles, or a wall face sampled by 9 points: the push stays that of one point
    assert repulsion_velocity([[0.5, 0.0, 0.0]] * 5, params) == pytest.approx(one, rel=1e-12)
    wall = [[0.5, y, 0.0] for y in np.linspace(-0.2, 0.2, 9)]
    v = repulsion_velocity(wall, params)
    assert v[1] == pytest.approx(0.0, abs=1e-12) and -v[0] <= -one[0] and -v[0] > 0.7 * -one[0]
    # symmetric pair: w = 1/2 each, so the forward part is one point's, projected
    d, y = 0.6, 0.2
    r = math.hypot(d, y)
    v = repulsion_velocity([[d, y, 0.0], [d, -y, 0.0]], params)
    assert v == pytest.approx([-0.2 * (1 / r - 1) / r**2 * d / r, 0.0, 0.0], rel=1e-12)
    # a near point dominates a far one: the weights follow the magnitudes
    near, far = [0.45, 0.0, 0.0], [0.0, 0.9, 0.0]
    v = repulsion_velocity([near, far], params)
    m_near, m_far = (0.2 * (1 / 0.45 - 1) / 0.45**2, 0.2 * (1 / 0.9 - 1) / 0.9**2)
    total = m_near + m_far
    assert v == pytest.approx([-m_near**2 / total, -m_far**2 / total, 0.0], rel=1e-12)


def test_default_gain_balances_the_full_push_just_outside_the_safe_distance() -> None:
    params = ReferenceParams()
    push = params.k_v_m_s   # full handle deflection

    def net(d: float) -> float:
        return push + float(repulsion_velocity([[d, 0.0, 0.0]] * 5, params)[0])

    assert net(0.60) > 0.1 and net(0.50) > 0.0 and net(params.safe_distance_m) < 0.0
    assert net(0.47) == pytest.approx(0.0, abs=0.03)


def test_repulsion_is_limited() -> None:
    params = ReferenceParams(repulsion_gain_m3_s=1.0, max_repulsion_m_s=0.7)
    v = repulsion_velocity([[0.1, 0.0, 0.0]] * 5, params)
    assert np.linalg.norm(v) == pytest.approx(0.7)
    assert v[0] < 0


def test_inside_safe_distance_the_component_toward_the_obstacle_is_removed() -> None:
    params = ReferenceParams(k_v_m_s=1.0, repulsion_gain_m3_s=0.0, safe_distance_m=0.45,
                             approach_gain_per_s=math.inf)   # the safe-distance rule alone
    # camera forward, obstacle 0.4 m ahead-right at 45 deg: forward push keeps only the part along (1,-1)
    p = np.array([0.4, 0.4, 0.0]) / math.sqrt(2) * 0.4 / 0.4
    out = reference_velocity(OperatorInput(qx=1.0), R_QC_FORWARD, NO_SCAN, [p], params)
    u = p / np.linalg.norm(p)
    assert np.dot(out.v_ref_h_m_s, u) == pytest.approx(0.0, abs=1e-12)
    assert out.v_ref_h_m_s == pytest.approx([0.5, -0.5, 0.0])
    assert out.constrained
    # the same obstacle at 0.5 m (outside the safe distance, no repulsion gain): untouched
    out = reference_velocity(OperatorInput(qx=1.0), R_QC_FORWARD, NO_SCAN, [u * 0.5], params)
    assert out.v_ref_h_m_s == pytest.approx([1.0, 0.0, 0.0])


def test_obstacle_straight_ahead_inside_safe_distance_stops_and_repels() -> None:
    params = ReferenceParams()  # defaults: full-stick speed below the repulsion limit
    assert params.k_v_m_s < params.max_repulsion_m_s
    out = reference_velocity(OperatorInput(qx=1.0), R_QC_FORWARD, NO_SCAN, [[0.4, 0.0, 0.0]], params)
    assert out.v_ref_h_m_s[0] < 0.0  # pushing forward still backs off
    assert out.v_ref_h_m_s[1:] == pytest.approx([0.0, 0.0])
    assert out.v_repulsion_h_m_s[0] < 0.0


def test_closing_speed_shrinks_to_zero_at_the_safe_distance() -> None:
    params = ReferenceParams(k_v_m_s=1.0, repulsion_gain_m3_s=0.0, approach_gain_per_s=2.0)
    for d in (0.85, 0.7, 0.55, 0.46):
        out = reference_velocity(OperatorInput(qx=1.0), R_QC_FORWARD, NO_SCAN, [[d, 0.0, 0.0]], params)
        assert out.v_ref_h_m_s == pytest.approx([min(1.0, 2.0 * (d - 0.45)), 0.0, 0.0])
    # beyond the influence distance, or moving away or sideways: untouched
    out = reference_velocity(OperatorInput(qx=1.0), R_QC_FORWARD, NO_SCAN, [[0.95, 0.0, 0.0]], params)
    assert out.v_ref_h_m_s == pytest.approx([1.0, 0.0, 0.0])
    v, changed = limit_speed_toward_obstacles(np.array([-0.5, 0.3, 0.0]), [[0.6, 0.0, 0.0]], 0.45, 2.0, params)
    assert not changed and v == pytest.approx([-0.5, 0.3, 0.0])


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.floats(-0.9, 0.9), st.floats(-0.9, 0.9), st.floats(-0.9, 0.9)), min_size=1, max_size=8),
       st.tuples(st.floats(-2, 2), st.floats(-2, 2), st.floats(-2, 2)), st.floats(0.1, 10.0))
def test_closing_speed_bound_holds_for_every_point(points: list[tuple[float, float, float]],
                                                   v: tuple[float, float, float], gain: float) -> None:
    p = np.array(points)
    p = p[np.linalg.norm(p, axis=1) > 1e-3]
    out, _ = limit_speed_toward_obstacles(np.array(v), p, 0.45, gain, reach_m=0.9)
    d = np.linalg.norm(p, axis=1)
    near = d < 0.9
    if np.any(near):
        u = p[near] / d[near, None]
        assert np.all(u @ out <= gain * np.maximum(d[near] - 0.45, 0.0) + 1e-6)


@pytest.mark.parametrize("push", [0.5, 1.0])
def test_pushed_vehicle_with_a_lagging_velocity_loop_rests_near_the_safe_distance(push: float) -> None:
    # a vehicle whose velocity follows the reference with a 0.3 s lag (the SITL's tracker is about that),
    # pushed at a wall 1.5 m ahead sampled by 9 points, as the camera sees it
    params = ReferenceParams()
    x, vx, dt, tau = 0.0, 0.0, 0.01, 0.3
    wall_x = 1.5
    closest = math.inf
    for _ in range(int(12.0 / dt)):
        pts = [[wall_x - x, y, 0.0] for y in np.linspace(-0.3, 0.3, 9)]
        out = reference_velocity(OperatorInput(qx=push), R_QC_FORWARD, NO_SCAN, pts, params)
        vx += (out.v_ref_h_m_s[0] - vx) * dt / tau
        x += vx * dt
        closest = min(closest, wall_x - x)
    rest = wall_x - x
    assert closest >= params.safe_distance_m - 0.02        # no coasting through the safe distance
    # "stops at about the safe distance": where the weighted repulsion balances the push (farther out for a
    # lighter push), never beyond the one-point balance distance d*
    d = np.linspace(params.safe_distance_m, params.influence_distance_m, 2001)
    m = params.repulsion_gain_m3_s * (1 / d - 1 / params.influence_distance_m) / d**2
    d_star = float(d[np.argmin(np.abs(m - push * params.k_v_m_s))])
    assert params.safe_distance_m - 0.02 <= rest <= d_star + 0.01
    assert rest <= params.safe_distance_m + 0.1
    assert abs(vx) < 0.01


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.floats(-0.44, 0.44), st.floats(-0.44, 0.44), st.floats(-0.44, 0.44)),
                min_size=1, max_size=6),
       st.tuples(st.floats(-2, 2), st.floats(-2, 2), st.floats(-2, 2)))
def test_no_component_toward_any_close_obstacle(points: list[tuple[float, float, float]],
                                               v: tuple[float, float, float]) -> None:
    p = np.array(points)
    p = p[(np.linalg.norm(p, axis=1) > 1e-3) & (np.linalg.norm(p, axis=1) < 0.45)]
    out, _ = remove_toward_close_obstacles(np.array(v), p, 0.45)
    if p.size:
        u = p / np.linalg.norm(p, axis=1)[:, None]
        assert np.all(u @ out <= 1e-6)


def test_unknown_sectors_block_horizontal_motion_toward_them() -> None:
    sectors = np.full(72, np.inf)
    sectors[0:4] = np.nan  # 0..20 deg unknown
    v, blocked = remove_toward_unknown(np.array([1.0, 0.1, -0.2]), sectors, math.radians(5))
    assert blocked and v == pytest.approx([0.0, 0.0, -0.2])
    v, blocked = remove_toward_unknown(np.array([0.0, 1.0, 0.0]), sectors, math.radians(5))  # 90 deg: known
    assert not blocked and v == pytest.approx([0.0, 1.0, 0.0])
    v, blocked = remove_toward_unknown(np.array([1.0, 0.0, 0.0]), None, 0.1)  # stale: nothing known
    assert blocked and v == pytest.approx([0.0, 0.0, 0.0])


def test_the_repulsion_never_pushes_toward_where_the_map_has_not_looked() -> None:
    """A wall seen 0.7 m ahead repels the vehicle backward (inside eq. (7)'s influence distance, outside the
    safe distance). With the sectors behind unknown the push is dropped (campaign 3, flight 1); with them
    observed and free it stays; inside the safe distance the speed law still backs the vehicle out."""
    params = ReferenceParams()
    wall = [[0.7, y, 0.0] for y in np.linspace(-0.3, 0.3, 7)]
    rear_unknown = np.full(72, np.inf)
    rear_unknown[27:46] = np.nan                   # 135..225 deg: behind, never seen
    seen = np.full(72, np.inf)
    seen[0] = 0.7
    hold = {"operator_enabled": False}
    blind = reference_velocity(OperatorInput(), R_QC_FORWARD, NO_SCAN, wall, params, sectors_m=rear_unknown, **hold)
    known = reference_velocity(OperatorInput(), R_QC_FORWARD, NO_SCAN, wall, params, sectors_m=seen, **hold)
    assert known.v_repulsion_h_m_s[0] < -0.05 and known.v_ref_h_m_s[0] < -0.05
    assert blind.v_repulsion_h_m_s == pytest.approx([0.0, 0.0, 0.0]) and blind.v_ref_h_m_s == pytest.approx([0, 0, 0])
    # the operator's push along the camera's axis (in view) is not blocked, and still stops short of the wall
    push = reference_velocity(OperatorInput(qx=1.0), R_QC_FORWARD, NO_SCAN, wall, params, sectors_m=rear_unknown)
    assert 0.0 < push.v_ref_h_m_s[0] < params.k_v_m_s
    too_close = [[0.3, y, 0.0] for y in np.linspace(-0.3, 0.3, 7)]
    out = reference_velocity(OperatorInput(), R_QC_FORWARD, NO_SCAN, too_close, params, sectors_m=rear_unknown,
                             **hold)
    assert out.v_ref_h_m_s[0] < -0.05                 # backed out of the safe distance by the speed law


def test_hold_keeps_repulsion_but_drops_operator() -> None:
    params = ReferenceParams()
    out = reference_velocity(OperatorInput(qx=1.0, qy=1.0), R_QC_FORWARD, NO_SCAN, [[0.5, 0, 0]], params,
                             operator_enabled=False)
    assert out.v_operator_h_m_s == pytest.approx([0, 0, 0])
    assert out.v_ref_h_m_s[0] < 0 and out.operator_yaw_rate_rad_s == 0.0


def test_pan_scan_rate_and_offset_follow_eqs_4_and_5() -> None:
    params = PanScanParams(amplitude_rad_s=0.5, omega_rad_s=2.0, gain=0.8, phase_rad=-2.5)
    for t in np.linspace(0.0, 5.0, 17):
        s = pan_scan(params, float(t))
        assert s.yaw_rate_rad_s == pytest.approx(0.5 * math.sin(2.0 * t))
        assert s.yaw_offset_rad == pytest.approx(0.8 * 0.25 * math.cos(2.0 * t - 2.5))
    assert swing_amplitude_rad(params) == pytest.approx(0.2)
    assert pan_scan(PanScanParams(enabled=False), 1.0) == PanScanState(0.0, 0.0, False)


def test_ideal_integrator_offset_is_the_integral_of_the_carrier() -> None:
    params = PanScanParams(amplitude_rad_s=0.6, omega_rad_s=1.5)  # gain 1, phase -pi
    t = np.linspace(0.0, 8.0, 8001)
    rates = np.array([pan_scan(params, float(x)).yaw_rate_rad_s for x in t])
    yaw = np.concatenate([[0.0], np.cumsum((rates[1:] + rates[:-1]) / 2 * np.diff(t))])
    yaw += pan_scan(params, 0.0).yaw_offset_rad  # same integration constant
    offsets = np.array([pan_scan(params, float(x)).yaw_offset_rad for x in t])
    assert np.max(np.abs(yaw - offsets)) < 1e-5


def _simulate_first_order(tau: float, delay: float, amp: float, omega: float, bias: float,
                          rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    dt = 0.002
    t = np.arange(0.0, 12.0, dt)
    cmd = 0.3 + amp * np.sin(omega * t)
    delayed = np.interp(t - delay, t, cmd, left=cmd[0])
    y = np.zeros_like(t)
    for k in range(1, t.size):  # exact discretisation of tau y' + y = u
        a = math.exp(-dt / tau)
        y[k] = a * y[k - 1] + (1 - a) * delayed[k - 1]
    gyro = y + bias + rng.normal(0.0, 0.01, t.size)
    return t, cmd, gyro


def test_identification_from_a_logged_flight_matches_the_model(rng: np.random.Generator) -> None:
    tau, delay, omega = 0.15, 0.02, 1.5
    t, cmd, gyro = _simulate_first_order(tau, delay, 0.6, omega, 0.02, rng)
    keep = t > 2.0  # after the transient
    from_log = identify_from_log(t[keep], cmd[keep], gyro[keep], omega)
    model = identify_first_order(tau, omega, delay)
    assert from_log.gain == pytest.approx(model.gain, abs=0.01)
    assert from_log.phase_rad == pytest.approx(model.phase_rad, abs=0.02)
    assert model.gain == pytest.approx(1 / math.sqrt(1 + (omega * tau) ** 2))


def test_identified_response_centres_the_real_yaw_swing(rng: np.random.Generator) -> None:
    tau, omega, amp = 0.3, 1.5, 0.6
    t, cmd, gyro = _simulate_first_order(tau, 0.0, amp, omega, 0.0, np.random.default_rng(1))
    resp = identify_first_order(tau, omega)
    params = PanScanParams(amplitude_rad_s=amp, omega_rad_s=omega, gain=resp.gain, phase_rad=resp.phase_rad)
    # measured yaw: integral of the carrier part of the response, after the transient
    carrier = gyro - 0.3 * (1 - np.exp(-t / tau))
    yaw = np.concatenate([[0.0], np.cumsum(carrier[1:] * np.diff(t))])
    keep = t > 4.0
    predicted = np.array([pan_scan(params, float(x)).yaw_offset_rad for x in t[keep]])
    measured = yaw[keep] - np.mean(yaw[keep]) + np.mean(predicted)
    assert np.max(np.abs(measured - predicted)) < 0.02 * amp / omega + 1e-3
    ideal = np.array([pan_scan(PanScanParams(amplitude_rad_s=amp, omega_rad_s=omega), float(x)).yaw_offset_rad
                      for x in t[keep]])
    assert np.max(np.abs(measured - ideal)) > 0.1 * amp / omega  # the correction matters


def test_sinusoid_fit_recovers_amplitude_phase_offset() -> None:
    t = np.linspace(0, 6, 600)
    fit = fit_sinusoid(t, 0.7 * np.sin(2.0 * t + 0.4) - 0.1, 2.0)
    assert (fit.amplitude, fit.phase_rad, fit.offset) == pytest.approx((0.7, 0.4, -0.1), abs=1e-9)
    with pytest.raises(IdentificationError):
        fit_sinusoid(t[:5], t[:5], 2.0)
    with pytest.raises(IdentificationError):
        identify_from_log(t, np.zeros_like(t), np.sin(t), 2.0)


def test_horizontal_only_ignores_floor_and_flattens_points() -> None:
    params = ReferenceParams(repulsion_gain_m3_s=0.2, influence_distance_m=1.0, max_repulsion_m_s=10.0,
                             vertical_band_m=0.5)
    # a point 0.4 m ahead and 0.3 m below: repelled horizontally as if at 0.4 m, no vertical push
    v = repulsion_velocity([[0.4, 0.0, 0.3]], params)
    assert v == pytest.approx([-0.2 * (1 / 0.4 - 1.0) / 0.4**2, 0.0, 0.0])
    # the floor 0.8 m below is outside the band: nothing (in 3D it would push up)
    assert repulsion_velocity([[0.0, 0.1, 0.8]], params) == pytest.approx([0, 0, 0])
    assert repulsion_velocity([[0.0, 0.1, 0.8]], dataclasses.replace(params, horizontal_only=False))[2] < 0
    # descending onto a point below is not blocked by the horizontal safe distance
    out, changed = remove_toward_close_obstacles(np.array([0.0, 0.0, 0.5]), [[0.0, 0.0, 0.3]], 0.45, params)
    assert not changed and out == pytest.approx([0.0, 0.0, 0.5])
    out, changed = remove_toward_close_obstacles(np.array([0.5, 0.0, 0.0]), [[0.3, 0.0, 0.2]], 0.45, params)
    assert changed and out == pytest.approx([0.0, 0.0, 0.0])


def test_floor_seen_ahead_by_a_low_vehicle_is_not_an_obstacle() -> None:
    params = ReferenceParams(vertical_band_m=0.6, floor_margin_m=0.15)
    floor_ahead = [[0.7, 0.0, 0.5], [0.8, 0.1, 0.5]]  # vehicle 0.5 m high, camera sees the floor 0.7 m ahead
    assert np.linalg.norm(repulsion_velocity(floor_ahead, params)) > 0  # height unknown: treated as obstacle
    assert repulsion_velocity(floor_ahead, params, height_m=0.5) == pytest.approx([0, 0, 0])
    # a box 0.3 m tall 0.6 m ahead of the same vehicle is still an obstacle
    box = [[0.6, 0.0, 0.2]]
    assert repulsion_velocity(box, params, height_m=0.5)[0] < 0
    out = reference_velocity(OperatorInput(), R_QC_FORWARD, NO_SCAN, floor_ahead, params, height_m=0.5)
    assert out.v_ref_h_m_s == pytest.approx([0, 0, 0])


def test_nearest_obstacle_counts_band_points_horizontally_and_others_in_3d() -> None:
    params = ReferenceParams(vertical_band_m=0.3)
    # a column seen 0.2 m below the vehicle at 0.9 m horizontally, and the floor 0.6 m below, 0.5 m ahead
    column, floor = [0.9, 0.0, 0.2], [0.5, 0.0, 0.6]
    got = nearest_obstacle([floor, column], params)
    assert got is not None
    v, d = got
    assert d == pytest.approx(math.hypot(0.5, 0.6)) and v == pytest.approx(floor)   # floor: 3D, 0.78 < 0.9
    v, d = nearest_obstacle([column, [2.0, 0.0, 0.6]], params)  # type: ignore[misc]
    assert d == pytest.approx(0.9) and v == pytest.approx([0.9, 0.0, 0.0])     # the column's own distance
    assert nearest_obstacle(None, params) is None and nearest_obstacle(np.full((2, 3), np.nan), params) is None
    v, d = nearest_obstacle([column], dataclasses.replace(params, horizontal_only=False))  # type: ignore[misc]
    assert d == pytest.approx(math.hypot(0.9, 0.2)) and v == pytest.approx(column)

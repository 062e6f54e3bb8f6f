"""The geometric SE(3) tracker (firmware_bridge.geometric_tracker) open loop and closed loop with a rigid body.

The closed-loop model: translational dynamics of paper 003 eq. (1) (``m dv/dt = m g e3 - tau R e3 + d - c v``,
NED), the attitude the MK board reaches from its setpoint through a first-order lag on roll and pitch and an
integrated, lagged yaw rate (the board flies roll/pitch angles and a yaw rate, not R_c directly).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pytest

from firmware_bridge.geometric_tracker import (
    GEOMETRIC_PARAM_SPECS,
    TM_PVA_YAW,
    TM_VA_YAW,
    GeometricGains,
    GeometricTracker,
    SetpointRejected,
    TrackerKind,
    TrackingState,
    TrajectoryTarget,
    attitude_from_force,
    decode_trajectory_setpoint,
    geometric_gains_from_params,
    make_tracker,
)
from firmware_bridge.velocity_tracker import TrackerGains, VelocityTracker
from quadlink.frames import GRAVITY_M_S2, R_from_euler, Rz, euler_from_R
from quadlink.lie import angle_between_rad
from quadlink.mavlink import mavlink
from quadlink.trajectory import minimum_snap

MASS_KG = 1.0
T_MAX_N = 20.0
DT_S = 0.01
SUBSTEPS = 5
OVAL_NED_M = np.array([[-1.0, -1.5, -1.2], [0.0, -0.5, -1.2], [0.0, 0.5, -1.2], [-1.0, -1.5, -1.2]])
OVAL_DURATIONS_S = (3.0, 1.7, 4.3)


@dataclass
class RigidBody:
    """Translational rigid body + the board's attitude response (roll/pitch lag, yaw-rate integration)."""

    p: np.ndarray = field(default_factory=lambda: np.zeros(3))
    v: np.ndarray = field(default_factory=lambda: np.zeros(3))
    roll: float = 0.0
    pitch: float = 0.0
    yaw: float = 0.0
    yaw_rate: float = 0.0
    mass_kg: float = MASS_KG
    attitude_tau_s: float = 0.06
    drag_n_s_m: tuple[float, float, float] = (0.25, 0.25, 0.35)

    @property
    def R(self) -> np.ndarray:
        return R_from_euler(self.roll, self.pitch, self.yaw)

    def step(self, roll_c: float, pitch_c: float, yaw_rate_c: float, thrust_fraction: float,
             force_n: np.ndarray | None = None) -> None:
        h = DT_S / SUBSTEPS
        a = 1.0 - math.exp(-h / self.attitude_tau_s)
        d = np.zeros(3) if force_n is None else np.asarray(force_n, dtype=float)
        for _ in range(SUBSTEPS):
            self.roll += a * (roll_c - self.roll)
            pitch_rate = a * (pitch_c - self.pitch) / h
            self.pitch += h * pitch_rate
            self.yaw_rate += a * (yaw_rate_c - self.yaw_rate)  # the board's yaw loop tracks the body z rate r
            # ZYX kinematics with q = theta_dot cos(phi) + psi_dot cos(theta) sin(phi) and
            # r = -theta_dot sin(phi) + psi_dot cos(theta) cos(phi):  psi_dot = (r + theta_dot sin phi) / (c_th c_ph)
            self.yaw += h * (self.yaw_rate + pitch_rate * math.sin(self.roll)) \
                / (math.cos(self.pitch) * math.cos(self.roll))
            acc = GRAVITY_M_S2 * np.array([0.0, 0.0, 1.0]) - thrust_fraction * T_MAX_N / self.mass_kg \
                * (self.R @ np.array([0.0, 0.0, 1.0])) + (d - np.asarray(self.drag_n_s_m) * self.v) / self.mass_kg
            self.p = self.p + self.v * h + 0.5 * acc * h * h
            self.v = self.v + acc * h


def fly(tracker: GeometricTracker, body: RigidBody, target_at, seconds: float, position: bool = True):
    """Closed loop at 100 Hz; returns arrays t, p, v, p_d, v_d."""
    rows = []
    for k in range(int(round(seconds / DT_S))):
        t = k * DT_S
        target = target_at(t)
        state = TrackingState(body.v.copy(), body.R, body.p.copy() if position else None)
        out = tracker.step(DT_S, target, state)
        c = out.attitude
        rows.append((t, body.p.copy(), body.v.copy(), np.asarray(target.p_ned_m if target.p_ned_m is not None
                                                                   else np.full(3, np.nan)),
                     np.asarray(target.v_ned_m_s), c))
        body.step(c.roll_rad, c.pitch_rad, c.yaw_rate_rad_s, c.thrust_fraction)
    t = np.array([r[0] for r in rows])
    return t, np.array([r[1] for r in rows]), np.array([r[2] for r in rows]), np.array([r[3] for r in rows]), \
        np.array([r[4] for r in rows]), [r[5] for r in rows]


def hold(p_d, yaw=0.0):
    return lambda t: TrajectoryTarget(np.zeros(3), np.zeros(3), np.asarray(p_d, dtype=float), yaw_rad=yaw)


def test_hover_is_exactly_level_at_hover_thrust() -> None:
    tr = GeometricTracker(MASS_KG, T_MAX_N)
    p_d = np.array([0.2, 2.2, -1.2])
    for _ in range(3):
        out = tr.step(DT_S, TrajectoryTarget(np.zeros(3), np.zeros(3), p_d, yaw_rad=0.0),
                      TrackingState(np.zeros(3), np.eye(3), p_d.copy()))
    assert angle_between_rad(out.R_c, np.eye(3)) < 1e-12
    assert out.thrust_n == pytest.approx(MASS_KG * GRAVITY_M_S2, abs=1e-12)
    assert out.attitude.thrust_fraction == pytest.approx(tr.hover_thrust_fraction, abs=1e-12)
    assert out.attitude.roll_rad == 0.0 and out.attitude.pitch_rad == 0.0
    assert out.attitude.yaw_rate_rad_s == pytest.approx(0.0, abs=1e-12)
    np.testing.assert_allclose(out.omega_c_q_rad_s, 0.0, atol=1e-12)
    np.testing.assert_allclose(out.f_des_n, [0.0, 0.0, -MASS_KG * GRAVITY_M_S2], atol=1e-12)
    assert not out.attitude.saturated
    # with a heading: R_c is that heading, level
    tr.reset()
    out = tr.step(DT_S, TrajectoryTarget(np.zeros(3), np.zeros(3), p_d, yaw_rad=0.7),
                  TrackingState(np.zeros(3), Rz(0.7), p_d.copy()))
    assert angle_between_rad(out.R_c, Rz(0.7)) < 1e-12


def test_thrust_is_the_desired_force_projected_on_the_measured_body_z() -> None:
    """Eq. (4): tau = -f_des . R e3 — m g cos(tilt) at hover with a tilted body, not m g / cos(tilt)."""
    tr = GeometricTracker(MASS_KG, T_MAX_N, gains=GeometricGains(k_i_1_s2=0.0))
    tilt = math.radians(20.0)
    R = R_from_euler(tilt, 0.0, 0.3)
    out = tr.step(DT_S, TrajectoryTarget(np.zeros(3), yaw_rad=0.3), TrackingState(np.zeros(3), R))
    assert out.thrust_n == pytest.approx(MASS_KG * GRAVITY_M_S2 * math.cos(tilt), rel=1e-12)
    assert angle_between_rad(out.R_c, Rz(0.3)) < 1e-12  # and it commands level at the heading


def test_commanded_attitude_points_the_thrust_along_the_desired_force() -> None:
    tr = GeometricTracker(MASS_KG, T_MAX_N, gains=GeometricGains(k_i_1_s2=0.0))
    a_d = np.array([2.0, -1.0, -0.5])  # north, west, up
    out = tr.step(DT_S, TrajectoryTarget(np.zeros(3), a_d, yaw_rad=0.4), TrackingState(np.zeros(3), Rz(0.4)))
    f = MASS_KG * (a_d - GRAVITY_M_S2 * np.array([0.0, 0.0, 1.0]))
    np.testing.assert_allclose(out.f_des_n, f, atol=1e-12)
    np.testing.assert_allclose(out.R_c @ np.array([0.0, 0.0, 1.0]), -f / np.linalg.norm(f), atol=1e-12)
    np.testing.assert_allclose(out.R_c.T @ out.R_c, np.eye(3), atol=1e-12)
    assert np.linalg.det(out.R_c) == pytest.approx(1.0)
    b1c = out.R_c[:, 0]
    assert math.atan2(b1c[1], b1c[0]) == pytest.approx(0.4, abs=1e-12)  # heading kept
    # the board gets R_c as ZYX roll/pitch at its heading: rebuilding from them and the heading gives R_c back
    roll, pitch, yaw = euler_from_R(out.R_c)
    assert yaw == pytest.approx(0.4, abs=1e-12)
    assert (roll, pitch) == pytest.approx((out.attitude.roll_rad, out.attitude.pitch_rad), abs=1e-12)
    assert angle_between_rad(R_from_euler(out.attitude.roll_rad, out.attitude.pitch_rad, 0.4), out.R_c) < 1e-12
    assert pitch < 0.0  # accelerating north = nose down in FRD/NED
    # while the vehicle still faces elsewhere, roll/pitch put its thrust axis on R_c's at *its* heading
    tr.reset()
    out = tr.step(DT_S, TrajectoryTarget(np.zeros(3), a_d, yaw_rad=0.4), TrackingState(np.zeros(3), Rz(-0.6)))
    b3 = R_from_euler(out.attitude.roll_rad, out.attitude.pitch_rad, -0.6) @ np.array([0.0, 0.0, 1.0])
    np.testing.assert_allclose(b3, out.R_c[:, 2], atol=1e-12)


def test_attitude_from_force_degenerate_heading() -> None:
    for f in ([-1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 0.0]):  # thrust axis along b1d, along y_d, none
        R = attitude_from_force(f, [1.0, 0.0, 0.0])
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)
        if np.linalg.norm(f) > 0:
            np.testing.assert_allclose(R[:, 2], -np.asarray(f), atol=1e-12)


@pytest.mark.parametrize("axis", [2, 1, 0])  # paper 003's order: z, y, x
def test_recovers_from_a_0p7_m_offset_within_3_s(axis: int) -> None:
    p_d = np.array([0.2, 2.2, -1.2])
    body = RigidBody(p=p_d.copy())
    body.p[axis] += 0.7
    tr = GeometricTracker(MASS_KG, T_MAX_N)
    t, p, v, _, _, _ = fly(tr, body, hold(p_d), 6.0)
    err = np.linalg.norm(p - p_d, axis=1)
    back = t[np.argmax(err < 0.05)] if np.any(err < 0.05) else math.inf
    assert back < 3.0, f"back within 5 cm after {back:.2f} s"
    assert np.all(err[t >= 3.0] < 0.05)  # and stays there
    assert np.max(err[t > 4.0]) < 0.02  # the integral's small overshoot decays
    assert err.max() <= 0.7 + 1e-9  # no overshoot beyond the start


def test_tracks_the_papers_oval_with_small_error() -> None:
    traj = minimum_snap(OVAL_NED_M, OVAL_DURATIONS_S)

    def target(t: float) -> TrajectoryTarget:
        s = traj.sample(t)
        return TrajectoryTarget(s.v_m_s, s.a_m_s2, s.p_m, yaw_rad=0.0)

    body = RigidBody(p=OVAL_NED_M[0].copy())
    tr = GeometricTracker(MASS_KG, T_MAX_N)
    t, p, v, p_d, v_d, _ = fly(tr, body, target, traj.duration_s)
    rmse_p = np.sqrt(np.mean((p - p_d) ** 2, axis=0))
    rmse_v = np.sqrt(np.mean((v - v_d) ** 2, axis=0))
    print(f"oval: position RMSE {rmse_p} m, velocity RMSE {rmse_v} m/s")
    assert np.all(rmse_p < 0.03), rmse_p  # paper 003 Table 4: 0.057 / 0.066 / 0.013 m (a real flight)
    assert np.all(rmse_v < 0.05), rmse_v  # Table 5: 0.063 / 0.083 / 0.021 m/s
    # without the acceleration feed-forward the same loop lags far more: the feed-forward is doing the work
    tr2 = GeometricTracker(MASS_KG, T_MAX_N)
    body2 = RigidBody(p=OVAL_NED_M[0].copy())

    def no_ff(t: float) -> TrajectoryTarget:
        s = traj.sample(t)
        return TrajectoryTarget(s.v_m_s, np.zeros(3), s.p_m, yaw_rad=0.0)

    _, p2, _, _, _, _ = fly(tr2, body2, no_ff, traj.duration_s)
    rmse_p2 = np.sqrt(np.mean((p2 - p_d) ** 2, axis=0))
    assert rmse_p2[:2].max() > 2.0 * rmse_p[:2].max()


def test_integral_removes_the_offset_of_a_wrong_mass() -> None:
    p_d = np.array([0.0, 0.0, -1.0])
    heavy = RigidBody(p=p_d.copy(), mass_kg=1.2)  # the tracker believes 1.0 kg
    t, p, _, _, _, _ = fly(GeometricTracker(MASS_KG, T_MAX_N), heavy, hold(p_d), 20.0)
    with_integral_m = abs(p[-1, 2] - p_d[2])
    plain = RigidBody(p=p_d.copy(), mass_kg=1.2)
    t, p0, _, _, _, _ = fly(GeometricTracker(MASS_KG, T_MAX_N, gains=GeometricGains(k_i_1_s2=0.0)), plain,
                            hold(p_d), 20.0)
    # eq. (4) alone sags until k_x e_z (per unit of believed mass) makes up the missing weight: 0.2 g / k_x
    assert p0[-1, 2] - p_d[2] == pytest.approx(0.2 * GRAVITY_M_S2 / 4.0, rel=0.02)
    assert with_integral_m < 0.1 * (p0[-1, 2] - p_d[2])


def test_turns_to_the_commanded_heading_through_the_boards_yaw_rate() -> None:
    p_d = np.array([0.0, 0.0, -1.0])
    body = RigidBody(p=p_d.copy())
    fly(GeometricTracker(MASS_KG, T_MAX_N), body, hold(p_d, yaw=1.0), 6.0)
    assert body.yaw == pytest.approx(1.0, abs=0.01)
    assert np.linalg.norm(body.p - p_d) < 0.01
    # a yaw-rate target turns b1d at that rate: Omega_c's z carries it to the board
    body = RigidBody(p=p_d.copy())
    tr = GeometricTracker(MASS_KG, T_MAX_N)
    rate = 0.5
    _, _, _, _, _, cmds = fly(tr, body, lambda t: TrajectoryTarget(np.zeros(3), p_ned_m=p_d, yaw_rate_rad_s=rate),
                              4.0)
    assert body.yaw == pytest.approx(4.0 * rate, abs=0.1)
    assert tr.last is not None and tr.last.omega_c_q_rad_s[2] == pytest.approx(rate, abs=0.02)


def test_drop_in_update_has_the_pid_trackers_signature_and_uses_the_acceleration_feed_forward() -> None:
    """update() in H: velocity + acceleration references; a velocity ramp is tracked with far less lag with a_d."""
    def ramp(tracker, with_ff: bool) -> float:
        body = RigidBody(p=np.zeros(3))
        errs = []
        for k in range(300):
            t = k * DT_S
            a_ref = np.array([0.5, -0.3, 0.0]) if t < 2.0 else np.zeros(3)
            v_ref = a_ref * t if t < 2.0 else np.array([1.0, -0.6, 0.0])
            kwargs = {"a_ref_h": a_ref} if with_ff else {}
            cmd = tracker.update(DT_S, v_ref, 0.0, body.v.copy(), body.roll, body.pitch, **kwargs)
            body.step(cmd.roll_rad, cmd.pitch_rad, cmd.yaw_rate_rad_s, cmd.thrust_fraction)
            errs.append(np.linalg.norm(body.v - (v_ref if t >= 2.0 else a_ref * (t + DT_S))))
        return float(np.sqrt(np.mean(np.square(errs[:200]))))

    geo_ff = ramp(GeometricTracker(MASS_KG, T_MAX_N), True)
    geo = ramp(GeometricTracker(MASS_KG, T_MAX_N), False)
    pid = ramp(VelocityTracker(MASS_KG, T_MAX_N), False)
    assert geo_ff < 0.5 * geo
    assert geo_ff < 0.5 * pid
    # the yaw rate passes through, clamped like the PID tracker's
    cmd = GeometricTracker(MASS_KG, T_MAX_N).update(DT_S, np.zeros(3), 10.0, np.zeros(3), 0.0, 0.0)
    assert cmd.yaw_rate_rad_s == pytest.approx(TrackerGains().max_yaw_rate_rad_s)


def test_limits_bound_tilt_and_thrust() -> None:
    lim = TrackerGains(max_tilt_rad=math.radians(20.0))
    tr = GeometricTracker(MASS_KG, T_MAX_N, lim)
    out = tr.step(DT_S, TrajectoryTarget(np.zeros(3), p_ned_m=np.array([50.0, 0.0, -1.0]), yaw_rad=0.0),
                  TrackingState(np.zeros(3), np.eye(3), np.array([0.0, 0.0, -1.0])))
    tilt = math.acos(out.R_c[2, 2])
    assert tilt == pytest.approx(math.radians(20.0), abs=1e-9)
    assert out.attitude.saturated
    out = tr.step(DT_S, TrajectoryTarget(np.zeros(3), p_ned_m=np.array([0.0, 0.0, -60.0]), yaw_rad=0.0),
                  TrackingState(np.zeros(3), np.eye(3), np.zeros(3)))
    assert out.attitude.thrust_fraction <= lim.thrust_max_fraction + 1e-12


def test_selected_by_parameter() -> None:
    lim = TrackerGains()
    assert isinstance(make_tracker(0, MASS_KG, T_MAX_N, lim), VelocityTracker)
    assert isinstance(make_tracker(TrackerKind.GEOMETRIC, MASS_KG, T_MAX_N, lim), GeometricTracker)
    with pytest.raises(ValueError):
        make_tracker(2, MASS_KG, T_MAX_N, lim)
    names = {p.name for p in GEOMETRIC_PARAM_SPECS}
    assert "BRG_TRACKER" in names
    g = geometric_gains_from_params({"BRG_GEO_KX": 2.5, "MPC_XY_VEL_P": 9.0})
    assert g.k_x_1_s2 == 2.5 and g.k_v_1_s == GeometricGains().k_v_1_s
    from firmware_bridge.params import PARAM_SPECS

    bridge = [p.name for p in PARAM_SPECS]
    assert names <= set(bridge) and len(bridge) == len(set(bridge))  # wired into the bridge's table, no clash


# ---------------------------------------------------------------------- setpoint decoding
def _msg(type_mask: int, frame: int = mavlink.MAV_FRAME_LOCAL_NED, p=(1.0, 2.0, -1.5), v=(0.5, -0.2, 0.1),
         a=(0.3, 0.0, -0.2), yaw=0.8, yaw_rate=0.0):
    """A SET_POSITION_TARGET_LOCAL_NED through the real encoder and decoder (as MAVSDK/pymavlink send it)."""
    enc = mavlink.MAVLink(None, 255, 190)
    m = mavlink.MAVLink_set_position_target_local_ned_message(0, 1, 1, frame, type_mask, *p, *v, *a, yaw, yaw_rate)
    buf = m.pack(enc)
    dec = mavlink.MAVLink(None)
    return dec.parse_char(buf)


def test_decodes_position_velocity_acceleration_setpoints_as_px4() -> None:
    tgt = decode_trajectory_setpoint(_msg(TM_PVA_YAW), yaw_rad=0.0)
    np.testing.assert_allclose(tgt.p_ned_m, [1.0, 2.0, -1.5], atol=1e-6)
    np.testing.assert_allclose(tgt.v_ned_m_s, [0.5, -0.2, 0.1], atol=1e-6)
    np.testing.assert_allclose(tgt.a_ned_m_s2, [0.3, 0.0, -0.2], atol=1e-6)
    assert tgt.yaw_rad == pytest.approx(0.8) and tgt.yaw_rate_rad_s is None
    tgt = decode_trajectory_setpoint(_msg(TM_VA_YAW), yaw_rad=0.0)
    assert tgt.p_ned_m is None
    np.testing.assert_allclose(tgt.a_ned_m_s2, [0.3, 0.0, -0.2], atol=1e-6)
    # velocity only (MAVSDK set_velocity_ned, 3527 = velocity + yaw... here 2503): a_d = 0
    tgt = decode_trajectory_setpoint(_msg(2503), yaw_rad=0.0)
    np.testing.assert_allclose(tgt.a_ned_m_s2, 0.0)
    # yaw rate instead of yaw (MAVSDK set_velocity_body: 1479)
    tgt = decode_trajectory_setpoint(_msg(1479, mavlink.MAV_FRAME_BODY_NED, yaw_rate=0.25), yaw_rad=0.0)
    assert tgt.yaw_rate_rad_s == pytest.approx(0.25) and tgt.yaw_rad is None


def test_body_frame_velocity_and_acceleration_are_rotated_by_yaw() -> None:
    yaw = math.radians(90.0)
    tgt = decode_trajectory_setpoint(_msg(TM_VA_YAW, mavlink.MAV_FRAME_BODY_NED, v=(1.0, 0.0, 0.0),
                                          a=(0.0, 1.0, 0.0)), yaw_rad=yaw)
    np.testing.assert_allclose(tgt.v_ned_m_s, [0.0, 1.0, 0.0], atol=1e-6)  # forward, facing east
    np.testing.assert_allclose(tgt.a_ned_m_s2, [-1.0, 0.0, 0.0], atol=1e-6)  # right, facing east = south
    v_h, a_h = tgt.in_h(yaw)
    np.testing.assert_allclose(v_h, [1.0, 0.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(a_h, [0.0, 1.0, 0.0], atol=1e-6)


@pytest.mark.parametrize("type_mask, frame", [
    (TM_PVA_YAW | 0x200, mavlink.MAV_FRAME_LOCAL_NED),  # force
    (TM_PVA_YAW | 0x008, mavlink.MAV_FRAME_LOCAL_NED),  # partial velocity
    (TM_PVA_YAW | 0x040, mavlink.MAV_FRAME_LOCAL_NED),  # partial acceleration
    (TM_PVA_YAW | 0x038, mavlink.MAV_FRAME_LOCAL_NED),  # no velocity
    (TM_PVA_YAW, mavlink.MAV_FRAME_BODY_NED),  # position in a body frame
    (TM_VA_YAW, mavlink.MAV_FRAME_GLOBAL),  # frame
])
def test_setpoints_it_cannot_fly_are_rejected(type_mask: int, frame: int) -> None:
    with pytest.raises(SetpointRejected):
        decode_trajectory_setpoint(_msg(type_mask, frame), yaw_rad=0.0)


def test_non_finite_values_are_rejected() -> None:
    with pytest.raises(SetpointRejected):
        decode_trajectory_setpoint(_msg(TM_VA_YAW, a=(math.nan, 0.0, 0.0)), yaw_rad=0.0)

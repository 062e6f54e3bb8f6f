"""Force law, eqs. (15)-(18), saturation and the link-loss fade."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from teleop.config import DeviceConfig, ForceConfig, MappingConfig
from teleop.force import LinkFade, VehicleMotion, force_law, link_ok, q_tilde, saturate
from teleop.mapping import command_to_velocity, map_device_to_command, mapping_gains

DEV = DeviceConfig()
MAP = MappingConfig()
GAINS = mapping_gains(MAP, DEV)
FORCE = ForceConfig(B_n_s_m=(3.0, 2.0, 1.0), K_f_n_m=(20.0, 10.0, 5.0), K_n_m=(60.0, 40.0, 30.0))


def test_q_tilde_projects_velocity_on_alpha_eq16_18():
    alpha = math.radians(30.0)
    motion = VehicleMotion((0.6, 0.2, -0.1), alpha, 0.0, 0.0)
    qt = q_tilde(motion, GAINS)
    assert qt[0] == pytest.approx((0.6 * math.cos(alpha) + 0.2 * math.sin(alpha)) / GAINS.k_v_xy_per_s)
    assert qt[2] == pytest.approx(-0.1 / GAINS.k_v_z_per_s)
    # velocity orthogonal to alpha does not appear (eq. (16))
    ortho = VehicleMotion((-math.sin(alpha), math.cos(alpha), 0.0), alpha, 0.0, 0.0)
    assert q_tilde(ortho, GAINS)[0] == pytest.approx(0.0, abs=1e-12)


def test_q_tilde_removes_pan_scan_component_eq17():
    with_ps = VehicleMotion((0, 0, 0), 0.0, 0.5 + 0.3, 0.3)  # 0.3 rad/s of pan-scan on top of 0.5 operator
    without = VehicleMotion((0, 0, 0), 0.0, 0.5, 0.0)
    assert q_tilde(with_ps, GAINS)[1] == pytest.approx(q_tilde(without, GAINS)[1])


@given(st.floats(-0.08, 0.08), st.floats(-0.08, 0.08), st.floats(-0.08, 0.08))
@settings(max_examples=60, deadline=None)
def test_no_cue_when_the_vehicle_does_what_is_commanded(qx, qy, qz):
    """q~ inverts the real mapping (device and companion dead-bands included): a vehicle that does exactly
    what the handle commands gives q~ = q wherever the handle commands motion."""
    q = np.array([qx, qy, qz])
    cmd = map_device_to_command(q, MAP, DEV)
    forward, v_down, yaw_rate = command_to_velocity(cmd, MAP)
    alpha = 0.7
    motion = VehicleMotion((forward * math.cos(alpha), forward * math.sin(alpha), v_down), alpha, yaw_rate, 0.0)
    qt = q_tilde(motion, GAINS, q)
    db = np.asarray(MAP.deadband_m)
    onset = db + MAP.companion_deadband * (np.asarray(DEV.workspace_m) - db)
    np.testing.assert_allclose(GAINS.command_onset_m, onset)
    # inside the onset the vehicle is commanded to rest, and resting it is q~ = q as well
    # rounding of MANUAL_CONTROL to integers: 1/1000 of full scale (1/500 for z)
    tol = np.array([0.076 / 1000, 0.076 / 1000, 0.076 / 500]) + 1e-9
    assert np.all(np.abs(qt - q) <= tol)
    # the paper's eq. (16) as written (no dead-band) leaves the onset as a standing cue
    literal = q_tilde(motion, GAINS)
    np.testing.assert_allclose(np.abs(q - literal), np.minimum(np.abs(q), onset), atol=float(tol.max()))


def test_a_push_held_by_the_spring_alone_once_the_vehicle_follows():
    """1 N on the handle, the vehicle at the commanded speed: the force law's equilibrium is q = F / K_f.

    The shipped gains (K 60 N/m) with the literal eq. (16) held the handle at about 0.022 m instead of
    0.05 m: the dead-band's offset was a standing 0.38 N against the push (the demo's approach stalled)."""
    cfg = ForceConfig()
    for q_x in np.linspace(0.0, 0.08, 161):
        q = np.array([q_x, 0.0, 0.0])
        forward, _, _ = command_to_velocity(map_device_to_command(q, MAP, DEV), MAP)
        qt = q_tilde(VehicleMotion((forward, 0.0, 0.0), 0.0, 0.0, 0.0), GAINS, q)
        if force_law(q, np.zeros(3), qt, cfg, 12.0)[0] + 1.0 <= 0.0:   # the spring balances 1 N here
            break
    assert q_x == pytest.approx(1.0 / cfg.K_f_n_m[0], abs=0.001)


def test_force_law_terms_eq15():
    q = np.array([0.02, -0.01, 0.005])
    qd = np.array([0.1, 0.2, -0.3])
    qt = np.array([0.005, 0.0, 0.0])
    tau = force_law(q, qd, qt, FORCE, force_limit_n=100.0)
    B, Kf, K = (np.array(v) for v in (FORCE.B_n_s_m, FORCE.K_f_n_m, FORCE.K_n_m))
    np.testing.assert_allclose(tau, -B * qd - Kf * q - K * (q - qt), rtol=1e-12)


def test_force_opposes_push_when_vehicle_is_blocked():
    """Operator pushes forward, the vehicle does not move (repulsion): the force pushes the handle back."""
    q = np.array([0.05, 0.0, 0.0])
    blocked = q_tilde(VehicleMotion((0.0, 0.0, 0.0), 0.0, 0.0, 0.0), GAINS)
    moving = q_tilde(VehicleMotion((0.55, 0.0, 0.0), 0.0, 0.0, 0.0), GAINS)
    tau_blocked = force_law(q, np.zeros(3), blocked, FORCE, 12.0)
    tau_moving = force_law(q, np.zeros(3), moving, FORCE, 12.0)
    assert tau_blocked[0] < 0.0
    assert tau_blocked[0] < tau_moving[0] - 2.0     # the cue adds K (q - q~) ~ 60 N/m x 0.05 m = 3 N


def test_saturation_keeps_direction():
    f = saturate(np.array([30.0, -40.0, 0.0]), 10.0)
    assert np.linalg.norm(f) == pytest.approx(10.0)
    np.testing.assert_allclose(f / np.linalg.norm(f), np.array([0.6, -0.8, 0.0]))
    np.testing.assert_allclose(saturate(np.array([1.0, 2.0, 2.0]), 10.0), [1.0, 2.0, 2.0])
    assert np.all(saturate(np.array([np.nan, 0.0, 0.0]), 10.0) == 0.0)
    tau = force_law(np.array([1.0, 1.0, 1.0]), np.zeros(3), None, FORCE, force_limit_n=12.0)
    assert np.linalg.norm(tau) == pytest.approx(12.0)


def test_link_loss_fades_force_without_a_jump():
    fade = LinkFade(fade_time_s=0.5, initial_gain=1.0)
    dt = 1e-3
    q = np.array([0.04, 0.0, 0.0])
    qt = np.zeros(3)
    forces, gains = [], []
    for k in range(1500):
        t = k * dt
        ok = link_ok(min(t, 0.2), t, timeout_s=0.1)   # feedback every tick until t = 0.2 s, then none
        gains.append(fade.update(ok, t))
        forces.append(force_law(q, np.zeros(3), qt, FORCE, 12.0, gains[-1])[0])
    gains_a, forces_a = np.array(gains), np.array(forces)
    assert gains_a[0] == 1.0 and gains_a[-1] == 0.0
    assert np.max(np.abs(np.diff(gains_a))) <= dt / 0.5 + 1e-12      # rate-limited
    full = abs(forces_a[0])
    assert np.max(np.abs(np.diff(forces_a))) <= full * dt / 0.5 + 1e-9  # never a jump
    # link lost at 0.2 + 0.1 (timeout), zero 0.5 s later
    assert gains_a[int(0.29 / dt)] == 1.0
    assert gains_a[int(0.55 / dt)] == pytest.approx(0.5, abs=0.01)
    assert gains_a[int(0.81 / dt)] == 0.0


def test_fade_back_in_when_link_returns():
    fade = LinkFade(fade_time_s=1.0)
    assert fade.update(True, 0.0) == 0.0
    assert fade.update(True, 0.25) == pytest.approx(0.25)
    assert fade.update(False, 0.35) == pytest.approx(0.15)
    assert fade.update(True, 10.0) == 1.0
    assert not link_ok(None, 1.0, 0.5)


def test_cue_gain_scales_only_the_haptic_cue():
    q = np.array([0.03, -0.01, 0.02])
    qd = np.array([0.05, 0.0, -0.1])
    qt = np.array([0.01, 0.0, 0.0])
    B, Kf, K = (np.array(v) for v in (FORCE.B_n_s_m, FORCE.K_f_n_m, FORCE.K_n_m))
    np.testing.assert_allclose(force_law(q, qd, qt, FORCE, 100.0, cue_gain=0.0), -B * qd - Kf * q)
    np.testing.assert_allclose(force_law(q, qd, qt, FORCE, 100.0, cue_gain=0.5),
                               -B * qd - Kf * q - 0.5 * K * (q - qt))

"""SITL vehicle + firmware against analytic cases (pybullet DIRECT, no sockets)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from quadlink.frames import GRAVITY_M_S2, Rz, euler_from_R
from quadlink.mk.flags import BoardFlightState
from quadlink.vehicle import VehicleConfig, load_vehicle
from sim_sitl.config import SitlConfig, load_scenario, load_sitl_config
from sim_sitl.firmware import AttitudeCommand
from sim_sitl.motors import body_wrench, mix, rotor_layout
from sim_sitl.vehicle_sim import SimVehicle


@pytest.fixture
def sim():
    vehicle = load_vehicle()
    s = SimVehicle(vehicle, load_sitl_config(), load_scenario("empty"), np.random.default_rng(3))
    s.power_up()   # the board calibrates its gyros on the ground before a test places it in the air
    yield s
    s.close()


def _airborne(sim: SimVehicle, z_m: float = -1.5, yaw_rad: float = 0.0) -> None:
    sim.world.reset_pose(np.array([0.0, 0.0, z_m]), Rz(yaw_rad))
    sim.world.motor_thrust_n[:] = sim.vehicle.mass_kg * GRAVITY_M_S2 / 4.0  # spun up at hover


def _fly(sim: SimVehicle, seconds: float, cmd_at) -> list:
    out = []
    for _ in range(round(seconds / sim.tick_s)):
        if sim.ticks % 5 == 0:  # 100 Hz setpoints, like the bridge
            sim.on_setpoint(cmd_at(sim.t_s))
        out.append(sim.tick())
    return out


@pytest.mark.parametrize("frame", ["x", "plus"])
def test_mixer_reproduces_the_demanded_wrench(frame):
    vehicle = VehicleConfig(frame=frame)
    layout = rotor_layout(vehicle)
    tau = np.array([0.05, -0.08, 0.02])
    thrusts = mix(layout, 10.0, tau, 0.0, 5.0)
    total, torque = body_wrench(layout, thrusts)
    assert total == pytest.approx(10.0, abs=1e-9)
    np.testing.assert_allclose(torque, tau, atol=1e-9)


def test_mixer_keeps_attitude_authority_when_saturated():
    layout = rotor_layout(VehicleConfig())
    thrusts = mix(layout, 19.5, np.array([0.3, 0.0, 0.0]), 0.4, 5.0)  # near full collective + big roll
    assert thrusts.max() <= 5.0 + 1e-12 and thrusts.min() >= 0.4 - 1e-12
    _, torque = body_wrench(layout, thrusts)
    assert torque[0] == pytest.approx(0.3, rel=1e-6)  # collective gave way, roll torque kept


def test_hover_thrust_fraction_holds_altitude(sim):
    _airborne(sim)
    hover = sim.vehicle.hover_thrust_fraction
    assert hover * sim.vehicle.max_total_thrust_n == pytest.approx(sim.vehicle.mass_kg * GRAVITY_M_S2)
    res = _fly(sim, 2.0, lambda t: AttitudeCommand(0.0, 0.0, 0.0, hover, True, 0))
    z = np.array([r.state.p_ned_m[2] for r in res])
    assert abs(z[-1] - z[0]) < 0.02
    assert abs(res[-1].state.v_ned_m_s[2]) < 0.02
    assert res[-1].firmware.flight_state == 1


def test_free_fall_matches_gravity_with_linear_drag(sim):
    sim.world.reset_pose(np.array([0.0, 0.0, -2.5]), np.eye(3))
    res = [sim.tick() for _ in range(250)]  # disarmed: motors off, 0.5 s
    t = res[-1].t_s + sim.tick_s
    m, c = sim.vehicle.mass_kg, sim.vehicle.linear_drag_n_s_m[2]
    dz_expected = m * GRAVITY_M_S2 / c * t - m * m * GRAVITY_M_S2 / (c * c) * (1.0 - math.exp(-c * t / m))
    dz = sim.world.state.p_ned_m[2] - (-2.5)
    assert dz == pytest.approx(dz_expected, abs=0.01)
    assert dz == pytest.approx(0.5 * GRAVITY_M_S2 * t * t, rel=0.1)  # mostly gravity
    # an accelerometer in free fall reads only the drag
    assert np.linalg.norm(res[-1].imu.accel_q_m_s2) < 0.25 * GRAVITY_M_S2


def test_roll_step_settles_with_bounded_overshoot(sim):
    _airborne(sim)
    hover = sim.vehicle.hover_thrust_fraction
    step_rad = 0.2
    res = _fly(sim, 2.0, lambda t: AttitudeCommand(step_rad if t >= 0.2 else 0.0, 0.0, 0.0, hover, True, 0))
    t = np.array([r.t_s for r in res]) - 0.2
    roll = np.array([euler_from_R(r.state.R_ned_q)[0] for r in res])
    assert roll.max() < step_rad * 1.25  # overshoot < 25 %
    # settled within 1 s: to 5 % on the true attitude once; on the board's own estimate (issue 29) its accelerometer
    # correction leaks a held tilt back toward level (the firmware's ~6 % per 0.5 s), so 15 % of the step
    outside = np.where(np.abs(roll - step_rad) > 0.15 * step_rad)[0]
    assert t[outside[-1]] < 1.0
    assert t[np.argmax(roll > 0.9 * step_rad)] < 0.4  # rise time
    # rolling right (positive roll, FRD) accelerates the vehicle east (+y NED)
    assert res[-1].state.v_ned_m_s[1] > 0.5


def test_pitch_step_moves_backwards_for_nose_up(sim):
    _airborne(sim)
    hover = sim.vehicle.hover_thrust_fraction
    res = _fly(sim, 1.5, lambda t: AttitudeCommand(0.0, 0.15, 0.0, hover, True, 0))
    assert euler_from_R(res[-1].state.R_ned_q)[1] == pytest.approx(0.15, abs=0.01)
    assert res[-1].state.v_ned_m_s[0] < -0.3  # nose up -> backwards (south at yaw 0)


def test_yaw_rate_tracking(sim):
    _airborne(sim)
    hover = sim.vehicle.hover_thrust_fraction
    res = _fly(sim, 2.0, lambda t: AttitudeCommand(0.0, 0.0, 1.0, hover, True, 0))
    rates = np.array([r.state.omega_q_rad_s[2] for r in res[-250:]])
    assert rates.mean() == pytest.approx(1.0, rel=0.03)
    yaw0 = euler_from_R(res[-250].state.R_ned_q)[2]
    yaw1 = euler_from_R(res[-1].state.R_ned_q)[2]
    assert (yaw1 - yaw0) % (2 * math.pi) == pytest.approx(249 * sim.tick_s, rel=0.05)


def test_disarm_cuts_the_motors_at_once(sim):
    _airborne(sim)
    hover = sim.vehicle.hover_thrust_fraction
    _fly(sim, 0.5, lambda t: AttitudeCommand(0.0, 0.0, 0.0, hover, True, 0))
    res = _fly(sim, 0.3, lambda t: AttitudeCommand(0.0, 0.0, 0.0, hover, False, 1))
    assert not res[0].firmware.armed
    assert np.all(res[0].firmware.motor_cmd_n == 0.0)
    assert res[-1].state.motor_thrust_n.max() < 0.01 * sim.vehicle.motor.max_thrust_n  # lag has decayed
    assert res[-1].state.v_ned_m_s[2] > 1.0  # falling


def test_failsafe_levels_descends_and_cuts_on_the_ground(sim):
    _airborne(sim, z_m=-1.0)
    hover = sim.vehicle.hover_thrust_fraction
    _fly(sim, 0.5, lambda t: AttitudeCommand(0.1, 0.0, 0.0, hover, True, 0))
    states = []
    for _ in range(round(12.0 / sim.tick_s)):  # setpoints stop
        states.append(sim.tick())
        if not states[-1].firmware.armed:
            break
    fs = [r for r in states if r.firmware.flight_state == BoardFlightState.FAILSAFE_DESCEND]
    assert fs, "failsafe never engaged"
    t_engage = fs[0].t_s - states[0].t_s
    assert t_engage == pytest.approx(sim.cfg.firmware.setpoint_timeout_s, abs=0.01)
    assert abs(euler_from_R(fs[-1].state.R_ned_q)[0]) < 0.03  # levelled
    assert max(r.state.v_ned_m_s[2] for r in fs) > 0.1  # descending
    final = states[-1]
    assert not final.firmware.armed and final.firmware.flight_state == BoardFlightState.LANDED
    assert final.state.p_ned_m[2] > -0.15  # on the floor (CoM 0.1 m up on its landing gear)
    assert sim.firmware.error_flags & 0x01


def test_setpoint_timeout_on_the_ground_just_disarms(sim):
    _fly(sim, 0.2, lambda t: AttitudeCommand(0.0, 0.0, 0.0, 0.0, True, 0))
    assert sim.firmware.armed
    res = [sim.tick() for _ in range(400)]
    assert not res[-1].firmware.armed
    assert all(r.firmware.flight_state != BoardFlightState.FAILSAFE_DESCEND for r in res)


def test_nan_setpoint_is_ignored(sim):
    _airborne(sim)
    hover = sim.vehicle.hover_thrust_fraction
    _fly(sim, 0.2, lambda t: AttitudeCommand(0.0, 0.0, 0.0, hover, True, 0))
    sim.on_setpoint(AttitudeCommand(float("nan"), 0.0, 0.0, hover, True, 1))
    assert sim.firmware.command.seq == 0 and sim.firmware.rejected_setpoints == 1


def test_config_files_load():
    cfg = load_sitl_config()
    assert isinstance(cfg, SitlConfig) and cfg.physics.rate_hz >= 500.0

"""External pushes on the SITL vehicle (sim_sitl.disturbance + the World/SimVehicle hooks), pybullet DIRECT."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from quadlink.config import from_dict
from quadlink.errors import ConfigError
from quadlink.frames import GRAVITY_M_S2
from quadlink.vehicle import load_vehicle
from sim_sitl.config import ScenarioConfig, load_scenario, load_sitl_config
from sim_sitl.disturbance import DisturbanceSchedule, Push
from sim_sitl.firmware import AttitudeCommand
from sim_sitl.vehicle_sim import SimVehicle


def test_schedule_sums_active_pushes_and_validates() -> None:
    s = DisturbanceSchedule([Push(2.0, 0.5, (1.0, 0.0, 0.0)), Push(1.0, 2.0, (0.0, 2.0, 0.0))])
    np.testing.assert_allclose(s.force_ned_n(0.5), 0.0)
    np.testing.assert_allclose(s.force_ned_n(1.5), [0.0, 2.0, 0.0])
    np.testing.assert_allclose(s.force_ned_n(2.2), [1.0, 2.0, 0.0])
    np.testing.assert_allclose(s.force_ned_n(2.5), [0.0, 2.0, 0.0])  # the end is exclusive
    np.testing.assert_allclose(s.force_ned_n(3.0), 0.0)
    s.push(4.0, (0.0, 0.0, -3.0), 0.1)
    assert s.active(4.05) and not s.active(4.1)
    p = Push.from_impulse(1.0, (0.3, 0.0, 0.0), duration_s=0.05)
    np.testing.assert_allclose(p.impulse_ned_n_s, [0.3, 0.0, 0.0])
    with pytest.raises(ConfigError):
        Push(1.0, 0.0, (1.0, 0.0, 0.0))
    with pytest.raises(ConfigError):
        Push(1.0, 0.1, (math.nan, 0.0, 0.0))


def test_scenario_yaml_carries_a_push_schedule() -> None:
    sc = from_dict(ScenarioConfig, {"name": "x", "disturbances": [
        {"start_s": 3.0, "duration_s": 0.2, "force_ned_n": [0.0, 0.0, 2.5], "name": "z"}]})
    assert sc.disturbances == (Push(3.0, 0.2, (0.0, 0.0, 2.5), "z"),)
    with pytest.raises(ConfigError):
        from_dict(ScenarioConfig, {"disturbances": [{"start_s": 1.0, "duration_s": -1.0}]})
    hover = load_scenario("paper003-hover")
    assert [p.name for p in hover.disturbances] == ["z", "y", "x"]  # paper 003's order


@pytest.fixture
def floating():
    """The vehicle in mid-air, level, every motor at hover thrust (no firmware: the rotor forces are constant)."""
    vehicle = load_vehicle()
    sim = SimVehicle(vehicle, load_sitl_config(), load_scenario("empty"), np.random.default_rng(3))
    sim.power_up()
    sim.world.reset_pose(np.array([0.0, 0.0, -1.5]), np.eye(3))
    hover_n = vehicle.mass_kg * GRAVITY_M_S2 / 4.0
    sim.world.motor_thrust_n[:] = hover_n
    yield sim, np.full(4, hover_n)
    sim.close()


def test_an_impulse_displaces_the_body_as_the_drag_law_predicts(floating) -> None:
    """A 0.3 N s kick north: v0 = J / m, then x(T) = (J / c) (1 - exp(-c T / m)) with the body's linear drag c
    (airframe + rotor drag at hover thrust), computed independently of the SITL's code."""
    sim, motors = floating
    world = sim.world
    vehicle = sim.vehicle
    J = 0.3
    pulse_s = 0.02
    sched = DisturbanceSchedule([Push.from_impulse(0.0, (J, 0.0, 0.0), duration_s=pulse_s)])
    p0 = world.state.p_ned_m.copy()
    steps = round(2.0 / world.dt_s)
    v_after_pulse = None
    for k in range(steps):
        world.external_force_ned_n = sched.force_ned_n(k * world.dt_s)
        world.step(motors)
        if v_after_pulse is None and (k + 1) * world.dt_s >= pulse_s - 1e-12:
            v_after_pulse = world.state.v_ned_m_s.copy()
    m = vehicle.mass_kg
    c = vehicle.linear_drag_n_s_m[0] + load_sitl_config().physics.rotor_drag_n_s_m_per_n * m * GRAVITY_M_S2
    assert v_after_pulse is not None and v_after_pulse[0] == pytest.approx(J / m, rel=0.03)
    T = steps * world.dt_s - pulse_s / 2.0  # the impulse acts, on average, half a pulse after t = 0
    expected = J / c * (1.0 - math.exp(-c * T / m))
    dx = world.state.p_ned_m - p0
    print(f"impulse {J} N s: displaced {dx[0]:.4f} m north in 2 s (drag law {expected:.4f} m)")
    assert dx[0] == pytest.approx(expected, rel=0.03)
    assert abs(dx[1]) < 1e-3 and abs(dx[2]) < 0.01  # sideways nothing, vertically hover


def test_a_scripted_push_reaches_the_flying_vehicle_through_the_scenario() -> None:
    """SimVehicle with the board's firmware holding level at hover thrust; the scenario pushes it up for 0.2 s."""
    vehicle = load_vehicle()
    J = 0.5  # N s, upwards
    scenario = dataclasses.replace(load_scenario("empty"),
                                   disturbances=(Push(1.0, 0.2, (0.0, 0.0, -J / 0.2), "up"),))
    sim = SimVehicle(vehicle, load_sitl_config(), scenario, np.random.default_rng(3))
    sim.power_up()
    try:
        sim.world.reset_pose(np.array([0.0, 0.0, -1.5]), np.eye(3))
        sim.world.motor_thrust_n[:] = vehicle.mass_kg * GRAVITY_M_S2 / 4.0
        vz = {}
        for _ in range(round(1.5 / sim.tick_s)):
            if sim.ticks % 5 == 0:
                sim.on_setpoint(AttitudeCommand(0.0, 0.0, 0.0, vehicle.hover_thrust_fraction, True))
            r = sim.tick()
            vz[round(r.t_s, 3)] = float(r.state.v_ned_m_s[2])
        dv = vz[1.2] - vz[1.0]
        # J / m, less the vertical drag (0.35 N s/m) acting over the pulse: ~ -0.49 m/s
        assert dv == pytest.approx(-J / vehicle.mass_kg, rel=0.05)
        assert abs(vz[0.98] - vz[0.0]) < 0.02  # nothing before the push
    finally:
        sim.close()

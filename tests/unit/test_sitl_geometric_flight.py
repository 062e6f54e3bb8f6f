"""Paper 003's two experiments on the SITL's physics and board firmware (pybullet DIRECT, in process, no links):
the geometric tracker at 100 Hz on the true state, the board's attitude loop at 500 Hz, the scenario's pushes.

This is the tracker and the disturbance against the real vehicle model; the full stack (estimator, companion,
MAVLink, the bridge's services) is the lead's wiring and is not in these figures.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from firmware_bridge.geometric_tracker import GeometricGains, GeometricTracker, TrackingState, TrajectoryTarget
from harness.demo import paper003
from quadlink.frames import GRAVITY_M_S2
from quadlink.trajectory import minimum_snap
from quadlink.vehicle import load_vehicle
from sim_sitl.config import load_scenario, load_sitl_config
from sim_sitl.firmware import AttitudeCommand
from sim_sitl.vehicle_sim import SimVehicle

HOVER_NED_M = np.array([0.2, 2.2, -1.2])  # paper 003's goal p = [0.2 2.2 1.2] (NWU up) as arena NED here
OVAL_NED_M = np.array([[-1.0, -1.5, -1.2], [0.0, -0.5, -1.2], [0.0, 0.5, -1.2], [-1.0, -1.5, -1.2]])


def _fly(scenario_name: str, start_ned_m: np.ndarray, target_at, seconds: float, push_shift_s: float | None = None,
         gains: GeometricGains | None = None):
    vehicle = load_vehicle()
    scenario = load_scenario(scenario_name)
    if push_shift_s is not None:  # the scripted pushes, moved to this flight's clock
        scenario = dataclasses.replace(scenario, disturbances=tuple(
            dataclasses.replace(p, start_s=p.start_s - push_shift_s) for p in scenario.disturbances))
    sim = SimVehicle(vehicle, load_sitl_config(), scenario, np.random.default_rng(5))
    sim.power_up()
    try:
        sim.world.reset_pose(start_ned_m, np.eye(3))
        sim.world.motor_thrust_n[:] = vehicle.mass_kg * GRAVITY_M_S2 / 4.0
        tracker = GeometricTracker(vehicle.mass_kg, vehicle.max_total_thrust_n, gains=gains)
        rows = []
        for _ in range(round(seconds / sim.tick_s)):
            s = sim.world.state
            if sim.ticks % 5 == 0:  # 100 Hz, like the bridge
                t = sim.t_s
                tgt = target_at(t)
                out = tracker.step(0.01, tgt, TrackingState(s.v_ned_m_s.copy(), s.R_ned_q.copy(), s.p_ned_m.copy()))
                c = out.attitude
                sim.on_setpoint(AttitudeCommand(c.roll_rad, c.pitch_rad, c.yaw_rate_rad_s, c.thrust_fraction, True))
                rows.append((t, s.p_ned_m.copy(), s.v_ned_m_s.copy(), np.asarray(tgt.p_ned_m),
                             np.asarray(tgt.v_ned_m_s)))
            sim.tick()
    finally:
        sim.close()
    t = np.array([r[0] for r in rows])
    return t, np.array([r[1] for r in rows]), np.array([r[2] for r in rows]), np.array([r[3] for r in rows]), \
        np.array([r[4] for r in rows])


@pytest.mark.slow  # 31 s of simulated flight at 500 Hz
def test_hover_recovers_from_the_three_pushes_within_3_s() -> None:
    """configs/scenarios/paper003-hover.yaml's pushes (z, y, x; 10 s apart), shifted to t = 2, 12, 22 s."""
    pushes = load_scenario("paper003-hover").disturbances
    shift = pushes[0].start_s - 2.0

    def hold(t: float) -> TrajectoryTarget:
        return TrajectoryTarget(np.zeros(3), np.zeros(3), HOVER_NED_M, yaw_rad=0.0)

    t, p, v, _, _ = _fly("paper003-hover", HOVER_NED_M.copy(), hold, 31.0, push_shift_s=shift)
    err = np.linalg.norm(p - HOVER_NED_M, axis=1)
    for push in pushes:
        start = push.start_s - shift
        end = start + push.duration_s
        window = (t >= start) & (t < start + 10.0)
        peak = float(err[window].max())
        speed = float(np.linalg.norm(v[window], axis=1).max())
        after = window & (t >= end)
        settled = t[after][np.argmax(err[after] < 0.05)] - end
        print(f"push {push.name}: peak displacement {peak:.2f} m, peak speed {speed:.2f} m/s, "
              f"back within 5 cm {settled:.2f} s after release")
        assert 0.55 < peak < 0.9  # about the paper's 0.7 m
        assert settled < 3.0  # "the controller takes less than 3 s to stabilize"
        assert np.all(err[after & (t >= end + 3.0) & (t < start + 10.0)] < 0.05)


# the SITL's horizontal linear drag per unit mass: airframe 0.25 N s/m + rotor drag 0.02 N s/m per N at hover (1 kg)
SITL_DRAG_1_S = 0.25 + 0.02 * GRAVITY_M_S2


@pytest.mark.parametrize("drag_ff_1_s", [0.0, SITL_DRAG_1_S], ids=["eq4", "drag-ff"])
def test_oval_tracking_errors_on_the_sitl_physics(tmp_path: Path, drag_ff_1_s: float) -> None:
    traj = minimum_snap(OVAL_NED_M, (3.0, 1.7, 4.3))

    def target(t: float) -> TrajectoryTarget:
        s = traj.sample(t)
        return TrajectoryTarget(s.v_m_s, s.a_m_s2, s.p_m, yaw_rad=0.0)

    t, p, v, p_d, v_d = _fly("empty", OVAL_NED_M[0].copy(), target, traj.duration_s,
                             gains=GeometricGains(drag_ff_1_s=drag_ff_1_s))
    rmse_p = np.sqrt(np.mean((p - p_d) ** 2, axis=0))
    rmse_v = np.sqrt(np.mean((v - v_d) ** 2, axis=0))
    print(f"SITL oval (true state, drag ff {drag_ff_1_s:.2f} 1/s): position RMSE {np.round(rmse_p, 4)} m, "
          f"velocity RMSE {np.round(rmse_v, 4)} m/s, max position error {np.linalg.norm(p - p_d, axis=1).max():.3f} m")
    # issue 19: 0.05 (on the estimate); with drag feed-forward 0.025 while the board flew on the true attitude, on its
    # own estimate (issue 29) 0.017/0.029/0.002 m measured: widened to 0.035 with them
    assert np.all(rmse_p <= (0.05 if drag_ff_1_s == 0.0 else 0.035)), rmse_p
    assert np.all(rmse_v <= 0.06), rmse_v
    assert rmse_p[:2].max() > 1e-3  # it is a real flight, not a replay of the reference
    # the report pieces the full-stack demo will use: the same figures, and the plots
    tab = paper003.tables(paper003.Paper003Series(t, p_d, v_d, p, v))
    np.testing.assert_allclose(tab["true_position_vs_desired_m"], rmse_p, rtol=1e-12)
    assert len(paper003.make_plots(paper003.Paper003Series(t, p_d, v_d, p, v), tmp_path)) == 3



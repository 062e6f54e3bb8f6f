"""Take-off without odometry on the ground (pure state machine, injected clock: the point-mass Sim of
test_bridge_autopilot, 2 ms IMU steps).

On the ground the RGB-D camera sees the floor closer than its minimum range, so the companion's odometry
is absent or flagged failed (quality 0) until ~0.3-0.5 m up. Phase 1 climbs level on the accelerometer;
valid odometry switches to the closed-loop tracker; without it the climb is bounded and the vehicle lands.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_bridge_autopilot import GCS, Sim, msg

from firmware_bridge.autopilot import FlightMode, TakeoffPhase
from firmware_bridge.params import ParamTable
from firmware_bridge.vertical_estimator import VerticalEstimator
from quadlink.frames import GRAVITY_M_S2
from quadlink.mavlink import mavlink

ACCEL_BIAS_Q_M_S2 = np.array([0.03, -0.02, 0.06])  # a realistic constant accelerometer bias


def blind_sim(bias: bool = True, params: ParamTable | None = None) -> Sim:
    sim = Sim(params=params, odom=False)
    if bias:
        on_imu = sim.ap.on_imu
        sim.ap.on_imu = lambda now, t_us, a, w: on_imu(now, t_us, np.asarray(a) + ACCEL_BIAS_Q_M_S2, w)
    return sim


def height(sim: Sim) -> float:
    return float(-sim.p[2])


def arm_and_sit(sim: Sim, seconds: float = 2.0) -> None:
    sim.step(0.5)
    assert sim.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)[0] == mavlink.MAV_RESULT_ACCEPTED
    sim.step(seconds)


def test_arming_and_sitting_landed_never_need_odometry():
    sim = blind_sim()
    arm_and_sit(sim, 3.0)
    assert sim.ap.armed_cmd and not sim.ap.in_air and sim.ap.mode == FlightMode.POSCTL
    assert sim.ap.failsafe_reason is None
    assert not any("dometry" in t for t in sim.statustext), sim.statustext  # nothing to report ...
    health = sim.ap.sys_status(sim.t).onboard_control_sensors_health
    assert not health & mavlink.MAV_SYS_STATUS_SENSOR_VISION_POSITION  # ... but the health bit
    assert sim.ap.last_board_command.thrust == 0.0 and sim.ap.last_board_command.armed
    # odometry that comes and goes on the ground (quality flapping) raises no failsafe and no STATUSTEXT
    sim.odom = True
    sim.step(0.5)
    sim.odom = False
    sim.step(1.0)
    assert sim.ap.failsafe_reason is None and sim.ap.mode == FlightMode.POSCTL and sim.ap.armed_cmd
    assert not any("dometry" in t for t in sim.statustext), sim.statustext


def test_quality_zero_odometry_is_not_a_velocity_source():
    sim = Sim()
    sim.step(0.5)
    assert sim.ap.odom_ok
    failed = GCS.odometry_encode(0, mavlink.MAV_FRAME_LOCAL_FRD, mavlink.MAV_FRAME_BODY_FRD, 0, 0, 0, [1, 0, 0, 0],
                                 3.0, 0, 0, 0, 0, 0, [math.nan] * 21, [math.nan] * 21, 0, 0, 0)
    sim.odom = False
    for _ in range(60):
        sim.ap.handle_mavlink(sim.t, msg(failed))
        sim.step(0.02)
    assert not sim.ap.odom_ok  # quality 0 = the companion's "failed": it does not refresh the odometry
    assert sim.ap.counters["odometry_low_quality"] == 60 and sim.ap.counters["odometry_rejected"] == 0
    assert sim.ap.v_est_h(sim.t)[0] == pytest.approx(0.0)
    sim.ap.params.set("BRG_ODOM_QMIN", 0.0)  # accept "unknown" quality (MAVLink's 0) if the user says so
    sim.ap.handle_mavlink(sim.t, msg(failed))
    assert sim.ap.odom_ok and sim.ap.v_est_h(sim.t)[0] == pytest.approx(3.0)


def test_takeoff_climbs_open_loop_then_switches_to_closed_loop_when_odometry_arrives():
    sim = blind_sim()
    arm_and_sit(sim)
    result, _ = sim.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, math.nan, math.nan, 1.2)
    assert result == mavlink.MAV_RESULT_ACCEPTED
    assert sim.ap.mode == FlightMode.TAKEOFF and sim.ap.takeoff_phase == TakeoffPhase.OPEN_LOOP
    assert any("open loop" in t for t in sim.statustext)
    max_abs_angle = 0.0
    start = sim.t
    while height(sim) < 0.4:  # the camera starts to see the floor at ~0.4 m
        sim.step(0.02)
        cmd = sim.ap.last_board_command
        max_abs_angle = max(max_abs_angle, abs(cmd.roll_rad), abs(cmd.pitch_rad))
        assert cmd.thrust <= sim.ap.tracker.hover_thrust_fraction * 1.25 + 1e-9  # hover + the climb margin
        assert sim.t - start < 3.0, "no climb without odometry"
    assert max_abs_angle == 0.0  # level attitude hold
    assert sim.ap.failsafe_reason is None and sim.ap.mode == FlightMode.TAKEOFF
    assert sim.ap.vertical.height_m == pytest.approx(height(sim), abs=0.08)
    assert -sim.v[2] == pytest.approx(0.4, abs=0.15)  # the gentle open-loop climb rate
    sim.odom = True
    sim.step(0.1)
    assert sim.ap.takeoff_phase == TakeoffPhase.CLOSED_LOOP and not sim.ap.blind
    assert any("closed loop" in t for t in sim.statustext)
    sim.step(5.0)
    assert sim.ap.mode == FlightMode.LOITER and sim.ap.armed_cmd and sim.ap.failsafe_reason is None
    assert height(sim) == pytest.approx(1.2, abs=0.1)
    # phase 2 acquired odometry in the air: its loss is the usual failsafe (item 3 of the issue)
    sim.odom = False
    sim.step(1.0)
    assert sim.ap.mode == FlightMode.LAND and sim.ap.failsafe_reason == "odometry lost"
    assert any("Odometry lost" in t for t in sim.statustext)


def test_odometry_lost_low_in_the_climb_climbs_open_loop_until_it_returns():
    """The camera can lose the floor again just after the switch (too near, too fast): below BRG_TKO_OL_ALT the
    take-off goes back to phase 1 (no LAND at 0.5 m), keeps climbing level, and closes the loop when odometry is
    back; the take-off then completes."""
    sim = blind_sim()
    arm_and_sit(sim)
    assert sim.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, math.nan, math.nan, 1.2)[0] == \
        mavlink.MAV_RESULT_ACCEPTED
    while height(sim) < 0.15:
        sim.step(0.02)
    sim.odom = True
    sim.step(0.3)
    assert sim.ap.takeoff_phase == TakeoffPhase.CLOSED_LOOP
    sim.odom = False
    h_lost = height(sim)
    sim.step(0.4)   # lost at ~0.5 m: 0.4 s more keeps it under BRG_TKO_OL_ALT (0.7 m)
    assert sim.ap.mode == FlightMode.TAKEOFF and sim.ap.failsafe_reason is None, sim.statustext
    assert sim.ap.takeoff_phase == TakeoffPhase.OPEN_LOOP and sim.ap.blind
    assert any("in takeoff: open loop" in t for t in sim.statustext), sim.statustext
    assert height(sim) > h_lost + 0.05       # still climbing
    assert sim.ap.vertical.height_m == pytest.approx(height(sim), abs=0.12)  # continued from the odometry's height
    cmd = sim.ap.last_board_command   # level by the bridge's estimate: the board's error learnt so far (none here)
    assert (cmd.roll_rad, cmd.pitch_rad) == pytest.approx(tuple(sim.ap.state.level_trim_rad), abs=1e-12)
    assert max(abs(cmd.roll_rad), abs(cmd.pitch_rad)) < math.radians(0.1)
    sim.odom = True
    sim.step(5.0)
    assert sim.ap.mode == FlightMode.LOITER and sim.ap.failsafe_reason is None
    assert height(sim) == pytest.approx(1.2, abs=0.1)


def test_takeoff_without_odometry_is_bounded_in_height_then_lands():
    sim = blind_sim()
    arm_and_sit(sim)
    assert sim.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 4.0)[0] == mavlink.MAV_RESULT_ACCEPTED
    top = 0.0
    landed_at = None
    while sim.t < 30.0:
        sim.step(0.02)
        top = max(top, height(sim))
        if not sim.ap.armed_cmd:
            landed_at = sim.t
            break
    assert landed_at is not None, f"still armed at {sim.t:.1f} s, height {height(sim):.2f} m"
    assert any("No odometry in takeoff" in t for t in sim.statustext), sim.statustext
    assert 0.55 <= top <= 0.7 + 0.2  # BRG_TKO_OL_ALT (estimated) is the bound
    assert height(sim) < 0.01 and sim.ap.landed_state() == mavlink.MAV_LANDED_STATE_ON_GROUND


def test_takeoff_without_odometry_is_bounded_in_time_then_lands():
    sim = blind_sim()
    arm_and_sit(sim)
    start = sim.t
    # a take-off height under BRG_TKO_OL_ALT (0.7 m), so the time bound is what ends it
    assert sim.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, math.nan, math.nan, 0.5)[0] == \
        mavlink.MAV_RESULT_ACCEPTED
    aborted_at = None
    top = 0.0
    while sim.t < 30.0 and sim.ap.armed_cmd:
        sim.step(0.02)
        top = max(top, height(sim))
        if aborted_at is None and sim.ap.mode == FlightMode.LAND:
            aborted_at = sim.t - start
            assert sim.ap.failsafe_reason == "no odometry in takeoff"
    assert aborted_at == pytest.approx(6.0, abs=0.05)  # BRG_TKO_OL_T
    assert top == pytest.approx(0.5, abs=0.15)  # it held the take-off height on the estimate meanwhile
    assert not sim.ap.armed_cmd and height(sim) < 0.01


def test_land_command_in_the_open_loop_climb_descends_and_disarms():
    sim = blind_sim()
    arm_and_sit(sim)
    sim.command(mavlink.MAV_CMD_NAV_TAKEOFF)
    sim.step(2.5)
    assert height(sim) > 0.3
    assert sim.command(mavlink.MAV_CMD_DO_SET_MODE, 1, 4, 3)[0] == mavlink.MAV_RESULT_TEMPORARILY_REJECTED  # LOITER
    assert sim.command(mavlink.MAV_CMD_NAV_LAND)[0] == mavlink.MAV_RESULT_ACCEPTED
    sim.step(8.0)
    assert not sim.ap.armed_cmd and height(sim) < 0.01


def test_vertical_estimator_is_pinned_below_liftoff_thrust_and_learns_the_bias():
    est = VerticalEstimator(hover_thrust_fraction=0.5)
    bias = 0.07
    for _ in range(1000):  # 2 s armed at idle on the ground
        est.update(0.002, bias, 0.05)
    assert est.estimate.pinned and est.vz_m_s == 0.0 and est.height_m == 0.0
    assert est.estimate.accel_bias_m_s2 == pytest.approx(bias, abs=1e-3)
    for _ in range(100):  # thrust ramping below 70 % of hover: the ground holds the vehicle
        est.update(0.002, bias, 0.3)
    assert est.vz_m_s == 0.0
    for _ in range(500):  # airborne: 1 s at 0.5 m/s^2 up (NED -)
        est.update(0.002, bias - 0.5, 0.55)
    assert est.vz_m_s == pytest.approx(-0.5, abs=0.01) and est.height_m == pytest.approx(0.25, abs=0.01)
    for _ in range(5000):  # bounded: never faster than the climb limit
        est.update(0.002, bias - GRAVITY_M_S2, 0.9)
    assert est.vz_m_s == pytest.approx(-1.5)
    est.reset_ground()
    assert est.estimate.pinned and est.height_m == 0.0
    assert est.estimate.accel_bias_m_s2 == pytest.approx(bias, abs=1e-3)


def test_a_stuck_odometry_height_cannot_carry_the_take_off_past_its_target():
    """Campaign flight 33: the companion's odometry position stayed within 0.3 m while its velocity (right) and
    the vehicle climbed 3 m into the ceiling. The climb ends when the integrated climb rate says it is high
    enough, and a STATUSTEXT says the two disagree."""
    sim = Sim()
    send = sim.send

    def stuck_height(encoded):   # the ODOMETRY's position frozen at the ground, its velocity true
        if encoded.get_type() == "ODOMETRY":
            encoded.z = 0.0
        return send(encoded)

    sim.send = stuck_height
    sim.step(0.5)
    assert sim.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)[0] == mavlink.MAV_RESULT_ACCEPTED
    sim.step(0.5)
    assert sim.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, math.nan, math.nan, 1.2)[0] == \
        mavlink.MAV_RESULT_ACCEPTED
    sim.step(8.0)
    assert sim.ap.mode == FlightMode.LOITER, sim.statustext
    assert height(sim) == pytest.approx(1.2, abs=0.15)
    assert any(t.startswith("Takeoff: odometry height") and "climbed" in t for t in sim.statustext), sim.statustext


def test_odometry_back_in_the_climb_far_from_the_measured_climb_is_re_anchored():
    """CI: the odometry drifted on the ground (its height is only held to the floor once the camera sees it), the
    ground anchor was taken from it at arming, and when the odometry came back in the open-loop climb its height
    read 0.99 m with the vehicle 0.28 m up: the take-off ended at once. Now the odometry is re-anchored to the
    climb the IMU measured, and the take-off climbs to its target."""
    sim = Sim()
    sim.odom_z_offset_m = 0.7                      # on the ground the odometry says 0.7 m below the truth
    sim.step(0.5)
    assert sim.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)[0] == mavlink.MAV_RESULT_ACCEPTED
    sim.step(1.0)
    assert sim.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, math.nan, math.nan, 1.0)[0] == \
        mavlink.MAV_RESULT_ACCEPTED
    sim.odom = False                               # lost at lift-off (the camera too near the floor)
    while height(sim) < 0.3:
        sim.step(0.02)
    sim.odom_z_offset_m = 0.0                      # in the air the floor corrects it
    sim.odom = True
    sim.step(6.0)
    assert any("Odometry height" in t for t in sim.statustext), sim.statustext
    assert sim.ap.mode == FlightMode.LOITER and sim.ap.failsafe_reason is None
    assert height(sim) == pytest.approx(1.0, abs=0.1)


@pytest.mark.parametrize("stopped_before_s", [0.4, 1.5])
def test_takeoff_on_odometry_that_just_stopped_climbs_open_loop_not_on_a_frozen_velocity(stopped_before_s):
    """With a long BRG_ODOM_LOSS_T (2 s, as flights on a loaded machine set it) odometry that stopped 0.4-1.5 s
    before the take-off is not yet lost, but older than the IMU's prediction horizon its velocity is frozen at 0:
    a closed loop on it winds the integral up on a vehicle it thinks still (a RealSense SITL flight climbed 0.33 m
    past its height at 0.8 m/s). The take-off climbs open loop, closes the loop when odometry returns, and ends
    at its height."""
    params = ParamTable()
    params.set("BRG_ODOM_LOSS_T", 2.0)
    sim = blind_sim(params=params)
    sim.odom = True
    arm_and_sit(sim)
    sim.odom = False
    sim.step(stopped_before_s)
    assert sim.ap.odom_ok   # not yet timed out
    assert sim.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, math.nan, math.nan, 1.0)[0] == \
        mavlink.MAV_RESULT_ACCEPTED
    assert sim.ap.takeoff_phase == TakeoffPhase.OPEN_LOOP, sim.statustext
    top = v_up_max = 0.0
    while height(sim) < 0.25:
        sim.step(0.02)
        v_up_max = max(v_up_max, -sim.v[2])
        assert sim.t < 30.0
    sim.odom = True
    for _ in range(300):
        sim.step(0.02)
        top, v_up_max = max(top, height(sim)), max(v_up_max, -sim.v[2])
    assert sim.ap.mode == FlightMode.LOITER and sim.ap.failsafe_reason is None, sim.statustext
    assert v_up_max < 0.5 + 0.1   # MPC_TKO_SPEED, the open loop's BRG_TKO_OL_SPD below it
    assert top < 1.0 + 0.1 and height(sim) == pytest.approx(1.0, abs=0.1)


def paused_odometry_sim() -> Sim:
    params = ParamTable()
    params.set("BRG_ODOM_LOSS_T", 2.0)
    return blind_sim(bias=False, params=params)


def take_off_on_odometry_that_paused(sim: Sim, back, accel_bias_in_air_q: np.ndarray | None = None
                                     ) -> tuple[float, float]:
    """Odometry valid at arming, stale at the take-off (1 s: with BRG_ODOM_LOSS_T 2 s not yet lost), back 0.25 m up
    (``back()`` is called then); flown to the end of the take-off. Returns the accelerometer's climb when the odometry
    came back and the bridge's height error 0.1 s later."""
    sim.odom = True
    arm_and_sit(sim)
    sim.odom = False
    sim.step(1.0)
    assert sim.ap.odom_ok   # not yet timed out: the take-off starts open loop on the stale odometry
    if accel_bias_in_air_q is not None:
        sim.accel_bias_q = accel_bias_in_air_q
    assert sim.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, math.nan, math.nan, 1.0)[0] == \
        mavlink.MAV_RESULT_ACCEPTED
    assert sim.ap.takeoff_phase == TakeoffPhase.OPEN_LOOP, sim.statustext
    while height(sim) < 0.25:
        sim.step(0.02)
        assert sim.t < 30.0
    climbed_m = sim.ap.state.vertical.height_m
    back()
    sim.odom = True
    sim.step(0.1)
    height_error_m = sim.ap.state.height_m - height(sim)
    while sim.ap.mode == FlightMode.TAKEOFF:
        sim.step(0.02)
        assert sim.t < 30.0
    return climbed_m, height_error_m


def test_odometry_that_paused_on_the_ground_gives_the_height_from_its_ground_not_the_accelerometers_climb():
    """CI (test_bridge_sitl): odometry valid at arming, stale at the take-off (BRG_ODOM_LOSS_T 2 s), back 0.20 m up
    in the same frame with the accelerometer's climb reading 0.04 m: anchored to that climb, the take-off ended
    0.21 m above its height. The ground anchor taken at arming is kept; the height is the odometry's. Here the
    accelerometer reads 0.3 m/s^2 less climb once the motors spin (vibration), so its climb lags the truth."""
    sim = paused_odometry_sim()
    climbed_m, height_error_m = take_off_on_odometry_that_paused(sim, lambda: None, np.array([0.0, 0.0, 0.3]))
    at_loiter_m = top = height(sim)
    for _ in range(100):
        sim.step(0.02)
        top = max(top, height(sim))
    assert climbed_m < 0.25 - 0.05, climbed_m   # the accelerometer's climb is behind the truth here
    assert abs(height_error_m) < 0.02, height_error_m   # anchored on the ground: 0.10 m low on the climb's
    assert sim.ap.mode == FlightMode.LOITER and sim.ap.failsafe_reason is None, sim.statustext
    assert not any("Odometry height" in t for t in sim.statustext), sim.statustext  # not re-anchored
    assert at_loiter_m == pytest.approx(1.0, abs=0.06) and top < 1.0 + 0.06, (at_loiter_m, top)


def test_odometry_that_comes_back_in_a_new_frame_is_anchored_to_the_climb_not_the_old_ground():
    """The same take-off, but the odometry comes back reset (its reset counter moved, its origin 0.2 m away, as
    quadlink's companion restarts after a failure): the ground anchor taken at arming belongs to the old frame and
    is dropped; the new frame is anchored to the measured climb, and the take-off still ends at its height."""
    sim = paused_odometry_sim()
    send = sim.send
    new_frame = [False]

    def restarted(encoded):
        if new_frame[0] and encoded.get_type() == "ODOMETRY":
            encoded.reset_counter = 1
            encoded.z -= 0.2
        return send(encoded)

    sim.send = restarted
    _, height_error_m = take_off_on_odometry_that_paused(sim, lambda: new_frame.__setitem__(0, True))
    assert abs(height_error_m) < 0.05, height_error_m   # on the old ground anchor: 0.2 m off
    assert sim.ap.mode == FlightMode.LOITER and sim.ap.failsafe_reason is None, sim.statustext
    assert height(sim) == pytest.approx(1.0, abs=0.06)


def test_odometry_stale_in_the_closed_loop_climb_goes_open_loop_before_the_loss_timeout():
    """The same in the climb: odometry that stops at 0.15 m (BRG_ODOM_LOSS_T 2 s) is treated as lost after the IMU's
    prediction horizon, not flown frozen for 2 s."""
    params = ParamTable()
    params.set("BRG_ODOM_LOSS_T", 2.0)
    sim = blind_sim(params=params)
    sim.odom = True
    arm_and_sit(sim)
    assert sim.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, math.nan, math.nan, 1.0)[0] == \
        mavlink.MAV_RESULT_ACCEPTED
    assert sim.ap.takeoff_phase == TakeoffPhase.CLOSED_LOOP
    while height(sim) < 0.15:
        sim.step(0.02)
    sim.odom = False
    sim.step(0.5)
    assert sim.ap.takeoff_phase == TakeoffPhase.OPEN_LOOP and not sim.ap.odom_ok, sim.statustext
    top = 0.0
    while height(sim) < 0.4:
        sim.step(0.02)
        top = max(top, height(sim))
    sim.odom = True
    for _ in range(300):
        sim.step(0.02)
        top = max(top, height(sim))
    assert sim.ap.mode == FlightMode.LOITER and sim.ap.failsafe_reason is None, sim.statustext
    assert top < 1.0 + 0.1 and height(sim) == pytest.approx(1.0, abs=0.1)

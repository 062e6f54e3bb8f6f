"""Companion modes/safety state machine and the autopilot command queue."""

from __future__ import annotations

from companion.commands import CommandQueue, command_for
from companion.modes import AutopilotRequest, Mode, ModeMachine, ModeParams, StatusText, VehicleStatus
from quadlink.mavlink import mavlink

GROUND = VehicleStatus(armed=False, in_air=False)
ARMED_GROUND = VehicleStatus(armed=True, in_air=False)
CLIMBING = VehicleStatus(armed=True, in_air=True, taking_off=True)
FLYING = VehicleStatus(armed=True, in_air=True)


def _requests(actions: list) -> list[str]:
    return [a.name for a in actions if isinstance(a, AutopilotRequest)]


def _texts(actions: list) -> list[str]:
    return [a.text for a in actions if isinstance(a, StatusText)]


def _flying_machine(params: ModeParams | None = None) -> tuple[ModeMachine, float]:
    m = ModeMachine(params or ModeParams())
    t = 0.0
    m.on_manual_control(t)
    ok, actions = m.request("takeoff", t, GROUND)
    assert ok and _requests(actions) == ["arm", "takeoff"] and m.mode == Mode.TAKEOFF
    for t in (0.2, 0.5, 0.9):
        m.on_manual_control(t)
        assert m.update(t, CLIMBING, True) == [] or m.mode == Mode.TAKEOFF
    t = 1.5
    m.on_manual_control(t)
    actions = m.update(t, FLYING, True)
    assert _requests(actions) == ["offboard"] and m.mode == Mode.TELEOP
    assert any("TAKEOFF -> TELEOP" in s for s in _texts(actions))
    return m, t


def test_takeoff_sequence_arms_takes_off_then_offboard() -> None:
    m, _ = _flying_machine()
    assert m.operator_enabled and m.in_control


def test_takeoff_needs_idle_and_falls_back_when_refused() -> None:
    m = ModeMachine(ModeParams())
    ok, _ = m.request("takeoff", 0.0, ARMED_GROUND)
    assert ok and m.mode == Mode.TAKEOFF
    assert m.request("takeoff", 0.1, ARMED_GROUND)[0] is False
    actions = m.on_request_failed(AutopilotRequest("takeoff"), 0.2, "DENIED")
    assert m.mode == Mode.IDLE and any("IDLE" in s for s in _texts(actions))


def test_takeoff_timeout_goes_to_teleop_if_armed_without_landed_state() -> None:
    m = ModeMachine(ModeParams(takeoff_timeout_s=3.0))
    m.request("takeoff", 0.0, GROUND)
    assert m.update(2.9, CLIMBING, True) == [] or m.mode == Mode.TAKEOFF
    m.update(3.0, CLIMBING, True)
    assert m.mode == Mode.TELEOP
    # an autopilot reporting its landed state is waited for (slow simulation: no guessing)
    m = ModeMachine(ModeParams(takeoff_timeout_s=3.0))
    m.request("takeoff", 0.0, GROUND)
    climbing = VehicleStatus(armed=True, in_air=True, taking_off=True, reports_landed_state=True)
    m.update(10.0, climbing, True)
    assert m.mode == Mode.TAKEOFF


def test_takeoff_waits_for_the_arm_report_then_falls_back_on_disarm() -> None:
    m = ModeMachine(ModeParams(takeoff_timeout_s=8.0))
    m.request("takeoff", 0.0, GROUND)
    m.update(3.0, GROUND, True)  # the armed HEARTBEAT is late: keep waiting
    assert m.mode == Mode.TAKEOFF
    m.update(3.5, CLIMBING, True)
    m.update(4.0, GROUND, True)  # armed, then disarmed
    assert m.mode == Mode.IDLE


def test_gcs_loss_holds_then_lands_and_recovery_resumes() -> None:
    params = ModeParams(gcs_timeout_s=0.5, gcs_land_timeout_s=4.0)
    m, t = _flying_machine(params)
    last = t
    m.update(last + 0.4, FLYING, True)
    assert m.mode == Mode.TELEOP
    actions = m.update(last + 0.6, FLYING, True)
    assert m.mode == Mode.HOLD and not m.operator_enabled and m.in_control
    assert "companion: ground-station link lost" in _texts(actions)
    # link back -> teleop
    m.on_manual_control(last + 1.0)
    m.update(last + 1.0, FLYING, True)
    assert m.mode == Mode.TELEOP
    # lost again, long enough to land (measured from the last MANUAL_CONTROL)
    last += 1.0
    m.update(last + 0.6, FLYING, True)
    assert m.mode == Mode.HOLD
    assert _requests(m.update(last + 3.9, FLYING, True)) == []
    actions = m.update(last + 4.0, FLYING, True)
    assert _requests(actions) == ["land"] and m.mode == Mode.LAND
    m.update(last + 6.0, VehicleStatus(armed=True, in_air=False), True)
    assert m.mode == Mode.IDLE


def test_odometry_failure_holds_and_recovers_after_a_good_period() -> None:
    params = ModeParams(odometry_fail_s=0.2, odometry_recover_s=0.5, odometry_land_timeout_s=3.0)
    m, t = _flying_machine(params)
    m.on_manual_control(t + 0.05)
    m.update(t + 0.05, FLYING, False)  # one bad frame: bridged
    m.on_manual_control(t + 0.08)
    m.update(t + 0.08, FLYING, True)
    assert m.mode == Mode.TELEOP
    m.on_manual_control(t + 0.1)
    m.update(t + 0.1, FLYING, False)
    assert m.mode == Mode.TELEOP
    t += 0.25
    m.on_manual_control(t + 0.1)
    actions = m.update(t + 0.1, FLYING, False)
    assert m.mode == Mode.HOLD and "companion: odometry failed" in _texts(actions)
    m.on_manual_control(t + 0.3)
    m.update(t + 0.3, FLYING, True)
    assert m.mode == Mode.HOLD  # not yet good long enough
    m.on_manual_control(t + 0.85)
    m.update(t + 0.85, FLYING, True)
    assert m.mode == Mode.TELEOP
    # odometry bad for too long -> land
    for k in range(0, 32):
        now = t + 1.0 + 0.1 * k
        m.on_manual_control(now)
        actions = m.update(now, FLYING, False)
    assert m.mode == Mode.LAND


def test_ground_station_land_and_disarm_rules() -> None:
    m, t = _flying_machine()
    ok, actions = m.request("disarm", t, FLYING)
    assert not ok and m.mode == Mode.TELEOP
    ok, actions = m.request("land", t, FLYING)
    assert ok and _requests(actions) == ["land"] and m.mode == Mode.LAND
    m.update(t + 0.5, VehicleStatus(armed=False), True)
    assert m.mode == Mode.IDLE
    assert m.request("land", t + 1, GROUND)[0] is False
    assert m.request("bogus", t + 1, GROUND)[0] is False


def test_command_queue_orders_retries_and_fails() -> None:
    q = CommandQueue(ack_timeout_s=0.5, retries=2)
    q.push(AutopilotRequest("arm"))
    q.push(AutopilotRequest("takeoff", 1.0))
    send, failed = q.poll(0.0)
    assert [(c.command, conf) for c, conf in send] == [(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0)] and not failed
    assert q.poll(0.2) == ([], [])
    done, failed = q.on_ack(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, mavlink.MAV_RESULT_ACCEPTED, 0.3)
    assert done == AutopilotRequest("arm") and not failed
    send, _ = q.poll(0.3)
    assert send[0][0].command == mavlink.MAV_CMD_NAV_TAKEOFF and send[0][0].params[6] == 1.0
    # no ack: resent with increasing confirmation, then failed
    assert q.poll(0.81)[0][0][1] == 1
    assert q.poll(1.32)[0][0][1] == 2
    send, failed = q.poll(1.83)
    assert send == [] and failed == [(AutopilotRequest("takeoff", 1.0), "no acknowledgement")]
    # denied drops the queue
    q.push(AutopilotRequest("arm"))
    q.push(AutopilotRequest("takeoff", 1.0))
    q.poll(2.0)
    done, failed = q.on_ack(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, mavlink.MAV_RESULT_DENIED, 2.1)
    assert done is None and [r.name for r, _ in failed] == ["arm", "takeoff"] and q.pending == []


def test_offboard_is_px4_do_set_mode() -> None:
    c = command_for(AutopilotRequest("offboard"))
    assert c.command == mavlink.MAV_CMD_DO_SET_MODE
    assert c.params[0] == mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED and c.params[1] == 6


def test_follows_takeoff_and_landing_commanded_to_the_autopilot_directly() -> None:
    m = ModeMachine(ModeParams(takeoff_min_s=0.5))
    m.on_manual_control(0.0)
    actions = m.update(0.0, VehicleStatus(armed=True, in_air=True, taking_off=True), True)
    assert m.mode == Mode.TAKEOFF and _requests(actions) == []
    m.on_manual_control(1.0)
    actions = m.update(1.0, FLYING, True)
    assert m.mode == Mode.TELEOP and _requests(actions) == ["offboard"]
    m.on_manual_control(1.1)
    actions = m.update(1.1, VehicleStatus(armed=True, in_air=True, landing=True), True)
    assert m.mode == Mode.LAND and _requests(actions) == []
    m.update(3.0, VehicleStatus(armed=False), True)
    assert m.mode == Mode.IDLE


def test_a_live_link_without_fresh_commands_holds_then_lands() -> None:
    """Issue 18: heartbeats keep the link, but every command is stale (a 1 s delay) or the script stopped:
    the arbiter holds, and after gcs_land_timeout_s without a fresh command the vehicle lands."""
    params = ModeParams(gcs_timeout_s=0.5, gcs_land_timeout_s=4.0)
    m, t = _flying_machine(params)
    m.on_motion_command(t)                      # the last fresh command
    for k in range(1, 40):                       # heartbeats every 0.1 s: the link stays alive
        now = t + 0.1 * k
        m.on_manual_control(now)
        m.on_motion_command(t)
        assert _requests(m.update(now, FLYING, True)) == [] and m.mode == Mode.TELEOP
    m.on_manual_control(t + 4.0)
    actions = m.update(t + 4.0, FLYING, True)
    assert _requests(actions) == ["land"] and m.mode == Mode.LAND
    assert any("no fresh command for 4 s" in s for s in _texts(actions))


def test_no_land_before_the_first_command_of_a_flight_or_after_a_hold_was_asked() -> None:
    params = ModeParams(gcs_timeout_s=0.5, gcs_land_timeout_s=4.0)
    m = ModeMachine(params)
    m.on_motion_command(-100.0)                  # a command of an earlier flight
    m, t = _flying_machine(params)
    m.on_motion_command(-100.0)
    for now in (t + 5.0, t + 20.0):
        m.on_manual_control(now)
        assert _requests(m.update(now, FLYING, True)) == [] and m.mode == Mode.TELEOP
    m.on_motion_command(None)                    # the ground station switched to hold (offboard.stop())
    m.on_manual_control(t + 60.0)
    assert _requests(m.update(t + 60.0, FLYING, True)) == []


def test_a_failsafe_landing_over_an_object_moves_clear_first_then_lands() -> None:
    """Issue 14 (campaign flight 21: the script's LAND over a desk was refused, then its silence landed the
    vehicle on the desk): the failsafe holds and flies clear (``clearing_spot``) until the spot has looked clear
    for ``land_clear_hold_s``, then lands; it lands anyway after ``land_clear_timeout_s``; with the odometry
    failed, at once."""
    desk = "land refused: object below, 0.87 m tall"
    params = ModeParams(gcs_timeout_s=0.5, gcs_land_timeout_s=4.0, land_clear_timeout_s=6.0)
    m, t = _flying_machine(params)
    m.on_motion_command(t)
    m.on_manual_control(t + 4.0)                 # the link lives, the commands stopped at t
    actions = m.update(t + 4.0, FLYING, True, desk)
    assert _requests(actions) == [] and m.mode == Mode.HOLD and m.clearing_spot and m.in_control
    assert any("no fresh command for 4 s: land refused: object below" in s for s in _texts(actions))
    m.on_manual_control(t + 5.0)
    assert _requests(m.update(t + 5.0, FLYING, True, desk)) == [] and m.clearing_spot
    m.on_manual_control(t + 5.5)
    assert _requests(m.update(t + 5.5, FLYING, True, None)) == [] and m.clearing_spot   # clear: keeps going ...
    m.on_manual_control(t + 6.0)
    assert _requests(m.update(t + 6.0, FLYING, True, desk)) == []    # ... a sparse sample says not yet
    m.on_manual_control(t + 6.2)
    assert _requests(m.update(t + 6.2, FLYING, True, None)) == [] and m.clearing_spot
    m.on_manual_control(t + 7.3)
    actions = m.update(t + 7.3, FLYING, True, None)          # clear for land_clear_hold_s: it lands
    assert _requests(actions) == ["land"] and m.mode == Mode.LAND and not m.clearing_spot
    # never clear: it lands after land_clear_timeout_s wherever it is
    m, t = _flying_machine(params)
    m.on_motion_command(t)
    for dt in (4.0, 7.0, 9.9):
        m.on_manual_control(t + dt)
        assert _requests(m.update(t + dt, FLYING, True, desk)) == [] and m.clearing_spot
    m.on_manual_control(t + 10.0)
    actions = m.update(t + 10.0, FLYING, True, desk)
    assert _requests(actions) == ["land"] and any("could not clear the object below" in s for s in _texts(actions))
    # link lost too long, odometry failed: no safe motion, it lands where it is
    m, t = _flying_machine(params)
    m.update(t + 0.6, FLYING, True)
    assert m.mode == Mode.HOLD
    m.update(t + 3.0, FLYING, False)
    actions = m.update(t + 4.1, FLYING, False, desk)
    assert _requests(actions) == ["land"] and not m.clearing_spot
    # link lost too long, odometry fine: clear first; the operator coming back ends the clearing
    m, t = _flying_machine(params)
    m.update(t + 0.6, FLYING, True)
    assert _requests(m.update(t + 4.1, FLYING, True, desk)) == [] and m.clearing_spot
    m.on_manual_control(t + 5.0)
    m.on_motion_command(t + 5.0)
    m.update(t + 5.0, FLYING, True, desk)
    assert m.mode == Mode.TELEOP and not m.clearing_spot

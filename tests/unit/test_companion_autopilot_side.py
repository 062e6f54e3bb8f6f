"""The companion's autopilot side on its own (unit tier): the autopilot's time as the companion knows it and
the TIMESYNC with it (companion.timesync), the autopilot's messages by type (companion.autopilot_input), the
IMU clock (companion.imu_clock), the perception stage (companion.perception_stage) and what a frame leaves for
the rest of the loop (companion.frame_state)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from companion.autopilot_input import AutopilotInput
from companion.commands import CommandQueue
from companion.frame_state import FrameState
from companion.frame_step import NO_SCAN
from companion.guard import ErrorCounter
from companion.height import HeightParams
from companion.imu_clock import IMU_LAG_LIMIT, IMU_SILENT_S, ImuClock, imu_sample
from companion.modes import Mode, ModeMachine, ModeParams, StatusText, VehicleStatus
from companion.outbound import ToAutopilot
from companion.pan_scan import PanScanParams, pan_scan
from companion.perception_stage import PerceptionStage
from companion.stats import Stats
from companion.timesync import AutopilotTime, TimeSync
from companion.vehicle_state import VehicleState
from quadlink.camera import CameraIntrinsics, RgbdFrame
from quadlink.mavlink import mavlink

pytestmark = pytest.mark.unit

SYSID, AP_COMPID = 1, 1


def wire(msg: Any, src_system: int = SYSID, src_component: int = AP_COMPID) -> Any:
    """``msg`` as the companion gets it: packed by the sender's codec, parsed by a receiver's."""
    (out,) = mavlink.MAVLink(None).parse_buffer(bytes(msg.pack(mavlink.MAVLink(None, src_system, src_component))))
    return out


def clock() -> float:
    return 0.0


def test_the_autopilot_timesync_request_is_answered_with_our_clock() -> None:
    ts = TimeSync()
    reply = ts.on_message(wire(mavlink.MAVLink_timesync_message(0, 777), SYSID, AP_COMPID), 2.0)
    assert reply is not None and (reply.tc1, reply.ts1) == (2_000_000_000, 777)
    assert ts.on_message(wire(mavlink.MAVLink_timesync_message(5_000_000_000, 1_990_000_000)), 2.0) is None
    assert ts.offset_ns is not None


def test_the_autopilot_time_runs_on_from_the_last_imu_sample_else_the_last_frame() -> None:
    t = AutopilotTime(TimeSync(), "autopilot", start_wall_s=10.0)
    assert t.estimate_s(12.5) == pytest.approx(2.5)   # nothing yet: the time since the start
    assert t.on_frame(40.0, wall_s=13.0) == 40.0      # the camera stamps in the autopilot's time already
    assert t.estimate_s(13.25) == pytest.approx(40.25)
    t.on_imu(40.1, wall_s=13.05)
    assert t.estimate_s(13.25) == pytest.approx(40.3)


def test_local_camera_stamps_are_mapped_through_the_autopilot_timesync_once_known() -> None:
    ts = TimeSync()
    t = AutopilotTime(ts, "local", start_wall_s=0.0)
    assert t.on_frame(5.0, wall_s=5.0) == 5.0   # no estimate yet: taken as they come
    # our request at 5.000 s, answered with the autopilot's 105.005 s, back at 5.010 s: offset +100 s
    ts.on_message(wire(mavlink.MAVLink_timesync_message(105_005_000_000, 5_000_000_000), SYSID, AP_COMPID), 5.01)
    assert t.on_frame(6.0, wall_s=6.0) == pytest.approx(106.0, abs=1e-6)
    assert t.frame_stamp_s == pytest.approx(106.0, abs=1e-6) and t.frame_wall_s == 6.0


class Pipe:
    def __init__(self) -> None:
        self.imu: list[float] = []
        self.fail = False

    def on_imu(self, stamp_s: float, gyro: np.ndarray, accel: np.ndarray) -> None:
        if self.fail:
            raise ValueError("bad sample")
        self.imu.append(stamp_s)

    def on_frame(self, frame: RgbdFrame) -> Any:
        if self.fail:
            raise np.linalg.LinAlgError("singular")
        return frame.seq


def frame(seq: int, size: int = 8) -> RgbdFrame:
    K = CameraIntrinsics(6.0, 6.0, 4.0, 4.0, size, size)
    return RgbdFrame(seq, seq * 0.1, np.zeros((size, size, 3), np.uint8), np.ones((size, size), np.float32), K,
                     np.eye(3), np.zeros(3))


def test_perception_starts_on_the_first_frame_and_refuses_a_changed_camera() -> None:
    pipes: list[Pipe] = []
    stats, errors = Stats(), ErrorCounter(clock)
    stage = PerceptionStage(lambda f: pipes.append(Pipe()) or pipes[-1], stats, errors)
    stage.on_imu(0.0, np.zeros(3), np.zeros(3))   # before the first frame: nothing to feed
    assert stage.on_frame(frame(1)) == 1 and len(pipes) == 1
    stage.on_imu(0.15, np.zeros(3), np.zeros(3))
    assert pipes[0].imu == [0.15]
    assert stage.on_frame(frame(2, size=16)) is None and errors.by_where == {"camera frame": 1}
    pipes[0].fail = True
    assert stage.on_frame(frame(3)) is None
    stage.on_imu(0.3, np.zeros(3), np.zeros(3))
    assert stats.pipeline_errors == 3 and len(pipes) == 1


def test_a_refused_arm_during_takeoff_goes_back_to_the_mode_machine_and_timesync_is_answered() -> None:
    modes = ModeMachine(ModeParams())
    queue = CommandQueue()
    ap = AutopilotInput(VehicleState(), queue, modes, TimeSync(), lambda: 2.0)
    ok, actions = modes.request("takeoff", 1.0, VehicleStatus())
    assert ok and modes.mode == Mode.TAKEOFF
    for a in actions:
        if not isinstance(a, StatusText):
            queue.push(a)
    (sent,) = ap.poll_commands(1.0, SYSID, AP_COMPID)   # the arm first, to the autopilot, confirmation 0
    assert isinstance(sent, ToAutopilot) and sent.msg.command == mavlink.MAV_CMD_COMPONENT_ARM_DISARM
    assert (sent.msg.target_system, sent.msg.target_component, sent.msg.confirmation) == (SYSID, AP_COMPID, 0)
    out = ap.on_message(wire(mavlink.MAVLink_command_ack_message(mavlink.MAV_CMD_COMPONENT_ARM_DISARM,
                                                                 mavlink.MAV_RESULT_DENIED, 0, 0, SYSID, 191)))
    told = [o.text for o in out if isinstance(o, StatusText)]
    assert told[0] == "companion: autopilot arm failed (MAV_RESULT_DENIED)"
    assert modes.mode == Mode.IDLE and queue.pending == []
    (reply,) = ap.on_message(wire(mavlink.MAVLink_timesync_message(0, 777)))
    assert isinstance(reply, ToAutopilot) and (reply.msg.tc1, reply.msg.ts1) == (2_000_000_000, 777)


def test_the_vehicle_state_follows_the_autopilot_heartbeat_not_a_ground_station_s() -> None:
    vehicle = VehicleState()
    ap = AutopilotInput(vehicle, CommandQueue(), ModeMachine(ModeParams()), TimeSync(), lambda: 3.0)
    armed = mavlink.MAV_MODE_FLAG_SAFETY_ARMED
    ap.on_message(wire(mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, armed, 0,
                                                         0, 3)))
    assert not vehicle.armed and vehicle.heartbeat_wall_s is None
    ap.on_message(wire(mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, armed,
                                                         0, 0, 3)))
    assert vehicle.armed and vehicle.heartbeat_wall_s == 3.0


def test_the_autopilot_altitude_is_the_baro_height_while_fresh() -> None:
    """ALTITUDE's altitude_relative (the bridge's barometer-fused height) is kept with its arrival time; older
    than BARO_HEIGHT_MAX_AGE_S, or NaN (no baro fused), it is no height."""
    from companion.vehicle_state import BARO_HEIGHT_MAX_AGE_S

    vehicle = VehicleState()
    now = [10.0]
    ap = AutopilotInput(vehicle, CommandQueue(), ModeMachine(ModeParams()), TimeSync(), lambda: now[0])
    assert vehicle.baro_height(10.0) is None
    ap.on_message(wire(mavlink.MAVLink_altitude_message(0, 1.9, math.nan, 1.9, 1.9, math.nan, math.nan)))
    assert vehicle.baro_height(10.0) == pytest.approx(1.9)
    assert vehicle.baro_height(10.0 + BARO_HEIGHT_MAX_AGE_S + 0.01) is None
    now[0] = 11.0
    ap.on_message(wire(mavlink.MAVLink_altitude_message(0, math.nan, math.nan, math.nan, math.nan, math.nan,
                                                        math.nan)))
    assert vehicle.baro_height(11.0) is None


def test_the_ceilings_baro_height_is_the_higher_of_the_fused_one_and_the_boards_own_since_the_ground() -> None:
    """The fused height's reference follows the odometry's height in the air (the bridge's BRG_BARO_REF_T): against
    an odometry drifting low it reads low too. ALTITUDE's altitude_monotonic, the board's own altitude, less its
    value when the vehicle was last on the ground, is a height that follows nothing: the ceiling takes the higher."""
    vehicle = VehicleState()
    now = [10.0]
    ap = AutopilotInput(vehicle, CommandQueue(), ModeMachine(ModeParams()), TimeSync(), lambda: now[0])

    def altitude(relative: float, monotonic: float) -> None:
        ap.on_message(wire(mavlink.MAVLink_altitude_message(0, monotonic, math.nan, relative, relative, math.nan,
                                                            math.nan)))

    def landed(state: int) -> None:
        ap.on_message(wire(mavlink.MAVLink_extended_sys_state_message(mavlink.MAV_VTOL_STATE_MC, state)))

    landed(mavlink.MAV_LANDED_STATE_IN_AIR)           # the companion started in flight:
    altitude(1.0, 101.4)                               # not yet seen on the ground, the fused height alone
    assert vehicle.baro_height(10.0) == pytest.approx(1.0, abs=1e-4)
    landed(mavlink.MAV_LANDED_STATE_ON_GROUND)
    altitude(0.0, 99.9)                                # on the ground: the board's altitude is the reference,
    altitude(0.0, 100.1)                               # the mean of its samples there (it jitters by centimetres)
    altitude(0.0, 100.0)
    assert vehicle.baro_monotonic_ground_m == pytest.approx(100.0, abs=1e-4)
    assert vehicle.baro_height(10.0) == pytest.approx(0.0, abs=1e-4)
    landed(mavlink.MAV_LANDED_STATE_IN_AIR)
    altitude(1.0, 101.4)                               # the fused height follows an odometry 0.4 m low
    assert vehicle.baro_height(10.0) == pytest.approx(1.4, abs=1e-4)
    altitude(1.6, 101.4)                               # or reads higher than the board's: the higher
    assert vehicle.baro_height(10.0) == pytest.approx(1.6, abs=1e-4)
    altitude(math.nan, 101.4)                          # no fused height (the bridge's baro not fused)
    assert vehicle.baro_height(10.0) == pytest.approx(1.4, abs=1e-4)
    landed(mavlink.MAV_LANDED_STATE_ON_GROUND)
    altitude(0.0, 100.3)                               # landed again: a new reference (the flight's drift)
    landed(mavlink.MAV_LANDED_STATE_IN_AIR)
    altitude(0.5, 100.9)
    assert vehicle.baro_height(10.0) == pytest.approx(0.6, abs=1e-4)


def imu(time_usec: int, gyro_z: float = 0.1) -> Any:
    return wire(mavlink.MAVLink_highres_imu_message(time_usec, 0.0, 0.0, -9.81, 0.0, 0.0, gyro_z, 0, 0, 0, 0, 0, 0, 0,
                                                    0x3F))


def test_imu_samples_are_checked_and_the_wait_for_them_gives_up_on_a_lagging_stream() -> None:
    sample = imu_sample(imu(2_500_000))
    assert sample is not None and sample.stamp_s == 2.5 and sample.gyro_q_rad_s[2] == pytest.approx(0.1)
    assert imu_sample(imu(2_500_000, gyro_z=float("nan"))) is None and imu_sample(imu(2**60)) is None
    clock = ImuClock(feedback_rate_hz=50.0, imu_wait_s=0.005, imu_slack_s=0.005)
    assert clock.feedback_due(1.000) and not clock.feedback_due(1.010) and clock.feedback_due(1.021)
    assert ImuClock.silent(5.0, None) and ImuClock.silent(5.0, 5.0 - 2 * IMU_SILENT_S)
    assert not ImuClock.silent(5.0, 4.95)
    assert not clock.should_wait(1.0, None) and not clock.should_wait(1.0, 0.7)   # no IMU, or not flowing
    assert clock.should_wait(1.0, 0.99) and not clock.caught_up(1.0, 0.99) and clock.caught_up(1.0, 0.996)
    for _ in range(IMU_LAG_LIMIT):
        clock.on_wait_timeout()
    assert not clock.should_wait(1.0, 0.99)   # it keeps lagging: no more waiting


def test_the_frame_state_counts_odometry_restarts_and_starts_the_pan_scan_at_teleop() -> None:
    st = FrameState(HeightParams())
    good, bad = type("Out", (), {"odometry_ok": True}), type("Out", (), {"odometry_ok": False})
    st.on_odometry(good, first_frame=True)
    st.on_odometry(bad, first_frame=False)
    st.on_odometry(None, first_frame=False)
    st.on_odometry(good, first_frame=False)
    assert st.odometry_ok and st.reset_counter == 1
    scan = PanScanParams(True, 0.6, 1.5)
    st.on_mode(Mode.HOLD, 9.0)
    assert st.scan(Mode.HOLD, 9.5, scan) == NO_SCAN
    st.on_mode(Mode.TELEOP, 10.0)
    st.on_mode(Mode.TELEOP, 11.0)   # already scanning: the origin stays
    assert st.scan(Mode.TELEOP, 12.0, scan) == pan_scan(scan, 2.0)
    st.on_mode(Mode.HOLD, 13.0)
    st.on_mode(Mode.TELEOP, None)   # re-entered before any frame: from 0
    assert st.scan(Mode.TELEOP, 14.0, scan) == pan_scan(scan, 14.0)

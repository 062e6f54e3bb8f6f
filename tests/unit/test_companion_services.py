"""The daemon's small parts: routing decisions, deadlines and periodic tasks, the parameter service, the progress
line, the frame recording (unit tier)."""

from __future__ import annotations

import math
from typing import Any

import pytest

from companion.config import PanScanConfig
from companion.modes import StatusText
from companion.params import PARAM_NAMES, CompanionParams, handle_param_message, set_by_index
from companion.recording import FrameRecording
from companion.reference_params import ReferenceParams
from companion.router import route_from_autopilot, route_from_gcs
from companion.scheduler import Deadlines, HeartbeatBehindAutopilot, PeriodicTasks, StampTicker, Task
from companion.stats import AirborneCounts, ProgressLine, Stats
from quadlink.mavlink import mavlink

ME = 191


def test_autopilot_messages_go_to_the_gcs_unless_addressed_to_the_companion() -> None:
    hb = route_from_autopilot("HEARTBEAT", None, ME)
    assert hb.consume and hb.forward
    status = route_from_autopilot("SYS_STATUS", None, ME)
    assert not status.consume and status.forward
    ack_to_me = route_from_autopilot("COMMAND_ACK", ME, ME)
    assert ack_to_me.consume and not ack_to_me.forward
    ack_to_gcs = route_from_autopilot("COMMAND_ACK", 190, ME)
    assert not ack_to_gcs.consume and ack_to_gcs.forward
    assert route_from_autopilot("COMMAND_ACK", 0, ME).consume


def test_gcs_messages_route_by_target() -> None:
    mc = route_from_gcs("MANUAL_CONTROL", 1, None, 1, ME)
    assert mc.consume and not mc.forward
    assert not route_from_gcs("MANUAL_CONTROL", 7, None, 1, ME).consume
    to_me = route_from_gcs("COMMAND_LONG", 1, ME, 1, ME)
    assert to_me.consume and not to_me.forward
    to_ap = route_from_gcs("COMMAND_LONG", 1, 1, 1, ME)
    assert not to_ap.consume and to_ap.forward
    other = route_from_gcs("COMMAND_LONG", 2, 1, 1, ME)
    assert not other.consume and not other.forward
    bcast = route_from_gcs("PARAM_REQUEST_LIST", 1, 0, 1, ME)
    assert bcast.consume and bcast.forward
    assert not route_from_gcs("COMMAND_LONG", 0, 0, 1, ME).consume


def test_motion_commands_from_a_ground_station_never_reach_the_autopilot_raw() -> None:
    # issue 14: the companion is the one arbiter of motion
    for kind in ("SET_POSITION_TARGET_LOCAL_NED", "SET_POSITION_TARGET_GLOBAL_INT", "SET_ATTITUDE_TARGET", "SET_MODE"):
        for target_comp in (1, 0, None):
            r = route_from_gcs(kind, 1, target_comp, 1, ME)
            assert r.consume and not r.forward, (kind, target_comp)
    assert not route_from_gcs("SET_POSITION_TARGET_LOCAL_NED", 2, 1, 1, ME).forward   # another system


def test_deadlines_fire_once_per_period() -> None:
    d = Deadlines()
    fired = [t for t in [0.0, 0.3, 0.99, 1.0, 1.5, 2.0, 2.2] if d.due("hb", t, 1.0)]
    assert fired == [0.0, 1.0, 2.0]
    d.arm("later", 5.0)
    assert not d.due("later", 4.9, 1.0) and d.due("later", 5.0, 1.0)


def test_stamp_ticker_holds_its_rate_on_a_faster_clock_and_rearms_on_rewind() -> None:
    tick = StampTicker(0.02)   # 50 Hz on 500 Hz stamps
    stamps = [k * 0.002 for k in range(1, 501)]
    fired = [t for t in stamps if tick.due(t)]
    gaps = [b - a for a, b in zip(fired[1:], fired[2:])]
    # one per 20 ms period, also where a boundary stamp rounds just below the boundary (k * 0.002 floats)
    assert len(fired) == 51 and all(abs(g - 0.02) < 1e-9 for g in gaps)
    assert not tick.due(0.5)   # half a second back: a late sample, not a restart
    assert tick.due(0.001)     # a restarted producer (more than a second back) re-arms it
    assert not tick.due(0.002)


def test_params_validate_and_the_protocol_answers() -> None:
    p = CompanionParams(PanScanConfig(enabled=True), ReferenceParams())
    assert p.names == PARAM_NAMES
    assert p.set("CMP_K_V", 0.8) and p.reference.k_v_m_s == 0.8
    assert not p.set("CMP_K_V", -1.0) and p.reference.k_v_m_s == 0.8
    assert not p.set("PANSCAN_OMEGA", 0.0) and not p.set("CMP_SAFE_DIST", math.nan) and not p.set("NOPE", 1.0)
    omega0 = p.scan.omega_rad_s
    assert p.set("PANSCAN_OMEGA", 2.0) and p.scan.omega_rad_s == 2.0 != omega0
    assert set_by_index(p, PARAM_NAMES.index("PANSCAN_EN"), 0.0) == "PANSCAN_EN" and not p.scan.enabled
    assert set_by_index(p, 99, 1.0) is None

    replies, changed = handle_param_message(p, mavlink.MAVLink_param_request_list_message(1, ME))
    assert changed is None and [r.param_id for r in replies] == list(PARAM_NAMES)
    assert all(r.param_count == len(PARAM_NAMES) for r in replies)
    replies, changed = handle_param_message(
        p, mavlink.MAVLink_param_set_message(1, ME, b"CMP_K_PSI", 0.5, mavlink.MAV_PARAM_TYPE_REAL32))
    assert changed == "CMP_K_PSI" and replies[0].param_value == pytest.approx(0.5)
    replies, changed = handle_param_message(
        p, mavlink.MAVLink_param_set_message(1, ME, b"CMP_K_PSI", -2.0, mavlink.MAV_PARAM_TYPE_REAL32))
    # refused: the unchanged value goes back (the sender's retries end) with a STATUSTEXT saying why
    assert changed is None and p.reference.k_psi_rad_s == pytest.approx(0.5)
    assert replies[0].get_type() == "PARAM_VALUE" and isinstance(replies[1], StatusText) and len(replies) == 2
    assert replies[0].param_id == "CMP_K_PSI" and replies[0].param_value == pytest.approx(0.5)
    assert replies[1].text.startswith("companion: CMP_K_PSI refused: ") and len(replies[1].text) > 35


def test_periodic_tasks_run_in_order_and_the_conditional_ones_only_while_their_condition_holds() -> None:
    periods = {task: 1.0 for task in Task} | {Task.FEEDBACK: 0.02, Task.PROGRESS: 5.0}
    tasks = PeriodicTasks(periods, start_s=0.0)
    assert tasks.due(0.0, camera_silent=False, imu_silent=False) == [Task.HEARTBEAT, Task.TIMESYNC, Task.GCS_TIMESYNC,
                                                                      Task.COMMAND_AGE]
    assert tasks.due(0.5, camera_silent=True, imu_silent=True) == [Task.FALLBACK, Task.FEEDBACK]
    assert tasks.due(0.51, camera_silent=True, imu_silent=True) == []
    assert tasks.due(1.0, camera_silent=False, imu_silent=False) == [Task.HEARTBEAT, Task.TIMESYNC, Task.GCS_TIMESYNC,
                                                                      Task.COMMAND_AGE]
    assert tasks.due(5.0, camera_silent=False, imu_silent=False)[-1] == Task.PROGRESS   # first one period in


def test_the_companions_heartbeat_waits_for_the_autopilots_next_message_while_the_autopilot_is_heard() -> None:
    gate = HeartbeatBehindAutopilot(lost_s=1.5)
    assert gate.due(0.0), "never heard the autopilot: the heartbeat goes alone"
    assert not gate.forwarded(), "nothing held"
    assert not gate.due(1.0), "the autopilot heard 1 s ago (marked at this turn): held"
    assert not gate.expired(1.2)
    assert gate.forwarded(), "the next forwarded autopilot message carries it"
    assert not gate.forwarded(), "once"
    # the autopilot falls silent while a heartbeat waits: it goes alone once the silence passes lost_s
    assert not gate.due(2.0)
    assert not gate.expired(3.5), "1.5 s of silence is still heard"
    assert gate.expired(3.6) and not gate.expired(3.7)
    assert gate.due(4.0), "silent: due heartbeats go at once"


def test_the_progress_line_gives_the_camera_rate_since_the_last_line() -> None:
    stats, line = Stats(frames=150), ProgressLine(5.0)
    text = line.line(stats, "TELEOP", True, False, "height ?", "commands 0 ok")
    assert text.startswith("mode TELEOP  camera 30.0 fps  frame->setpoint p50 -")
    assert text.endswith("gcs link lost  manual 0  routed 0 to GCS / 0 to autopilot  height ?  commands 0 ok")
    stats.frames += 50
    assert "camera 10.0 fps" in line.line(stats, "TELEOP", True, False, "height ?", "commands 0 ok")


def test_a_failing_frame_recording_stops_and_the_loop_goes_on() -> None:
    class Full:
        def __init__(self) -> None:
            self.written, self.closed = 0, False

        def write(self, frame: object) -> None:
            self.written += 1
            if self.written == 2:
                raise OSError("No space left on device")

        def close(self) -> None:
            self.closed = True

    writer = Full()
    frame: Any = None
    rec = FrameRecording(writer)
    for _ in range(4):
        rec.write(frame)
    rec.close()
    assert writer.written == 2 and not writer.closed   # stopped at the failure; nothing more to close
    FrameRecording(None).write(frame)   # no recording: nothing to do


def test_airborne_counts_take_only_the_frames_in_the_air() -> None:
    """The odometry's totals include the ground before the take-off; the air's counts take each output's increase
    only while the vehicle is off the ground, and a reset odometry's counts (lower than before) are all new."""
    from perception.odometry import OdometryCounts

    air = AirborneCounts()
    air.on_output(OdometryCounts(fallbacks=200, lost=8), airborne=False)     # on the ground: bridged, held
    air.on_output(OdometryCounts(fallbacks=210, lost=8), airborne=False)
    assert air.counts == OdometryCounts()
    air.on_output(OdometryCounts(fallbacks=213, lost=8, rejected_jumps=1), airborne=True)
    air.on_output(OdometryCounts(fallbacks=213, lost=9, rejected_jumps=1, restarts=2), airborne=True)
    assert air.counts == OdometryCounts(fallbacks=3, lost=1, rejected_jumps=1, restarts=2)
    air.on_output(OdometryCounts(fallbacks=2), airborne=True)    # the odometry was reset: its 2 bridged are new
    assert air.counts == OdometryCounts(fallbacks=5, lost=1, rejected_jumps=1, restarts=2)
    air.on_output(OdometryCounts(fallbacks=50), airborne=False)  # landed: the ground's frames stay out
    assert air.counts.fallbacks == 5


"""Regression tests for issue 16's bridge defects: each fails on the code before the fix.

The autopilot is driven in-process through its real MAVLink handlers (messages packed by a real pymavlink
codec and parsed back), with the point-mass vehicle of ``test_bridge_autopilot``.
"""

from __future__ import annotations

import math
import struct

import pytest
from test_bridge_autopilot import GCS, Sim, fly_to_hover, msg, velocity_body

from firmware_bridge.autopilot import Autopilot, FlightMode, NonFiniteCommand
from firmware_bridge.params import ParamTable
from firmware_bridge.state import BoardCommand
from quadlink.frames import quat_wxyz_from_euler
from quadlink.mavlink import mavlink
from quadlink.vehicle import VehicleConfig


def _finite(cmd: BoardCommand) -> bool:
    return all(math.isfinite(v) for v in (cmd.roll_rad, cmd.pitch_rad, cmd.yaw_rate_rad_s, cmd.thrust))


def _offboard_attitude(sim: Sim):
    fly_to_hover(sim)
    q = quat_wxyz_from_euler(0.0, 0.0, 0.0)
    good = GCS.set_attitude_target_encode(0, 1, 1, 0, q, 0, 0, 0.1, 0.5)
    sim.step(0.3, setpoint=good)
    assert sim.command(mavlink.MAV_CMD_DO_SET_MODE, 1, 6, 0)[0] == mavlink.MAV_RESULT_ACCEPTED
    sim.step(0.2, setpoint=good)
    return q


def test_attitude_target_with_nan_yaw_rate_is_refused_and_never_reaches_the_board():
    sim = Sim()
    q = _offboard_attitude(sim)
    rejected = sim.ap.counters["setpoint_rejected"]
    bad = GCS.set_attitude_target_encode(0, 1, 1, 0, q, 0, 0, math.nan, 0.5)  # NaN body yaw rate, used
    for _ in range(20):
        sim.step(0.01, setpoint=bad)
        assert _finite(sim.ap.last_board_command)
    assert sim.ap.counters["setpoint_rejected"] > rejected
    assert sim.ap.last_board_command.yaw_rate_rad_s == pytest.approx(0.1)  # still the last good setpoint


@pytest.mark.parametrize("field", ["yaw_rate", "yaw"])
def test_position_target_with_a_non_finite_used_field_is_refused(field):
    ap = Autopilot(VehicleConfig(), ParamTable())
    if field == "yaw_rate":
        sp = velocity_body(0.5, 0.0, 0.0, yaw_rate=math.inf)
    else:  # velocity + yaw (type_mask 2503: yaw rate ignored, yaw used)
        sp = GCS.set_position_target_local_ned_encode(0, 1, 1, mavlink.MAV_FRAME_LOCAL_NED, 2503, 0, 0, 0,
                                                      0.5, 0, 0, 0, 0, 0, math.nan, 0)
    ap.handle_mavlink(0.0, msg(sp))
    assert ap.counters["setpoint_rejected"] == 1 and ap.state.vel_sp is None  # before: yaw rate NaN -> 0.0, accepted


def test_board_command_refuses_nan_and_the_control_step_stays_finite(monkeypatch):
    with pytest.raises(NonFiniteCommand):
        BoardCommand(0.0, 0.0, math.nan, 0.5, True)
    sim = Sim()
    fly_to_hover(sim)
    real_update = sim.ap.tracker.update

    def broken(*args, **kwargs):  # a tracker bug producing NaN: level hold, counted, never a NaN frame
        out = real_update(*args, **kwargs)
        return type(out)(math.nan, out.pitch_rad, out.yaw_rate_rad_s, math.nan, out.a_des_h_m_s2, out.saturated)

    monkeypatch.setattr(sim.ap.tracker, "update", broken)
    cmd = sim.ap.control_step(sim.t + 0.01)
    assert _finite(cmd) and cmd.roll_rad == 0.0 and cmd.thrust > 0.3 and cmd.armed
    assert sim.ap.counters["nonfinite_commands"] == 1


@pytest.mark.parametrize("interval_us", [3.4e38, math.nan, math.inf, -1.0, -5.0, 5e6])
def test_heartbeat_cannot_be_silenced_by_set_message_interval(interval_us):
    sim = Sim()
    sim.step(0.5)
    result = sim.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAVLINK_MSG_ID_HEARTBEAT, interval_us)[0]
    assert result == mavlink.MAV_RESULT_DENIED
    t0 = sim.t
    beats = [t0 + 0.02 * i for i in range(150)  # 3 s of 50 Hz ticks
             if any(o.msg.get_type() == "HEARTBEAT" for o in sim.ap.tick(t0 + 0.02 * i))]
    assert len(beats) == 3 and max(b - a for a, b in zip([t0] + beats, beats)) <= 1.0 + 1e-6


def test_set_message_interval_bounds_other_streams():
    sim = Sim()
    att = mavlink.MAVLINK_MSG_ID_ATTITUDE
    before = sim.ap.stream_interval_s[att]
    for bad in (3.4e38, math.nan, -5.0):
        assert sim.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, att, bad)[0] == mavlink.MAV_RESULT_DENIED
        assert sim.ap.stream_interval_s[att] == before
    assert sim.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, att, -1)[0] == mavlink.MAV_RESULT_ACCEPTED
    assert sim.ap.stream_interval_s[att] < 0  # -1: off
    assert sim.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, att, 0)[0] == mavlink.MAV_RESULT_ACCEPTED
    assert sim.ap.stream_interval_s[att] == pytest.approx(0.02)  # 0: default
    # a NaN message id: the required param of the one NaN table (quadlink.mavlink.command_params) -> DENIED
    assert sim.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, math.nan, 1e5)[0] == mavlink.MAV_RESULT_DENIED


@pytest.mark.parametrize("param1", [math.nan, math.inf, 0.4, 2.0, -1.0])
def test_arm_disarm_param1_must_be_exactly_zero_or_one(param1):
    sim = Sim()
    sim.step(0.3)
    assert sim.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)[0] == mavlink.MAV_RESULT_ACCEPTED
    sim.step(0.1)
    assert sim.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, param1, math.nan)[0] == mavlink.MAV_RESULT_DENIED
    assert sim.ap.armed_cmd  # before: NaN read as 0 = disarm
    assert sim.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, math.nan)[0] == mavlink.MAV_RESULT_ACCEPTED
    assert not sim.ap.armed_cmd


def test_forced_disarm_needs_the_exact_magic_number():
    sim = Sim()
    fly_to_hover(sim)
    for almost in (21196.4, math.nan):
        assert sim.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, almost)[0] == mavlink.MAV_RESULT_DENIED
    assert sim.ap.armed_cmd and sim.ap.in_air


def _param_set(sim: Sim, name: bytes, value: float, ptype: int = mavlink.MAV_PARAM_TYPE_REAL32):
    out = sim.send(GCS.param_set_encode(1, 1, name, value, ptype))
    return [o for o in out if o.msg.get_type() == "PARAM_VALUE"], [o.msg.text for o in out
                                                                   if o.msg.get_type() == "STATUSTEXT"]


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf, 1e30, 0.0])
def test_param_set_non_finite_or_out_of_range_is_refused_with_the_unchanged_value(value):
    sim = Sim()
    values, _ = _param_set(sim, b"MIS_TAKEOFF_ALT", 2.5)
    assert values[0].msg.param_value == pytest.approx(2.5)
    values, texts = _param_set(sim, b"MIS_TAKEOFF_ALT", value)
    assert len(values) == 1 and values[0].msg.param_value == pytest.approx(2.5)  # before: reset to default 1.0
    assert values[0].link == 0  # answered to the sender
    assert sim.ap.params["MIS_TAKEOFF_ALT"] == 2.5 and sim.ap.takeoff_target_m == 2.5
    assert any("MIS_TAKEOFF_ALT refused" in t for t in texts)
    assert sim.ap.counters["param_refused"] == 1


def test_param_set_with_a_mismatched_type_is_refused():
    """An INT32 7 sent bytewise (PX4's PARAM_ENCODE_BYTEWISE) to a REAL32 parameter: before, it became 0.2."""
    sim = Sim()
    int32_7 = struct.unpack("<f", struct.pack("<i", 7))[0]
    values, texts = _param_set(sim, b"MIS_TAKEOFF_ALT", int32_7, mavlink.MAV_PARAM_TYPE_INT32)
    assert values[0].msg.param_value == pytest.approx(1.0) and sim.ap.params["MIS_TAKEOFF_ALT"] == 1.0
    assert values[0].msg.param_type == mavlink.MAV_PARAM_TYPE_REAL32
    assert any("refused" in t for t in texts)


class _Exploding(float):
    """A field value whose comparisons raise: a bug class no handler anticipates."""

    def __eq__(self, other):  # noqa: ANN001
        raise RuntimeError("boom")

    __hash__ = float.__hash__


def test_an_unexpected_exception_in_a_handler_is_counted_and_the_loop_goes_on():
    sim = Sim()
    sim.step(0.2)
    bad = msg(GCS.command_long_encode(1, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0))
    bad.command = _Exploding(bad.command)
    assert sim.ap.handle_mavlink(sim.t, bad) == []  # before: RuntimeError escaped into the daemon's loop
    assert sim.ap.counters["handler_errors"] == 1
    assert sim.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)[0] == mavlink.MAV_RESULT_ACCEPTED
    assert sim.ap.mode == FlightMode.POSCTL

"""The motion arbiter (companion/arbiter.py): sources, frames, priority and liveness, with time as an argument.

The scripted setpoints are packed and decoded by the dialect's codec exactly as MAVSDK's offboard plugin sends
them (set_velocity_body: MAV_FRAME_BODY_NED, type_mask 1479 with the yaw rate; set_velocity_ned:
MAV_FRAME_LOCAL_NED, type_mask 2503 with the yaw; set_position_ned: LOCAL_NED, 2552).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.arbiter import (
    Arbiter,
    ArbiterParams,
    Pose,
    Refusal,
    ScriptTarget,
    Setpoint,
    Source,
    parse_setpoint,
    script_velocity_h,
)
from quadlink.mavlink import mavlink

MAVSDK_VELOCITY_BODY_MASK = 1 | 2 | 4 | 64 | 128 | 256 | 1024       # = 1479, offboard_impl.cpp send_velocity_body
MAVSDK_VELOCITY_NED_MASK = 1 | 2 | 4 | 64 | 128 | 256 | 2048        # = 2503, send_velocity_ned
MAVSDK_POSITION_NED_MASK = 8 | 16 | 32 | 64 | 128 | 256 | 2048      # = 2552, send_position_ned
POSE = Pose((1.0, 2.0, -1.0), math.radians(90.0))


def _wire(frame: int, mask: int, pos: tuple[float, float, float] = (0.0, 0.0, 0.0),
          vel: tuple[float, float, float] = (0.0, 0.0, 0.0), yaw: float = 0.0, yaw_rate: float = 0.0) -> Setpoint:
    """A setpoint through the codec (pack, then parse the bytes back), as the daemon receives it."""
    codec = mavlink.MAVLink(None, 255, 190)
    msg = mavlink.MAVLink_set_position_target_local_ned_message(1234, 1, 1, frame, mask, *pos, *vel, 0.0, 0.0, 0.0,
                                                                yaw, yaw_rate)
    decoded = mavlink.MAVLink(None, 1, 191).parse_char(msg.pack(codec))
    return Setpoint(decoded.coordinate_frame, decoded.type_mask, (decoded.x, decoded.y, decoded.z),
                    (decoded.vx, decoded.vy, decoded.vz), decoded.yaw, decoded.yaw_rate)


def test_mavsdk_masks_are_the_documented_ones() -> None:
    assert (MAVSDK_VELOCITY_BODY_MASK, MAVSDK_VELOCITY_NED_MASK, MAVSDK_POSITION_NED_MASK) == (1479, 2503, 2552)


def test_velocity_body_is_yaw_aligned_with_yaw_rate() -> None:
    sp = _wire(mavlink.MAV_FRAME_BODY_NED, MAVSDK_VELOCITY_BODY_MASK, vel=(0.5, -0.2, 0.1), yaw_rate=0.3)
    t = parse_setpoint(sp, POSE)
    assert isinstance(t, ScriptTarget)
    v, r = script_velocity_h(t, POSE, ArbiterParams())
    assert v == pytest.approx([0.5, -0.2, 0.1], abs=1e-6) and r == pytest.approx(0.3, abs=1e-6)
    # with the pan-scan swung 0.2 rad right, "forward" is the swing's centre: 0.2 rad left in H
    v, _ = script_velocity_h(t, Pose(POSE.position_ned_m, POSE.yaw_rad, 0.2), ArbiterParams())
    assert math.atan2(v[1], v[0]) == pytest.approx(math.atan2(-0.2, 0.5) - 0.2, abs=1e-6)


def test_velocity_ned_is_rotated_into_h_and_yaw_becomes_a_rate() -> None:
    # heading east (yaw 90 deg): north in NED is to the left in H
    sp = _wire(mavlink.MAV_FRAME_LOCAL_NED, MAVSDK_VELOCITY_NED_MASK, vel=(0.4, 0.0, 0.0), yaw=math.radians(100))
    t = parse_setpoint(sp, POSE)
    assert isinstance(t, ScriptTarget)
    p = ArbiterParams(yaw_gain_per_s=2.0)
    v, r = script_velocity_h(t, POSE, p)
    assert v == pytest.approx([0.0, -0.4, 0.0], abs=1e-6)
    assert r == pytest.approx(2.0 * math.radians(10.0), abs=1e-6)


def test_position_target_becomes_a_bounded_velocity_toward_it() -> None:
    sp = _wire(mavlink.MAV_FRAME_LOCAL_NED, MAVSDK_POSITION_NED_MASK, pos=(1.0, 5.0, -1.0))
    t = parse_setpoint(sp, POSE)
    assert isinstance(t, ScriptTarget) and t.position_ned_m == pytest.approx((1.0, 5.0, -1.0))
    p = ArbiterParams(position_gain_per_s=1.0, position_max_speed_m_s=0.5)
    v, _ = script_velocity_h(t, POSE, p)
    assert v == pytest.approx([0.5, 0.0, 0.0], abs=1e-6)   # 3 m east = straight ahead, clamped to 0.5 m/s
    near = Pose((1.0, 4.8, -1.0), POSE.yaw_rad)
    v, _ = script_velocity_h(t, near, p)
    assert v == pytest.approx([0.2, 0.0, 0.0], abs=1e-6)   # proportional inside the clamp
    # a body offset is resolved against the position at receipt: 1 m forward of (1, 2) facing east = (1, 3)
    t = parse_setpoint(_wire(mavlink.MAV_FRAME_BODY_OFFSET_NED, 3576, pos=(1.0, 0.0, 0.0)), POSE)
    assert isinstance(t, ScriptTarget) and t.position_ned_m == pytest.approx((1.0, 3.0, -1.0))


@pytest.mark.parametrize("frame, mask, why", [
    (mavlink.MAV_FRAME_LOCAL_NED, 3135, "acceleration"),             # acceleration setpoint (PX4's accel mask)
    (mavlink.MAV_FRAME_LOCAL_NED, 2503 | 8, "partial"),              # vx ignored only
    (mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT, 2503, "frame"),
    (mavlink.MAV_FRAME_LOCAL_NED, 4095 - 512, "empty"),
])
def test_unsupported_setpoints_are_refused_with_a_reason(frame: int, mask: int, why: str) -> None:
    got = parse_setpoint(_wire(frame, mask), POSE)
    assert isinstance(got, Refusal) and why in got.text


def test_position_target_without_a_position_estimate_is_refused() -> None:
    got = parse_setpoint(_wire(mavlink.MAV_FRAME_LOCAL_NED, 2552, pos=(1, 1, -1)), Pose(None, None))
    assert isinstance(got, Refusal)


def _body(v: float = 0.5) -> Setpoint:
    return _wire(mavlink.MAV_FRAME_BODY_NED, MAVSDK_VELOCITY_BODY_MASK, vel=(v, 0.0, 0.0))


def test_operator_overrides_a_script_only_out_of_the_deadband() -> None:
    a = Arbiter(ArbiterParams())
    a.on_setpoint(0.0, _body(), POSE)
    a.on_manual_control(0.0, 0, 0, 500)            # handle centred: the script flies
    cmd = a.command(0.01, POSE)
    assert cmd.source == Source.SCRIPT and cmd.v_h_m_s is not None and cmd.v_h_m_s[0] == pytest.approx(0.5)
    a.on_manual_control(0.02, 20, 0, 500)          # 0.02 < dead-band 0.03: still the script
    assert a.command(0.03, POSE).source == Source.SCRIPT
    a.on_manual_control(0.04, 300, 0, 500)         # out of the dead-band: the operator
    cmd = a.command(0.05, POSE)
    assert cmd.source == Source.OPERATOR and cmd.operator is not None and cmd.operator.qx > 0.2
    a.on_manual_control(0.06, 0, 0, 500)           # released: back to the script
    assert a.command(0.07, POSE).source == Source.SCRIPT


def test_script_loss_holds_like_px4_com_of_loss_t() -> None:
    p = ArbiterParams(script_timeout_s=1.0)
    a = Arbiter(p)
    a.on_setpoint(0.0, _body(), POSE)
    assert a.on_set_mode(0.1, offboard=True)
    assert a.command(0.99, POSE).source == Source.SCRIPT
    cmd = a.command(1.01, POSE)
    assert cmd.source == Source.NONE and cmd.hold
    assert not a.offboard_engaged and any("lost" in e for e in a.take_events())
    # a tool that switches modes (MAVSDK) must re-engage: a resumed stream alone does not
    a.on_setpoint(2.0, _body(), POSE)
    assert a.command(2.01, POSE).source == Source.NONE
    assert a.on_set_mode(2.02, offboard=True) and a.command(2.03, POSE).source == Source.SCRIPT


def test_a_script_that_never_switches_modes_is_engaged_by_its_stream() -> None:
    a = Arbiter(ArbiterParams())
    a.on_setpoint(0.0, _body(), POSE)
    assert a.command(0.1, POSE).source == Source.SCRIPT
    assert a.command(1.5, POSE).source == Source.NONE          # lost
    a.on_setpoint(2.0, _body(), POSE)                           # resumed: engaged again
    assert a.command(2.1, POSE).source == Source.SCRIPT


def test_offboard_needs_a_setpoint_stream_and_stop_holds() -> None:
    a = Arbiter(ArbiterParams())
    assert not a.on_set_mode(0.0, offboard=True)               # PX4: no stream, no offboard
    a.on_setpoint(0.1, _body(), POSE)
    assert a.on_set_mode(0.2, offboard=True)
    assert a.on_set_mode(0.3, offboard=False)                  # MAVSDK offboard.stop(): HOLD
    cmd = a.command(0.35, POSE)
    assert cmd.source == Source.NONE and cmd.hold


def test_link_is_alive_on_heartbeats_and_setpoints_not_only_manual_control() -> None:
    a = Arbiter(ArbiterParams(link_timeout_s=3.0))
    assert not a.link_alive(0.0)
    a.on_heartbeat(0.0)
    assert a.link_alive(2.9) and not a.link_alive(3.1)
    a.on_setpoint(3.0, _body(), POSE)
    assert a.link_alive(5.9)
    # the operator silent for its timeout: with no script the command is hold
    b = Arbiter(ArbiterParams(operator_timeout_s=0.5))
    b.on_manual_control(0.0, 500, 0, 500)
    assert b.command(0.4, POSE).source == Source.OPERATOR
    assert b.command(0.6, POSE).source == Source.NONE


events = st.lists(st.tuples(st.floats(0.0, 0.5), st.sampled_from(["manual", "manual0", "setpoint", "offboard",
                                                                   "hold", "heartbeat", "tick"])),
                  min_size=1, max_size=40)


@settings(max_examples=200, deadline=None)
@given(events)
def test_arbiter_invariants_over_any_event_sequence(seq: list[tuple[float, str]]) -> None:
    """Whatever arrives in whatever order: a script never flies while the operator's handle is out of the
    dead-band; nothing flies from a source older than its timeout; the command is always finite."""
    p = ArbiterParams()
    a = Arbiter(p)
    t = 0.0
    last = {"manual": -math.inf, "setpoint": -math.inf}
    deflected = False
    for dt, kind in seq:
        t += dt
        if kind in ("manual", "manual0"):
            a.on_manual_control(t, 800 if kind == "manual" else 0, 0, 500)
            last["manual"], deflected = t, kind == "manual"
        elif kind == "setpoint":
            a.on_setpoint(t, _body(0.7), POSE)
            last["setpoint"] = t
        elif kind == "offboard":
            a.on_set_mode(t, offboard=True)
        elif kind == "hold":
            a.on_set_mode(t, offboard=False)
        elif kind == "heartbeat":
            a.on_heartbeat(t)
        cmd = a.command(t, POSE)
        if cmd.source == Source.SCRIPT:
            assert not (deflected and t - last["manual"] <= p.operator_timeout_s)
            assert t - last["setpoint"] <= p.script_timeout_s
            assert cmd.v_h_m_s is not None and np.all(np.isfinite(cmd.v_h_m_s))
            assert float(np.linalg.norm(cmd.v_h_m_s)) <= p.script_max_speed_m_s + 1e-9
        elif cmd.source == Source.OPERATOR:
            assert t - last["manual"] <= p.operator_timeout_s
        else:
            assert cmd.hold


@settings(max_examples=200, deadline=None)
@given(st.sampled_from([mavlink.MAV_FRAME_LOCAL_NED, mavlink.MAV_FRAME_LOCAL_OFFSET_NED, mavlink.MAV_FRAME_BODY_NED,
                        mavlink.MAV_FRAME_BODY_OFFSET_NED, mavlink.MAV_FRAME_BODY_FRD]),
       st.integers(0, 4095), st.lists(st.floats(allow_nan=True, allow_infinity=True, width=32), min_size=8,
                                      max_size=8))
def test_any_setpoint_is_refused_or_gives_a_bounded_finite_command(frame: int, mask: int, values: list[float]) -> None:
    sp = Setpoint(frame, mask, tuple(values[0:3]), tuple(values[3:6]), values[6], values[7])  # type: ignore[arg-type]
    got = parse_setpoint(sp, POSE)
    if isinstance(got, Refusal):
        return
    p = ArbiterParams()
    v, r = script_velocity_h(got, POSE, p)
    assert np.all(np.isfinite(v)) and math.isfinite(r)
    assert float(np.linalg.norm(v)) <= p.script_max_speed_m_s + 1e-6 and abs(r) <= p.script_max_yaw_rate_rad_s


def test_the_last_command_is_forgotten_once_the_ground_station_asks_for_a_hold() -> None:
    """MAVSDK's offboard.stop(): the script's silence after it is meant (the mode machine holds, no land)."""
    a = Arbiter(ArbiterParams())
    assert a.last_command_s is None
    a.on_manual_control(1.0, 0, 0, 500)
    a.on_heartbeat(2.0)
    assert a.last_command_s == 1.0               # a heartbeat is no command
    a.on_set_mode(3.0, offboard=False)
    assert a.last_command_s is None
    a.on_manual_control(4.0, 0, 0, 500)
    assert a.last_command_s == 4.0


# ---------------------------------------------------------------- trajectory setpoints (issue 19)
def _trajectory_wire(pos: tuple[float, float, float], vel: tuple[float, float, float],
                     acc: tuple[float, float, float], mask: int = mavlink.POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE
                     ) -> Setpoint:
    """A PX4-style trajectory setpoint (``quadlink trajectory``'s: p + v + a + yaw, LOCAL_NED) through the codec."""
    codec = mavlink.MAVLink(None, 255, 190)
    msg = mavlink.MAVLink_set_position_target_local_ned_message(1234, 1, 1, mavlink.MAV_FRAME_LOCAL_NED, mask, *pos,
                                                                *vel, *acc, math.radians(90.0), 0.0)
    m = mavlink.MAVLink(None, 1, 191).parse_char(msg.pack(codec))
    return Setpoint(m.coordinate_frame, m.type_mask, (m.x, m.y, m.z), (m.vx, m.vy, m.vz), m.yaw, m.yaw_rate,
                    (m.afx, m.afy, m.afz))


def test_a_trajectory_setpoint_is_the_companion_position_loop_with_its_acceleration_in_h() -> None:
    from companion.arbiter import script_command_h

    # vehicle at (1, 2, -1) facing east; desired 0.1 m north of it, moving east at 0.5 m/s, accelerating north
    t = parse_setpoint(_trajectory_wire((1.1, 2.0, -1.0), (0.0, 0.5, 0.0), (0.4, 0.0, 0.0)), POSE)
    assert isinstance(t, ScriptTarget) and t.accel_ned_m_s2 == pytest.approx((0.4, 0.0, 0.0))
    p = ArbiterParams(trajectory_gain_per_s=1.25)
    v_h, yaw_rate, a_h = script_command_h(t, POSE, p)
    # v_ref (NED) = v_d - k_p e_x = (0.125, 0.5, 0); in H (x east = forward, y south = right): (0.5, -0.125, 0)
    assert v_h == pytest.approx([0.5, -0.125, 0.0], abs=1e-6)
    assert a_h is not None and a_h == pytest.approx([0.0, -0.4, 0.0], abs=1e-6)
    assert yaw_rate == pytest.approx(0.0, abs=1e-6)   # yaw target = current yaw
    a = Arbiter(p)
    assert a.on_setpoint(0.0, _trajectory_wire((1.1, 2.0, -1.0), (0.0, 0.5, 0.0), (0.4, 0.0, 0.0)), POSE) is None
    cmd = a.command(0.1, POSE)
    assert cmd.source == Source.SCRIPT and cmd.a_ff_h_m_s2 is not None and cmd.reason == "trajectory"
    # a plain velocity script carries no feed-forward
    a.on_setpoint(0.2, _wire(mavlink.MAV_FRAME_BODY_NED, 1479, vel=(0.3, 0.0, 0.0)), POSE)
    assert a.command(0.3, POSE).a_ff_h_m_s2 is None


def test_trajectory_correction_and_feed_forward_are_bounded() -> None:
    from companion.arbiter import script_command_h

    p = ArbiterParams(trajectory_max_correction_m_s=1.0, trajectory_max_accel_m_s2=3.0, script_max_speed_m_s=1.0)
    t = parse_setpoint(_trajectory_wire((100.0, 2.0, -1.0), (0.0, 0.0, 0.0), (50.0, 0.0, 0.0)), POSE)
    assert isinstance(t, ScriptTarget)
    v_h, _, a_h = script_command_h(t, POSE, p)
    assert float(np.linalg.norm(v_h)) == pytest.approx(1.0) and a_h is not None
    assert float(np.linalg.norm(a_h)) == pytest.approx(3.0)


@pytest.mark.parametrize("frame, mask, why", [
    (mavlink.MAV_FRAME_BODY_NED, 1031, "local frame"),                      # body-frame acceleration
    (mavlink.MAV_FRAME_LOCAL_NED, 3135, "acceleration"),                    # acceleration without a velocity
    (mavlink.MAV_FRAME_LOCAL_NED, 2048 | 64, "partial"),                    # afx ignored only
    (mavlink.MAV_FRAME_LOCAL_NED, 2048 | mavlink.POSITION_TARGET_TYPEMASK_FORCE_SET, "force"),
])
def test_acceleration_setpoints_other_than_trajectories_are_refused(frame: int, mask: int, why: str) -> None:
    got = parse_setpoint(_wire(frame, mask), POSE)
    assert isinstance(got, Refusal) and why in got.text

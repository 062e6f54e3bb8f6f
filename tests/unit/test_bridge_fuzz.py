"""Property tests: the bridge's MAVLink handlers, driven in-process, survive anything the wire can carry.

From a hovering point-mass flight (``test_bridge_autopilot.Sim``), each example sends a few generated
messages of every type the bridge handles, then flies on. Properties: no handler raises or trips the
catch-all, every board command is finite, the heartbeat keeps its 1 Hz, parameters stay inside their
bounds. Marked ``fuzz``; budget: ``QUADLINK_FUZZ_EXAMPLES`` (``scripts/fuzz.sh`` soaks).
"""

from __future__ import annotations

import copy
import math

import pytest
from fuzzing import FUZZ, hostile_floats, message_strategy, over_the_wire
from hypothesis import given
from hypothesis import strategies as st
from test_bridge_autopilot import GCS, Sim, fly_to_hover

from firmware_bridge.params import PARAM_SPECS
from quadlink.mavlink import mavlink

_target = {"target_system": st.sampled_from([0, 1, 7]), "target_component": st.sampled_from([0, 1, 9])}
_commands = st.sampled_from([mavlink.MAV_CMD_COMPONENT_ARM_DISARM, mavlink.MAV_CMD_DO_SET_MODE,
                             mavlink.MAV_CMD_NAV_TAKEOFF, mavlink.MAV_CMD_NAV_LAND, mavlink.MAV_CMD_REQUEST_MESSAGE,
                             mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES])
_names = st.sampled_from([p.name.encode() for p in PARAM_SPECS] + [b"NO_SUCH_PARAM", b""])
_param_types = st.sampled_from([mavlink.MAV_PARAM_TYPE_REAL32, mavlink.MAV_PARAM_TYPE_INT32,
                                mavlink.MAV_PARAM_TYPE_UINT8, 0, 200])
_masks = st.one_of(st.sampled_from([1479, 3527, 2503, 0, 0xFFFF]), st.integers(0, 0xFFFF))
_frames = st.one_of(st.sampled_from([mavlink.MAV_FRAME_BODY_NED, mavlink.MAV_FRAME_LOCAL_NED,
                                     mavlink.MAV_FRAME_BODY_FRD, mavlink.MAV_FRAME_LOCAL_FRD]), st.integers(0, 255))

MESSAGES = st.one_of(
    message_strategy(mavlink.MAVLink_command_long_message, command=_commands, **_target),
    message_strategy(mavlink.MAVLink_command_int_message, command=_commands, **_target),
    message_strategy(mavlink.MAVLink_set_mode_message, target_system=st.sampled_from([0, 1])),
    message_strategy(mavlink.MAVLink_param_set_message, param_id=_names, param_type=_param_types, **_target),
    message_strategy(mavlink.MAVLink_param_request_read_message, param_id=_names, **_target),
    message_strategy(mavlink.MAVLink_param_request_list_message, **_target),
    message_strategy(mavlink.MAVLink_timesync_message),
    message_strategy(mavlink.MAVLink_set_position_target_local_ned_message, type_mask=_masks,
                     coordinate_frame=_frames, **_target),
    message_strategy(mavlink.MAVLink_set_attitude_target_message, type_mask=st.integers(0, 255), **_target),
    message_strategy(mavlink.MAVLink_odometry_message, frame_id=_frames, child_frame_id=_frames),
    message_strategy(mavlink.MAVLink_heartbeat_message),
)

pytestmark = pytest.mark.fuzz


@pytest.fixture(scope="module")
def hovering() -> Sim:
    sim = Sim()
    fly_to_hover(sim)
    return sim


def _fresh_copy(sim: Sim) -> Sim:
    """An independent copy of the hovering flight (the pymavlink encoder is shared: it holds no flight state)."""
    return copy.deepcopy(sim, {id(sim.ap.mav): sim.ap.mav})


def _finite_command(sim: Sim) -> bool:
    c = sim.ap.last_board_command
    return all(math.isfinite(v) for v in (c.roll_rad, c.pitch_rad, c.yaw_rate_rad_s, c.thrust))


def _check_params(sim: Sim) -> None:
    for spec in PARAM_SPECS:
        value = sim.ap.params[spec.name]
        assert math.isfinite(value) and spec.min <= value <= spec.max, (spec.name, value)


@FUZZ
@given(st.lists(MESSAGES, min_size=1, max_size=6))
def test_any_message_sequence_keeps_the_vehicle_flying_on_finite_commands(hovering, messages):
    sim = _fresh_copy(hovering)
    beats: list[float] = []
    for message in messages:
        received = over_the_wire(GCS, message)
        if received is None:
            continue
        out = sim.ap.handle_mavlink(sim.t, received)
        assert all(o.msg is not None for o in out)
        for _ in range(10):  # 20 ms of flight between messages
            sim.step(0.002)
            assert _finite_command(sim)
    sim.step(0.1)
    assert _finite_command(sim)
    t0 = sim.t
    for i in range(56):  # 1.12 s of 50 Hz ticks: the heartbeat is still there
        if any(o.msg.get_type() == "HEARTBEAT" for o in sim.ap.tick(t0 + 0.02 * i)):
            beats.append(t0 + 0.02 * i)
    assert sim.ap.counters["handler_errors"] == 0
    _check_params(sim)
    assert beats, "heartbeat silenced"


@FUZZ
@given(_names, hostile_floats, _param_types)
def test_param_set_keeps_every_value_in_bounds_and_always_answers(hovering, name, value, ptype):
    sim = _fresh_copy(hovering)
    before = dict(sim.ap.params.values)
    out = sim.ap.handle_mavlink(sim.t, over_the_wire(GCS, GCS.param_set_encode(1, 1, name, value, ptype)))
    values = [o.msg for o in out if o.msg.get_type() == "PARAM_VALUE"]
    known = name.decode() in before
    assert len(values) == (1 if known else 0)
    _check_params(sim)
    changed = {k for k in before if before[k] != sim.ap.params[k]}
    assert changed <= {name.decode()}
    if known and ptype != mavlink.MAV_PARAM_TYPE_REAL32:
        assert not changed  # a mismatched type never changes anything


@FUZZ
@given(_commands, st.lists(hostile_floats, min_size=7, max_size=7))
def test_every_command_is_acked_once_and_nan_never_disarms(hovering, command, params):
    sim = _fresh_copy(hovering)
    out = sim.ap.handle_mavlink(sim.t, over_the_wire(GCS, GCS.command_long_encode(1, 1, command, 0, *params)))
    acks = [o.msg for o in out if o.msg.get_type() == "COMMAND_ACK"]
    assert len(acks) == 1 and acks[0].command == command
    if command == mavlink.MAV_CMD_COMPONENT_ARM_DISARM and not sim.ap.armed_cmd:
        assert params[0] == 0.0 and params[1] == 21196.0  # in the air only the exact forced disarm
    sim.step(0.1)
    assert _finite_command(sim)

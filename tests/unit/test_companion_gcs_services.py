"""The companion's ground-station services on their own (unit tier): the endpoint's gate
(companion.security), the commands (companion.gcs_commands), the parameter service (companion.params), the
command clock (companion.command_clock), the messages by type (companion.gcs_input), the arbiter's command as
the loop takes it (companion.motion) and the sending edge (companion.outbound). Messages go through
pymavlink's codec as on the wire; clocks are injected."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import pytest

from companion.arbiter import Arbiter, ArbiterParams, Pose
from companion.command_clock import GcsCommandClock
from companion.config import PanScanConfig
from companion.gcs_commands import GcsCommands
from companion.gcs_input import GcsInput
from companion.guard import ErrorCounter
from companion.modes import AutopilotRequest, Mode, ModeMachine, ModeParams, SpotRefusal, StatusText, VehicleStatus
from companion.motion import Motion
from companion.operator_input import OperatorInput
from companion.outbound import AutopilotAck, GcsReply, Outbox, Output
from companion.params import PARAM_NAMES, CompanionParams, ParamService
from companion.reference_params import ReferenceParams
from companion.security import GcsSecurity
from companion.stats import Stats
from quadlink.errors import QuadlinkError
from quadlink.mavlink import mavlink
from quadlink.mavlink.security import SecurityConfig, write_key
from quadlink.mavlink.statustext import StatusTextAssembler
from quadlink.px4_modes import AUTO_LOITER, OFFBOARD, POSCTL, Px4MainMode

pytestmark = pytest.mark.unit

SYSID, COMPID, AP_COMPID = 1, 191, 1
ARM = mavlink.MAV_CMD_COMPONENT_ARM_DISARM
TAKEOFF = mavlink.MAV_CMD_NAV_TAKEOFF
CUSTOM = float(mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED)


class Clock:
    """Settable monotonic time (s)."""

    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def wire(msg: Any, src_system: int = 255, src_component: int = 190) -> Any:
    """``msg`` as the companion gets it: packed by the sender's codec, parsed by a receiver's."""
    rx = mavlink.MAVLink(None)
    (out,) = rx.parse_buffer(bytes(msg.pack(mavlink.MAVLink(None, src_system, src_component))))
    return out


def command(cmd: int, *params: float, src_system: int = 255, target_component: int = COMPID) -> Any:
    p = (list(params) + [0.0] * 7)[:7]
    return wire(mavlink.MAVLink_command_long_message(SYSID, target_component, cmd, 0, *p), src_system)


def acks(out: list[Output]) -> list[tuple[int, int, int | None]]:
    """(command, result, packed-as component) of every COMMAND_ACK among ``out``."""
    return [(o.msg.command, o.msg.result, o.src_component) for o in out
            if isinstance(o, GcsReply) and o.msg.get_type() == "COMMAND_ACK"]


def texts(out: list[Output]) -> list[str]:
    return [o.text for o in out if isinstance(o, StatusText)]


# ---- companion.security ---------------------------------------------------------------------------------
def test_a_command_from_an_unlisted_sysid_is_denied_as_its_target_and_told_once_per_period() -> None:
    clock = Clock()
    gate = GcsSecurity(SecurityConfig(), SYSID, COMPID, clock)
    disarm = command(ARM, 0.0, 21196.0, src_system=77, target_component=AP_COMPID)
    assert not gate.permits(disarm)
    first = gate.refuse_sender(disarm)
    assert acks(first) == [(ARM, mavlink.MAV_RESULT_DENIED, AP_COMPID)]   # answered as the autopilot it targeted
    assert first[0].msg.target_system == 77 and first[0].msg.target_component == 190
    assert texts(first) == ["companion: COMMAND_LONG from sysid 77 refused (not allowed)"]
    clock.t += 1.0
    assert texts(gate.refuse_sender(disarm)) == []   # within 2 s: the ack only
    clock.t += 1.5
    assert texts(gate.refuse_sender(disarm)) != []
    assert acks(gate.refuse_sender(command(ARM, 1.0, src_system=77))) == [(ARM, mavlink.MAV_RESULT_DENIED, None)]


def test_listed_senders_and_read_only_messages_pass_and_the_own_sysid_follows_the_autopilot() -> None:
    gate = GcsSecurity(SecurityConfig(), SYSID, COMPID, Clock())
    assert gate.permits(command(ARM, 1.0, src_system=255)) and gate.permits(command(ARM, 1.0, src_system=SYSID))
    assert gate.permits(wire(mavlink.MAVLink_param_request_list_message(SYSID, COMPID), 77))
    assert not gate.permits(command(ARM, 1.0, src_system=42))
    gate.on_system_id(42)   # the autopilot turned out to be system 42
    assert gate.permits(command(ARM, 1.0, src_system=42)) and not gate.permits(command(ARM, 1.0, src_system=SYSID))


def test_a_non_finite_command_for_the_autopilot_is_denied_as_the_autopilot() -> None:
    gate = GcsSecurity(SecurityConfig(), SYSID, COMPID, Clock())
    msg = command(mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH, math.inf, target_component=0)
    out = gate.refuse_forward(msg, ap_compid=7)
    assert acks(out) == [(mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH, mavlink.MAV_RESULT_DENIED, 7)]
    assert texts(out) == ["companion: COMMAND_LONG not forwarded: non-finite value"]
    assert texts(gate.refuse_forward(msg, ap_compid=7)) == []


def test_signing_signs_what_is_sent_and_refuses_unsigned_packets(tmp_path: Path) -> None:
    key = write_key(tmp_path / "k.key")
    gate = GcsSecurity(SecurityConfig(str(tmp_path / "k.key"), require_signing=True), SYSID, COMPID, Clock())
    tx, rx = mavlink.MAVLink(None, SYSID, COMPID), mavlink.MAVLink(None)
    rx.robust_parsing = True
    gate.enable_signing(tx, rx, lambda: 1_790_000_000.0)
    assert gate.signing
    hb = mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3)
    peer = mavlink.MAVLink(None, 255, 190)
    peer.signing.secret_key = key
    (got,) = peer.parse_buffer(bytes(hb.pack(tx)))
    assert got.get_type() == "HEARTBEAT" and peer.signing.goodsig_count == 1
    assert [m.get_type() for m in rx.parse_buffer(bytes(hb.pack(mavlink.MAVLink(None, 255, 190))))] == ["BAD_DATA"]


class _Wire:
    """An in-memory link: what was written."""

    def __init__(self) -> None:
        self.sent: list[bytes] = []

    def write(self, buf: bytes) -> None:
        self.sent.append(bytes(buf))


def test_with_signing_the_autopilots_forwarded_traffic_and_its_acks_reach_the_station_signed(tmp_path: Path) -> None:
    """Issue 16: a station that requires signing dropped the autopilot's heartbeats and the mode acks the
    companion answers for it, which went out unsigned. They keep the autopilot's ids and sequence number."""
    key = write_key(tmp_path / "k.key")
    gate = GcsSecurity(SecurityConfig(str(tmp_path / "k.key"), require_signing=True), SYSID, COMPID, Clock())
    gcs, autopilot = _Wire(), _Wire()
    out = Outbox(autopilot, gcs, SYSID, COMPID, 1, ErrorCounter(lambda: 0.0), Stats(), None, lambda: 0.0)
    gate.enable_signing(out.gcs_codec, mavlink.MAVLink(None), lambda: 1_790_000_000.0)
    bridge = mavlink.MAVLink(None, SYSID, 1)            # the autopilot: unsigned on its own link
    bridge.seq = 41
    hb = mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, 0, 0, 4, 3)
    (arrived,) = mavlink.MAVLink(None).parse_buffer(bytes(hb.pack(bridge)))
    received = bytes(arrived.get_msgbuf())
    assert out.forward(gcs, arrived)
    assert out.to_gcs_as(mavlink.MAVLink_command_ack_message(mavlink.MAV_CMD_DO_SET_MODE, 0, 0, 0, 255, 190),
                         SYSID, 1)
    station = mavlink.MAVLink(None, 255, 190)
    station.signing.secret_key = key
    station.signing.allow_unsigned_callback = lambda _mav, _msg_id: False   # requires signing
    got = [m for buf in gcs.sent for m in station.parse_buffer(buf) or []]
    assert [m.get_type() for m in got] == ["HEARTBEAT", "COMMAND_ACK"]
    assert station.signing.goodsig_count == 2
    assert [(m.get_srcSystem(), m.get_srcComponent()) for m in got] == [(SYSID, 1), (SYSID, 1)]
    assert got[0].get_seq() == 41
    # to the autopilot, a forwarded message keeps its own bytes (the autopilot link is not signed)
    assert out.forward(autopilot, arrived) and autopilot.sent == [received]
    # and without signing, the forwarded bytes are the received ones
    plain = Outbox(autopilot, _Wire(), SYSID, COMPID, 1, ErrorCounter(lambda: 0.0), Stats(), None, lambda: 0.0)
    assert plain.forward(plain.gcs, arrived) and plain.gcs.sent == [received]   # type: ignore[attr-defined]


def test_signing_without_a_codec_to_check_it_is_an_error_and_no_key_is_no_signing(tmp_path: Path) -> None:
    write_key(tmp_path / "k.key")
    with pytest.raises(QuadlinkError, match="no MAVLink codec"):
        GcsSecurity(SecurityConfig(str(tmp_path / "k.key")), SYSID, COMPID, Clock()).enable_signing(
            mavlink.MAVLink(None), None, lambda: 0.0)
    off = GcsSecurity(SecurityConfig(), SYSID, COMPID, Clock())
    tx = mavlink.MAVLink(None)
    off.enable_signing(tx, None, lambda: 0.0)
    assert not off.signing and tx.signing.secret_key is None


# ---- companion.params.ParamService -----------------------------------------------------------------------
def params() -> ParamService:
    return ParamService(CompanionParams(PanScanConfig(), ReferenceParams()))


def param_set(name: str, value: float, param_type: int = mavlink.MAV_PARAM_TYPE_REAL32) -> Any:
    return wire(mavlink.MAVLink_param_set_message(SYSID, COMPID, name.encode(), value, param_type))


def test_a_parameter_change_is_announced_then_echoed() -> None:
    svc = params()
    out = svc.on_message(param_set("CMP_K_V", 0.9))
    assert texts(out) == ["companion: CMP_K_V 0.6 -> 0.9"] and isinstance(out[0], StatusText)
    (echo,) = [o.msg for o in out if isinstance(o, GcsReply)]
    assert echo.get_type() == "PARAM_VALUE" and echo.param_value == pytest.approx(0.9)
    assert svc.store.values()["CMP_K_V"] == pytest.approx(0.9)


def test_a_refused_parameter_change_is_echoed_unchanged_without_a_change_notice() -> None:
    svc = params()
    out = svc.on_message(param_set("CMP_K_V", math.nan))
    (value,) = (o.msg for o in out if isinstance(o, GcsReply))
    (why,) = texts(out)     # a warning saying why (not a change notice)
    assert value.param_value == pytest.approx(0.6) and why.startswith("companion: CMP_K_V refused: ")
    assert len(svc.on_message(wire(mavlink.MAVLink_param_request_list_message(SYSID, COMPID)))) == len(PARAM_NAMES)


def test_set_by_index_answers_the_value_now_and_nothing_out_of_range() -> None:
    svc = params()
    i = PARAM_NAMES.index("PANSCAN_EN")
    changed, out = svc.set_by_index(i, 0.0)
    assert changed and texts(out) == ["companion: PANSCAN_EN 1 -> 0"] and not svc.store.values()["PANSCAN_EN"]
    changed, out = svc.set_by_index(i, 0.5)   # a flag: only 0 or 1
    assert not changed and [o.msg.param_value for o in out if isinstance(o, GcsReply)] == [0.0]
    assert svc.set_by_index(len(PARAM_NAMES), 1.0) == (False, [])
    assert svc.set("CMP_SAFE_DIST", 99.0) == (False, [])


# ---- companion.gcs_commands ------------------------------------------------------------------------------
class Rig:
    def __init__(self) -> None:
        self.clock = Clock()
        self.modes = ModeMachine(ModeParams())
        self.arbiter = Arbiter(ArbiterParams())
        self.status = VehicleStatus()
        self.camera = True
        self.land_refusal: SpotRefusal | None = None
        self.cmds = GcsCommands(self.modes, self.arbiter, params(), self.clock, lambda: self.status,
                                lambda: self.camera, lambda: self.land_refusal)


def test_arm_and_takeoff_go_to_the_mode_machine_and_are_acked_after() -> None:
    rig = Rig()
    out = rig.cmds.on_command_long(command(ARM, 1.0))
    assert out[0] == AutopilotRequest("arm") and acks(out) == [(ARM, mavlink.MAV_RESULT_ACCEPTED, None)]
    assert out[-1].msg.target_system == 255   # acked to its sender
    out = rig.cmds.on_command_long(command(TAKEOFF, 0, 0, 0, math.nan, math.nan, math.nan, 1.0))
    assert AutopilotRequest("takeoff", 1.0) in out and rig.modes.mode == Mode.TAKEOFF
    assert acks(out) == [(TAKEOFF, mavlink.MAV_RESULT_ACCEPTED, None)]
    assert acks(rig.cmds.on_command_long(command(ARM, 1.0))) == [(ARM, mavlink.MAV_RESULT_TEMPORARILY_REJECTED, None)]


def test_takeoff_without_camera_frames_is_rejected_and_bad_params_denied() -> None:
    rig = Rig()
    rig.camera = False
    out = rig.cmds.on_command_long(command(TAKEOFF))
    assert texts(out) == ["companion: takeoff refused: no camera frames (perception not running)"]
    assert acks(out) == [(TAKEOFF, mavlink.MAV_RESULT_TEMPORARILY_REJECTED, None)] and rig.modes.mode == Mode.IDLE
    out = rig.cmds.on_command_long(command(ARM, math.nan))   # arm's param1 is required
    assert acks(out) == [(ARM, mavlink.MAV_RESULT_DENIED, None)] and len(texts(out)) == 1
    assert not any(isinstance(o, AutopilotRequest) for o in out)
    assert acks(rig.cmds.on_command_long(command(mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH))) == \
        [(mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH, mavlink.MAV_RESULT_UNSUPPORTED, None)]


def test_a_land_over_an_object_is_denied_whoever_it_is_sent_to_and_the_failsafe_still_lands() -> None:
    """Issue 14 (campaign flights 21 and 39 landed on a desk's and a box's top): a commanded LAND in flight over
    an object the map holds below is refused with its reason, to the companion or to the autopilot (MAVSDK's
    ``action.land()``); over the floor it lands as before; the failsafe landings do not ask."""
    rig = InputRig()
    rig.modes.mode = Mode.TELEOP
    rig.status = VehicleStatus(armed=True, in_air=True)
    rig.land_refusal = SpotRefusal("land refused: object below, 0.75 m tall")
    land = mavlink.MAV_CMD_NAV_LAND
    out, forward = rig.on(command(land, 0, 0, 0, math.nan, math.nan, math.nan, math.nan))
    assert not forward and acks(out) == [(land, mavlink.MAV_RESULT_DENIED, None)]
    assert texts(out) == ["companion: land refused: object below, 0.75 m tall"] and rig.modes.mode == Mode.TELEOP
    out, forward = rig.on(command(land, 0, 0, 0, math.nan, math.nan, math.nan, math.nan, target_component=AP_COMPID))
    (ack,) = [o.msg for o in out if isinstance(o, AutopilotAck)]
    assert not forward and ack.command == land and ack.result == mavlink.MAV_RESULT_DENIED and texts(out)
    rig.land_refusal = None     # moved clear: to the autopilot it goes on, to the companion it is accepted
    assert rig.on(command(land, target_component=AP_COMPID)) == ([], True)
    out, _ = rig.on(command(land, 0, 0, 0, math.nan, math.nan, math.nan, math.nan))
    assert AutopilotRequest("land") in out and rig.modes.mode == Mode.LAND
    # not flying it (IDLE): the autopilot's own business, whatever is below
    rig.modes.mode, rig.land_refusal = Mode.IDLE, SpotRefusal("land refused: object below, 0.75 m tall")
    assert rig.on(command(land, target_component=AP_COMPID)) == ([], True)
    # the failsafe landing (no fresh command for gcs_land_timeout_s) is not asked
    rig.modes.mode = Mode.HOLD
    actions = rig.modes.update(rig.clock() + 100.0, rig.status, True)
    assert AutopilotRequest("land") in actions and rig.modes.mode == Mode.LAND


def test_a_land_over_unseen_ground_is_accepted_and_moves_to_seen_ground_first() -> None:
    """Issue 30: a ground station's LAND is refused only for an object under the footprint. Over ground the camera
    has not seen (companion.seen_ground) it is accepted, to the companion or to the autopilot (MAVSDK's
    ``action.land()``): the vehicle holds and moves to seen ground (``clearing_spot``, as a failsafe landing
    moves clear), then the autopilot is asked to land; a ground station's mode change calls it off."""
    unseen = SpotRefusal("ground below not seen (63 %)", unseen=True)
    land = mavlink.MAV_CMD_NAV_LAND
    for target in (COMPID, AP_COMPID):
        rig = InputRig()
        rig.modes.mode, rig.modes.odometry_ok = Mode.TELEOP, True
        rig.status = VehicleStatus(armed=True, in_air=True)
        rig.land_refusal = unseen
        out, forward = rig.on(command(land, 0, 0, 0, math.nan, math.nan, math.nan, math.nan,
                                      target_component=target))
        (ack,) = [o.msg for o in out if isinstance(o, AutopilotAck | GcsReply)]
        assert not forward and ack.command == land and ack.result == mavlink.MAV_RESULT_ACCEPTED
        assert AutopilotRequest("land") not in out and rig.modes.mode == Mode.HOLD and rig.modes.clearing_spot
        assert "companion: ground-station land: ground below not seen (63 %), moving clear" in texts(out)
        # a second LAND while it moves: accepted, nothing new
        out, _ = rig.on(command(land, target_component=target))
        assert AutopilotRequest("land") not in out and rig.modes.clearing_spot
        # the operator's sticks do not end it (HOLD), the spot seen for land_clear_hold_s lands it
        now = rig.clock()
        rig.modes.on_manual_control(now + 0.5)
        rig.modes.on_motion_command(now + 0.5)
        assert _requests_of(rig.modes.update(now + 0.5, rig.status, True, "ground below not seen (40 %)")) == []
        assert rig.modes.mode == Mode.HOLD and rig.modes.clearing_spot and rig.modes.commanded_clearing
        assert _requests_of(rig.modes.update(now + 1.0, rig.status, True, None)) == []
        actions = rig.modes.update(now + 2.1, rig.status, True, None)
        assert _requests_of(actions) == ["land"] and rig.modes.mode == Mode.LAND
    # called off by a mode change (POSCTL: the operator's again)
    rig = InputRig()
    rig.modes.mode, rig.modes.odometry_ok = Mode.TELEOP, True
    rig.status = VehicleStatus(armed=True, in_air=True)
    rig.land_refusal = unseen
    rig.on(command(land, target_component=AP_COMPID))
    assert rig.modes.clearing_spot
    set_mode = command(mavlink.MAV_CMD_DO_SET_MODE, target_component=AP_COMPID)
    handled, out = rig.cmds.on_set_mode(set_mode, CUSTOM, Px4MainMode.POSCTL, 0.0)
    assert handled and rig.modes.mode == Mode.TELEOP and not rig.modes.clearing_spot
    assert any("land called off" in t for t in texts(out))
    # without a pose to move on, it lands where it is (as a failsafe landing does)
    rig = InputRig()
    rig.modes.mode, rig.modes.odometry_ok = Mode.TELEOP, False
    rig.status = VehicleStatus(armed=True, in_air=True)
    rig.land_refusal = unseen
    out, _ = rig.on(command(land, 0, 0, 0, math.nan, math.nan, math.nan, math.nan))
    assert AutopilotRequest("land") in out and rig.modes.mode == Mode.LAND
    assert acks(out) == [(land, mavlink.MAV_RESULT_ACCEPTED, None)]


def test_a_landing_mode_is_checked_as_a_land_is() -> None:
    """QGroundControl's Land asks a PX4 vehicle for AUTO.LAND (DO_SET_MODE), MAVProxy's ``mode land`` for
    ArduCopter's LAND (9, SET_MODE): while the companion flies, neither may bypass the landing-spot check. Over an
    object: DENIED, answered as the autopilot (SET_MODE has no ack); over unseen ground: accepted, moving to seen
    ground; over seen floor, or not flying it: the autopilot's (forwarded)."""
    set_mode = command(mavlink.MAV_CMD_DO_SET_MODE, target_component=AP_COMPID)
    for main, sub in ((Px4MainMode.AUTO, 6.0), (9.0, 0.0)):
        rig = InputRig()
        rig.modes.mode, rig.modes.odometry_ok = Mode.TELEOP, True
        rig.status = VehicleStatus(armed=True, in_air=True)
        rig.land_refusal = SpotRefusal("land refused: object below, 0.75 m tall")
        handled, out = rig.cmds.on_set_mode(set_mode, CUSTOM, main, sub)
        (ack,) = [o.msg for o in out if isinstance(o, AutopilotAck)]
        assert handled and ack.command == mavlink.MAV_CMD_DO_SET_MODE and ack.result == mavlink.MAV_RESULT_DENIED
        assert texts(out) == ["companion: land refused: object below, 0.75 m tall"] and rig.modes.mode == Mode.TELEOP
        handled, out = rig.cmds.on_set_mode(set_mode, CUSTOM, main, sub, ack=False)   # SET_MODE: no ack
        assert handled and not [o for o in out if isinstance(o, AutopilotAck)] and rig.modes.mode == Mode.TELEOP
        rig.land_refusal = SpotRefusal("ground below not seen (40 %)", unseen=True)
        handled, out = rig.cmds.on_set_mode(set_mode, CUSTOM, main, sub)
        (ack,) = [o.msg for o in out if isinstance(o, AutopilotAck)]
        assert handled and rig.modes.clearing_spot and ack.result == mavlink.MAV_RESULT_ACCEPTED
        rig = InputRig()
        rig.modes.mode = Mode.TELEOP
        assert rig.cmds.on_set_mode(set_mode, CUSTOM, main, sub) == (False, [])      # nothing below: the autopilot's
        rig.modes.mode, rig.land_refusal = Mode.IDLE, SpotRefusal("land refused: object below, 0.75 m tall")
        assert rig.cmds.on_set_mode(set_mode, CUSTOM, main, sub) == (False, [])      # not flying it


def _requests_of(actions: list[Any]) -> list[str]:
    return [a.name for a in actions if isinstance(a, AutopilotRequest)]


def test_command_int_is_handled_and_acked_like_command_long() -> None:
    """QGroundControl sends some commands as COMMAND_INT: the companion's are answered, the others UNSUPPORTED —
    never silence (MAVLink: every command gets a COMMAND_ACK)."""
    rig = Rig()
    arm = wire(mavlink.MAVLink_command_int_message(SYSID, COMPID, mavlink.MAV_FRAME_GLOBAL, ARM, 0, 0,
                                                   1.0, 0, 0, 0, 0, 0, 0), 255)
    out = rig.cmds.on_command_int(arm)
    assert out[0] == AutopilotRequest("arm") and acks(out) == [(ARM, mavlink.MAV_RESULT_ACCEPTED, None)]
    rtl = wire(mavlink.MAVLink_command_int_message(SYSID, COMPID, mavlink.MAV_FRAME_GLOBAL,
                                                   mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH, 0, 0, 0, 0, 0, 0, 0, 0, 0),
               255)
    assert acks(rig.cmds.on_command_int(rtl)) == [(mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH,
                                                    mavlink.MAV_RESULT_UNSUPPORTED, None)]


def test_do_set_parameter_changes_the_value_and_acks() -> None:
    rig = Rig()
    i = PARAM_NAMES.index("CMP_K_PSI")
    out = rig.cmds.on_command_long(command(mavlink.MAV_CMD_DO_SET_PARAMETER, i, 1.2))
    assert texts(out) == ["companion: CMP_K_PSI 0.8 -> 1.2"]
    assert acks(out) == [(mavlink.MAV_CMD_DO_SET_PARAMETER, mavlink.MAV_RESULT_ACCEPTED, None)]
    out = rig.cmds.on_command_long(command(mavlink.MAV_CMD_DO_SET_PARAMETER, i, 30.0))
    assert acks(out) == [(mavlink.MAV_CMD_DO_SET_PARAMETER, mavlink.MAV_RESULT_DENIED, None)]
    assert rig.cmds.params.store.values()["CMP_K_PSI"] == pytest.approx(1.2)


def test_mode_changes_are_answered_as_the_autopilot_only_while_the_companion_flies() -> None:
    rig = Rig()
    set_mode = command(mavlink.MAV_CMD_DO_SET_MODE, CUSTOM, Px4MainMode.POSCTL, target_component=AP_COMPID)
    handled, out = rig.cmds.on_set_mode(set_mode, CUSTOM, Px4MainMode.POSCTL, 0.0)
    assert not handled and out == []   # IDLE: the autopilot answers its own modes
    rig.modes.mode = Mode.TELEOP
    handled, out = rig.cmds.on_set_mode(set_mode, CUSTOM, Px4MainMode.OFFBOARD, 0.0)
    (ack,) = [o.msg for o in out if isinstance(o, AutopilotAck)]
    assert handled and ack.result == mavlink.MAV_RESULT_DENIED   # OFFBOARD needs a fresh setpoint stream first
    handled, out = rig.cmds.on_set_mode(set_mode, CUSTOM, Px4MainMode.POSCTL, 0.0, ack=False)
    assert handled and not any(isinstance(o, AutopilotAck) for o in out)
    assert rig.cmds.on_set_mode(set_mode, CUSTOM, Px4MainMode.AUTO, 6.0) == (False, [])   # RTL: the autopilot's
    assert rig.cmds.on_set_mode(set_mode, 0.0, Px4MainMode.POSCTL, 0.0) == (False, [])
    assert rig.cmds.on_set_mode(set_mode, CUSTOM, math.nan, 0.0) == (False, [])
    for base in (math.nan, math.inf, -math.inf):   # param1 NaN (found by the companion's fuzz test) or inf
        assert rig.cmds.on_set_mode(set_mode, base, Px4MainMode.POSCTL, 0.0) == (False, [])


def test_setpoints_engage_offboard_and_the_reported_mode_follows() -> None:
    rig = Rig()
    hb = wire(mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, 0, 0, 4, 3),
              SYSID, AP_COMPID)
    assert rig.cmds.mode_heartbeat(hb).custom_mode == AUTO_LOITER.custom_mode
    sp = wire(mavlink.MAVLink_set_position_target_local_ned_message(
        0, SYSID, AP_COMPID, mavlink.MAV_FRAME_BODY_OFFSET_NED, 1479, 0, 0, 0, 0.5, 0, 0, 0, 0, 0, 0, 0))
    assert rig.cmds.on_setpoint(sp, Pose(None, None, 0.0)) == []
    assert rig.arbiter.offboard_engaged
    beat = rig.cmds.mode_heartbeat(hb)
    assert beat.custom_mode == OFFBOARD.custom_mode and beat.base_mode & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    rig.arbiter.on_manual_control(rig.clock(), 0, 0, 500)
    rig.arbiter.offboard_engaged = False
    assert rig.cmds.mode_heartbeat(hb).custom_mode == POSCTL.custom_mode


def test_a_motion_refusal_is_told_once_per_distinct_reason() -> None:
    rig = Rig()
    assert texts(rig.cmds.refuse_motion("SET_ATTITUDE_TARGET not supported")) == \
        ["companion: SET_ATTITUDE_TARGET not supported"]
    assert rig.cmds.refuse_motion("SET_ATTITUDE_TARGET not supported") == []
    assert rig.cmds.refuse_motion("another reason") != []


# ---- companion.command_clock -----------------------------------------------------------------------------
def test_the_command_clock_answers_requests_and_keeps_a_bounded_set_of_senders() -> None:
    clock = GcsCommandClock(max_command_age_s=0.5, timesync_max_rtt_s=2.0, max_senders=2)
    (answer,) = [clock.on_timesync(wire(mavlink.MAVLink_timesync_message(0, 123)), 1.5)]
    assert answer.tc1 == 1_500_000_000 and answer.ts1 == 123 and clock.sync == {}
    for sysid in (250, 251, 252):
        reply = wire(mavlink.MAVLink_timesync_message(2_000_000_000, 1_000_000_000), sysid)
        assert clock.on_timesync(reply, 1.01) is None
    assert sorted(clock.sync) == [(250, 190), (251, 190)]
    mc = wire(mavlink.MAVLink_manual_control_message(SYSID, 0, 0, 500, 0, 0))
    assert clock.on_command(mc, 2.0).accepted   # never stamped: taken at arrival, its age unknown
    report = {m.name: m.value for m in clock.report(2000)}
    assert report == {"CMD_OK": 1, "CMD_DROP": 0, "CMD_STALE": 0, "CMD_UNPAIR": 0}   # no age percentiles yet
    assert clock.summary().startswith("commands 1 ok / 0 dropped")


# ---- companion.gcs_input, companion.motion -------------------------------------------------------------------
class InputRig(Rig):
    def __init__(self) -> None:
        super().__init__()
        self.stats = Stats()
        self.clock_ = GcsCommandClock(0.5, 0.2)
        self.input = GcsInput(GcsSecurity(SecurityConfig(), SYSID, COMPID, self.clock), self.clock_, self.cmds,
                              self.cmds.params, self.arbiter, self.modes, self.stats, COMPID, self.clock)

    def on(self, msg: Any) -> tuple[list[Output], bool]:
        handled = self.input.on_message(msg, SYSID, AP_COMPID, lambda: Pose(None, None, 0.0))
        return handled.outputs, handled.forward


def manual(x: int, src_system: int = 255) -> Any:
    return wire(mavlink.MAVLink_manual_control_message(SYSID, x, 0, 500, 0, 0), src_system)


def test_ground_station_messages_go_to_their_service_and_on_to_the_autopilot_as_routed() -> None:
    rig = InputRig()
    out, forward = rig.on(manual(500, src_system=77))   # not on the allowlist: refused, told, not counted
    assert not forward and texts(out) and rig.stats.refused_senders == 1 and rig.stats.manual_controls == 0
    assert rig.on(manual(500)) == ([], False) and rig.stats.manual_controls == 1
    rig.modes.update(rig.clock(), VehicleStatus(), True)
    assert rig.arbiter.operator_alive(rig.clock()) and rig.modes.gcs_ok   # a fresh command: the link is alive
    set_mode = wire(mavlink.MAVLink_set_mode_message(SYSID, int(CUSTOM), POSCTL.custom_mode))
    assert rig.on(set_mode) == ([], True)   # IDLE: the autopilot's own mode, it answers
    out, forward = rig.on(wire(mavlink.MAVLink_param_request_list_message(SYSID, 0)))   # broadcast: both answer
    assert forward and [o.msg.param_id for o in out if isinstance(o, GcsReply)] == list(PARAM_NAMES)
    out, forward = rig.on(wire(mavlink.MAVLink_timesync_message(0, 5)))
    assert not forward and [o.msg.ts1 for o in out if isinstance(o, GcsReply)] == [5]
    rig.modes.mode = Mode.TELEOP
    out, forward = rig.on(command(mavlink.MAV_CMD_DO_SET_MODE, CUSTOM, Px4MainMode.POSCTL, target_component=AP_COMPID))
    assert not forward and [o.msg.command for o in out if isinstance(o, AutopilotAck)] == [mavlink.MAV_CMD_DO_SET_MODE]


def test_the_operator_input_reaches_the_reference_only_while_its_command_is_fresh() -> None:
    rig = InputRig()
    told: list[StatusText] = []
    motion = Motion(rig.arbiter, rig.clock_.age, rig.clock, told.append)
    rig.on(manual(1000))
    cmd = motion.command(Pose(None, None, 0.0))
    assert motion.operator_of(cmd).qx == pytest.approx(1.0) and motion.last is cmd
    assert motion.reported_mode(Mode.TELEOP) == Mode.TELEOP
    rig.clock.t += 0.6   # older than the age (0.5 s): zeroed
    assert motion.operator_of(cmd) == OperatorInput()
    held = motion.command(Pose(None, None, 0.0))   # and the arbiter holds: reported as HOLD
    assert held.hold and motion.reported_mode(Mode.TELEOP) == Mode.HOLD and motion.reported_mode(Mode.LAND) == Mode.LAND
    assert all(t.text.startswith("companion: ") for t in told)


def test_a_long_status_text_is_sent_in_chunks_a_ground_station_reassembles() -> None:
    gcs = MemLink()
    box = Outbox(MemLink(), gcs, SYSID, COMPID, AP_COMPID, ErrorCounter(Clock()), Stats(), None, lambda: 0.0)
    text = "companion: " + "x" * 60
    box.status_text(StatusText(mavlink.MAV_SEVERITY_WARNING, text))
    box.status_text(StatusText(mavlink.MAV_SEVERITY_INFO, "companion: short"))
    msgs = list(map(parsed, gcs.sent))
    assert [m.get_type() for m in msgs] == ["STATUSTEXT"] * 3
    assert [(m.chunk_seq, m.severity) for m in msgs[:2]] == [(0, mavlink.MAV_SEVERITY_WARNING),
                                                             (1, mavlink.MAV_SEVERITY_WARNING)]
    assert msgs[0].id == msgs[1].id != 0 and msgs[2].id == 0
    asm = StatusTextAssembler()
    assert [asm.add(m) for m in msgs] == [None, text, "companion: short"]


# ---- companion.outbound ------------------------------------------------------------------------------------
class MemLink:
    def __init__(self) -> None:
        self.sent: list[bytes] = []

    def recv_msg(self) -> Any:
        return None

    def write(self, buf: bytes) -> None:
        self.sent.append(bytes(buf))

    def close(self) -> None:
        pass


def parsed(buf: bytes) -> Any:
    (msg,) = mavlink.MAVLink(None).parse_buffer(buf)
    return msg


def test_the_outbox_packs_as_the_right_component_and_never_sends_a_non_finite_value() -> None:
    ap, gcs, stats, errors = MemLink(), MemLink(), Stats(), ErrorCounter(Clock())
    out = Outbox(ap, gcs, SYSID, COMPID, AP_COMPID, errors, stats, None, lambda: 0.0)
    ack = mavlink.MAVLink_command_ack_message(ARM, mavlink.MAV_RESULT_DENIED, 0, 0, 77, 190)
    out.to_gcs(ack, src_component=AP_COMPID)
    out.to_gcs(ack)
    assert [(m.get_srcSystem(), m.get_srcComponent()) for m in map(parsed, gcs.sent)] == [(1, AP_COMPID), (1, COMPID)]
    out.set_system_id(42)
    assert out.to_gcs_as(ack, 42, AP_COMPID) and parsed(gcs.sent[-1]).get_srcSystem() == 42
    out.to_autopilot(mavlink.MAVLink_command_long_message(SYSID, AP_COMPID, ARM, 0, math.nan, *[0.0] * 6))
    assert ap.sent == [] and stats.non_finite_dropped == 1
    out.to_gcs(mavlink.MAVLink_named_value_int_message(0, b"X", 2**40))   # does not pack: one message dropped
    assert errors.by_where == {"non-finite COMMAND_LONG": 1, "packing NAMED_VALUE_INT": 1} and len(gcs.sent) == 3
    out.to_autopilot(mavlink.MAVLink_timesync_message(0, 1))
    assert parsed(ap.sent[0]).get_srcSystem() == 42

"""``quadlink.client`` against a fake vehicle built from the producers, in-process (no socket, no thread).

The client runs on a real pymavlink ``mavfile`` whose bytes go to and come from :class:`FakeVehicle`: the vehicle's
messages are encoded by pymavlink's codec (the producer side), its parameters are served by the stack's own
:class:`quadlink.mavlink.param_service.ParamService`, and what the client sends is decoded back from its bytes and,
for setpoints and stamps, read by the readers that consume them on the vehicle (the type-mask rule, the companion's
command-age filter). Time is a fake clock that a wait advances when it would block.
"""

from __future__ import annotations

import collections
import math
from typing import Any

import pytest
from pymavlink import mavutil

from companion.command_age import CommandAgeFilter, CommandAgeParams, Verdict
from quadlink.client import (
    CommandRejected,
    GroundClient,
    Signing,
    land_command,
    position_velocity_accel_ned,
    set_px4_mode_command,
    velocity_body,
    velocity_ned,
)
from quadlink.errors import LinkTimeout
from quadlink.ids import COMPANION_COMPONENT_ID, GROUND_COMPONENT_ID, GROUND_SYSTEM_ID, VEHICLE_SYSTEM_ID
from quadlink.mavlink import mavlink
from quadlink.mavlink.param_service import ParamService, ParamSpec, ParamTable
from quadlink.mavlink.security import enable_signing
from quadlink.mavlink.setpoint_masks import mask_groups
from quadlink.px4_modes import OFFBOARD

pytestmark = pytest.mark.unit

KEY = bytes(range(32))
PARAMS = (ParamSpec("TEST_GAIN", 1.0, 0.0, 10.0, "1", "a real parameter"),
          ParamSpec("TEST_MODE", 0, 0, 5, "", "an integer parameter", mavlink.MAV_PARAM_TYPE_INT32))


class FakeClock:
    def __init__(self, now_s: float = 100.0) -> None:
        self.now_s = now_s

    def __call__(self) -> float:
        return self.now_s


class _Outbox:
    """The vehicle codec's file: each packet it sends is one datagram for the client."""

    def __init__(self) -> None:
        self.datagrams: collections.deque[bytes] = collections.deque()

    def write(self, buf: bytes) -> None:
        self.datagrams.append(bytes(buf))


class FakeVehicle:
    """System 1, component 191 (the companion): answers commands with the acks in ``acks`` (command -> results,
    in order; none: silent), parameters through :class:`ParamService`, and sends a HEARTBEAT every
    ``heartbeat_period_s`` of the clock (None: silent). ``received`` holds every message the client sent, decoded
    from its bytes by an independent parser (checking signatures when ``signing_key`` is given)."""

    def __init__(self, clock: FakeClock, acks: dict[int, tuple[int, ...]] | None = None,
                 heartbeat_period_s: float | None = 1.0, signing_key: bytes | None = None) -> None:
        self.clock = clock
        self.acks = acks or {}
        self.heartbeat_period_s = heartbeat_period_s
        self.next_heartbeat_s = clock()
        self.outbox = _Outbox()
        self.mav = mavlink.MAVLink(self.outbox, srcSystem=VEHICLE_SYSTEM_ID, srcComponent=COMPANION_COMPONENT_ID)
        self.params = ParamService(ParamTable(PARAMS), self.mav, VEHICLE_SYSTEM_ID, COMPANION_COMPONENT_ID)
        self.parser = mavlink.MAVLink(None)
        self.parser.robust_parsing = True   # a refused packet is BAD_DATA, as on the companion's links
        if signing_key is not None:
            enable_signing(self.parser, signing_key, require=True)
        self.received: list[Any] = []

    def on_bytes(self, buf: bytes) -> None:
        for msg in self.parser.parse_buffer(buf) or []:
            if msg.get_type() == "BAD_DATA":
                continue
            self.received.append(msg)
            self._answer(msg)

    def _answer(self, msg: Any) -> None:
        kind = msg.get_type()
        if kind == "COMMAND_LONG":
            for result in self.acks.get(msg.command, ()):
                self.mav.command_ack_send(msg.command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent())
        elif kind.startswith("PARAM_"):
            reply = self.params.handle(self.clock(), msg)
            for out in reply.to_sender + reply.to_all:
                self.mav.send(out)

    def tick(self) -> None:
        while self.heartbeat_period_s is not None and self.clock() >= self.next_heartbeat_s:
            self.next_heartbeat_s += self.heartbeat_period_s
            self.mav.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, 0, 0,
                                    mavlink.MAV_STATE_STANDBY)

    def sent(self, kind: str) -> list[Any]:
        return [m for m in self.received if m.get_type() == kind]


class LoopbackMavfile(mavutil.mavfile):  # type: ignore[misc]
    """A pymavlink ``mavfile`` whose peer is a :class:`FakeVehicle` in this process: writes go to the vehicle,
    reads come from its datagrams, and a blocking select advances the fake clock instead of sleeping."""

    def __init__(self, vehicle: FakeVehicle) -> None:
        super().__init__(None, "loopback", source_system=GROUND_SYSTEM_ID, source_component=GROUND_COMPONENT_ID)
        # the quadlink dialect's codec (TELEOP_FEEDBACK, COMMAND_STAMP), as open_mavlink's endpoints have
        self.mav = mavlink.MAVLink(self, srcSystem=GROUND_SYSTEM_ID, srcComponent=GROUND_COMPONENT_ID)
        self.vehicle = vehicle
        self.selected_s = 0.0

    def write(self, buf: bytes) -> None:
        self.vehicle.on_bytes(bytes(buf))

    def recv(self, n: int | None = None) -> bytes:
        self.vehicle.tick()
        return self.vehicle.outbox.datagrams.popleft() if self.vehicle.outbox.datagrams else b""

    def select(self, timeout: float) -> bool:
        self.selected_s += timeout
        self.vehicle.clock.now_s += timeout
        return False

    def close(self) -> None:
        pass


def make(acks: dict[int, tuple[int, ...]] | None = None, heartbeat_period_s: float | None = 1.0,
         signing_key: bytes | None = None) -> tuple[GroundClient, FakeVehicle, FakeClock]:
    clock = FakeClock()
    vehicle = FakeVehicle(clock, acks, heartbeat_period_s, signing_key)
    return GroundClient(LoopbackMavfile(vehicle), clock=clock), vehicle, clock


def test_arm_waits_for_its_ack_and_sends_what_mavsdk_sends() -> None:
    client, vehicle, _ = make({mavlink.MAV_CMD_COMPONENT_ARM_DISARM: (mavlink.MAV_RESULT_ACCEPTED,)})
    client.arm()
    (cmd,) = vehicle.sent("COMMAND_LONG")
    assert (cmd.target_system, cmd.target_component) == (VEHICLE_SYSTEM_ID, COMPANION_COMPONENT_ID)
    assert cmd.get_srcSystem() == GROUND_SYSTEM_ID and cmd.get_srcComponent() == GROUND_COMPONENT_ID
    assert cmd.command == mavlink.MAV_CMD_COMPONENT_ARM_DISARM and cmd.param1 == 1.0


def test_in_progress_is_waited_through() -> None:
    client, _, _ = make({mavlink.MAV_CMD_NAV_TAKEOFF: (mavlink.MAV_RESULT_IN_PROGRESS, mavlink.MAV_RESULT_ACCEPTED)})
    client.takeoff(1.0)


def test_a_refused_command_is_an_error_naming_it() -> None:
    client, _, _ = make({mavlink.MAV_CMD_NAV_TAKEOFF: (mavlink.MAV_RESULT_TEMPORARILY_REJECTED,)})
    with pytest.raises(CommandRejected, match="MAV_CMD_NAV_TAKEOFF refused by 1/191: TEMPORARILY_REJECTED"):
        client.takeoff(1.0)


def test_a_command_without_ack_times_out_on_the_clock_with_a_clear_error() -> None:
    client, vehicle, clock = make()
    t0 = clock()
    with pytest.raises(LinkTimeout, match=r"no COMMAND_ACK for MAV_CMD_NAV_LAND from 1/191 within 0\.5 s"):
        client.command(land_command(), timeout_s=0.5)
    assert clock() - t0 == pytest.approx(0.5, abs=0.011)   # waited on the injected clock, not past it
    (cmd,) = vehicle.sent("COMMAND_LONG")
    assert math.isnan(cmd.param4) and cmd.param7 == 0.0   # unused params NaN, as MAVSDK sends them


def test_an_ack_for_another_command_does_not_end_the_wait() -> None:
    client, _, _ = make({mavlink.MAV_CMD_DO_SET_MODE: (mavlink.MAV_RESULT_ACCEPTED,)})
    with pytest.raises(LinkTimeout, match="MAV_CMD_COMPONENT_ARM_DISARM"):
        client.send_command_long(set_px4_mode_command(OFFBOARD))
        client.arm(timeout_s=0.2)   # the DO_SET_MODE ack arrives during the wait: not ours


def test_px4_mode_change_sends_main_and_sub_mode() -> None:
    client, vehicle, _ = make({mavlink.MAV_CMD_DO_SET_MODE: (mavlink.MAV_RESULT_ACCEPTED,)})
    client.set_px4_mode(OFFBOARD)
    (cmd,) = vehicle.sent("COMMAND_LONG")
    assert cmd.param1 == mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED and (cmd.param2, cmd.param3) == (6.0, 0.0)


def test_parameter_set_and_read_round_trip_through_the_param_service() -> None:
    client, vehicle, _ = make()
    assert client.set_param("TEST_GAIN", 2.5) == 2.5
    assert client.get_param("TEST_GAIN") == 2.5
    assert vehicle.params.table["TEST_GAIN"] == 2.5
    # an integer parameter goes bytewise both ways (PX4's encoding): 3 is stored as 3, read back as 3
    assert client.set_param("TEST_MODE", 3, mavlink.MAV_PARAM_TYPE_INT32) == 3.0
    assert vehicle.params.table["TEST_MODE"] == 3.0 and client.get_param("TEST_MODE") == 3.0
    # a refused set is answered with the unchanged value
    assert client.set_param("TEST_GAIN", 20.0) == 2.5


def test_an_unknown_parameter_times_out() -> None:
    client, _, _ = make()
    with pytest.raises(LinkTimeout, match="no PARAM_VALUE NOPE from 1/191 within 1 s"):
        client.get_param("NOPE", timeout_s=1.0)


def test_heartbeat_wait_sees_the_vehicle_and_times_out_without_it() -> None:
    client, _, clock = make(heartbeat_period_s=1.0)
    clock.now_s += 0.3    # the first heartbeat was due at the start
    msg = client.wait_heartbeat(timeout_s=2.0)
    assert msg.autopilot == mavlink.MAV_AUTOPILOT_PX4 and client.state.heartbeat_s == clock()
    silent, _, clock = make(heartbeat_period_s=None)
    t0 = clock()
    with pytest.raises(LinkTimeout, match=r"no HEARTBEAT from the vehicle 1 within 2 s"):
        silent.wait_heartbeat(timeout_s=2.0)
    assert clock() - t0 == pytest.approx(2.0, abs=0.011)


def test_heartbeat_if_due_is_1_hz_on_the_given_clock() -> None:
    client, vehicle, _ = make()
    sent = [client.heartbeat_if_due(t) for t in (0.0, 0.5, 0.99, 1.0, 1.5, 2.2)]
    assert sent == [True, False, False, True, False, True]
    beats = vehicle.sent("HEARTBEAT")
    assert len(beats) == 3 and all(m.type == mavlink.MAV_TYPE_GCS for m in beats)


def test_setpoints_decode_back_with_their_frame_and_mask() -> None:
    client, vehicle, _ = make()
    client.send_position_target(velocity_body(0.3, -0.2, 0.1, 0.5), time_boot_ms=2**32 + 1234)
    client.send_position_target(velocity_ned(0.2, 0.1, 0.0, 1.5), time_boot_ms=10, target_component=1)
    client.send_position_target(position_velocity_accel_ned((1, 2, -1), (0.1, 0.2, 0.3), (0.01, 0.02, 0.03), 0.7),
                                time_boot_ms=20)
    body, ned, pva = vehicle.sent("SET_POSITION_TARGET_LOCAL_NED")
    assert body.coordinate_frame == mavlink.MAV_FRAME_BODY_NED and body.type_mask == 1479
    assert body.time_boot_ms == 1234 and body.target_component == COMPANION_COMPONENT_ID
    g = mask_groups(body.type_mask)
    assert (g.position, g.velocity, g.acceleration, g.yaw, g.yaw_rate) == (False, True, False, False, True)
    assert (body.vx, body.vy, body.vz, body.yaw_rate) == pytest.approx((0.3, -0.2, 0.1, 0.5))
    assert ned.coordinate_frame == mavlink.MAV_FRAME_LOCAL_NED and ned.target_component == 1
    g = mask_groups(ned.type_mask)
    assert (g.position, g.velocity, g.acceleration, g.yaw, g.yaw_rate) == (False, True, False, True, False)
    assert (ned.vx, ned.vy, ned.yaw) == pytest.approx((0.2, 0.1, 1.5))
    g = mask_groups(pva.type_mask)
    assert pva.type_mask == 2048 and (g.position, g.velocity, g.acceleration, g.yaw) == (True, True, True, True)
    assert (pva.x, pva.y, pva.z, pva.vz, pva.afz, pva.yaw) == pytest.approx((1, 2, -1, 0.3, 0.03, 0.7))


def test_manual_control_carries_its_stamp_and_the_companion_pairs_them() -> None:
    client, vehicle, clock = make()
    clock.now_s = 12.345678
    client.send_manual_control(100, -200, 500, 300, 0)
    stamp, control = vehicle.received
    assert stamp.get_type() == "COMMAND_STAMP" and control.get_type() == "MANUAL_CONTROL"
    assert stamp.time_usec == 12_345_678 and stamp.command_msgid == mavlink.MAVLINK_MSG_ID_MANUAL_CONTROL
    assert (stamp.target_system, stamp.target_component) == (VEHICLE_SYSTEM_ID, COMPANION_COMPONENT_ID)
    assert (control.target, control.x, control.y, control.z, control.r) == (1, 100, -200, 500, 300)
    # the companion's command-age filter (the stamp's reader) pairs them: the stamp is the packet just before
    ages = CommandAgeFilter(CommandAgeParams())
    sender = (GROUND_SYSTEM_ID, GROUND_COMPONENT_ID)
    ages.on_stamp(sender, stamp.get_seq(), stamp.time_usec, stamp.command_msgid, 12.4)
    age = ages.on_command(sender, control.get_seq(), control.get_msgId(), 12.4, 0.0)
    assert age.stamped and age.verdict == Verdict.ACCEPTED and age.age_s == pytest.approx(12.4 - 12.345678)
    # unstamped (a client that does not stamp): just MANUAL_CONTROL
    client.send_manual_control(0, 0, 500, 0, 0, stamped=False)
    assert [m.get_type() for m in vehicle.received[2:]] == ["MANUAL_CONTROL"]


def test_timesync_requests_are_answered_on_the_client_clock() -> None:
    client, vehicle, clock = make(heartbeat_period_s=None)
    vehicle.mav.timesync_send(0, 5_000_000_000)          # the companion's request (tc1 = 0)
    (request,) = client.drain()
    clock.now_s = 7.0
    assert client.answer_timesync(request)
    (answer,) = vehicle.sent("TIMESYNC")
    assert (answer.tc1, answer.ts1) == (7_000_000_000, 5_000_000_000)
    vehicle.mav.timesync_send(1, 2)                       # a response: not answered
    (response,) = client.drain()
    assert not client.answer_timesync(response)


def test_teleop_feedback_gives_the_vehicle_clock_and_mode() -> None:
    client, vehicle, _ = make(heartbeat_period_s=None)
    seen: list[str] = []
    client.on_message = lambda m: seen.append(m.get_type())
    fields = dict.fromkeys(("vx_h", "vy_h", "vz_h", "vx_cmd", "vy_cmd", "vz_cmd", "vx_rep", "vy_rep", "vz_rep",
                            "alpha", "pan_scan_yaw_rate", "yaw_rate_cmd", "gyro_yaw_rate", "obstacle_x",
                            "obstacle_y", "obstacle_z", "obstacle_distance"), 0.0)
    vehicle.mav.send(mavlink.MAVLink_teleop_feedback_message(
        time_usec=42_500_000, mode=mavlink.QUADLINK_TELEOP_MODE_HOLD,
        flags=mavlink.QUADLINK_TELEOP_FLAGS_OBSTACLES_FRESH, **fields))
    assert client.wait_teleop_mode((mavlink.QUADLINK_TELEOP_MODE_TELEOP, mavlink.QUADLINK_TELEOP_MODE_HOLD),
                                   1.0) == mavlink.QUADLINK_TELEOP_MODE_HOLD
    assert client.state.time_s == 42.5 and client.state.teleop_flags == mavlink.QUADLINK_TELEOP_FLAGS_OBSTACLES_FRESH
    assert seen == ["TELEOP_FEEDBACK"]
    with pytest.raises(LinkTimeout, match="TELEOP_FEEDBACK in QUADLINK_TELEOP_MODE_LAND"):
        client.wait_teleop_mode((mavlink.QUADLINK_TELEOP_MODE_LAND,), 0.1)


def test_signing_signs_what_the_client_sends() -> None:
    clock = FakeClock()
    vehicle = FakeVehicle(clock, {mavlink.MAV_CMD_COMPONENT_ARM_DISARM: (mavlink.MAV_RESULT_ACCEPTED,)},
                          signing_key=KEY)     # the vehicle refuses unsigned packets
    conn = LoopbackMavfile(vehicle)
    Signing(KEY, link_id=3).enable(conn.mav)   # what connect(url, signing=...) does
    GroundClient(conn, clock=clock).arm()
    (cmd,) = vehicle.sent("COMMAND_LONG")
    assert cmd.get_signed() and cmd.get_link_id() == 3
    unsigned = FakeVehicle(FakeClock(), signing_key=KEY)
    GroundClient(LoopbackMavfile(unsigned)).send_heartbeat()
    assert unsigned.received == [] and unsigned.parser.signing.reject_count == 1   # refused by the signed vehicle

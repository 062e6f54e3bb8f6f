"""The deterministic lock-step's protocol pieces (quadlink/lockstep.py): routing of counts, registration rules,
the counted MAVLink link that hands over a step's datagrams and no more."""

from __future__ import annotations

import socket
import time

import pytest

from quadlink.lockstep import (
    Coordinator,
    CountedMavlink,
    LockstepClient,
    LockstepEnded,
    LockstepError,
    receiver_of,
    wait_for_units,
)
from quadlink.mavlink import mavlink
from quadlink.mavlink.connection import open_mavlink


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_receiver_of_a_link_is_the_name_after_the_arrow():
    assert receiver_of("companion>bridge") == "bridge"
    assert receiver_of("sitl>bridge.imu") == "bridge"
    assert receiver_of("sitl>companion.camera") == "companion"


def _pump_until(coord: Coordinator, done, timeout_s: float = 5.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not done():
        assert time.monotonic() < deadline, "coordinator did not see it"
        coord.poll(0.01)


def test_each_participant_is_sent_the_counts_of_its_own_input_links():
    coord = Coordinator("127.0.0.1", 0, ("bridge", "companion"))
    bridge = LockstepClient(coord.url, "bridge")
    companion = LockstepClient(coord.url, "companion")
    try:
        bridge.hello({"bridge>companion": 0, "bridge>sitl": 0})
        _pump_until(coord, lambda: coord.registered == {"bridge"})
        assert not coord.all_registered()
        companion.hello({"companion>bridge": 0})
        _pump_until(coord, coord.all_registered)
        coord.sent.update({"sitl>bridge.imu": 70, "sitl>companion.camera": 1})
        coord.send_step(0, 0.01)
        s_bridge, s_comp = bridge.next_step(2.0), companion.next_step(2.0)
        assert s_bridge is not None and s_comp is not None
        assert s_bridge.expect == {"companion>bridge": 0, "sitl>bridge.imu": 70}
        assert s_comp.expect == {"bridge>companion": 0, "sitl>companion.camera": 1}
        assert bridge.clock() == pytest.approx(0.01)
        bridge.done({"bridge>companion": 3, "bridge>sitl": 22})
        assert bridge.next_step(0.01) is None     # the DONE leaves as the participant turns to the next step
        _pump_until(coord, lambda: coord.waiting_for(0) == ["companion"])
        assert not coord.all_done(0)
        companion.done({"companion>bridge": 2})
        companion.close()      # its last step: it leaves at step 0, whatever the wall clock does next
        _pump_until(coord, lambda: coord.all_done(0))
        assert coord.left == {"companion"} and coord.all_registered()
        coord.send_step(1, 0.02)
        s_bridge = bridge.next_step(2.0)
        assert s_bridge is not None and s_bridge.expect["companion>bridge"] == 2
        coord.close("duration 0.02 s")
        with pytest.raises(LockstepEnded, match="duration"):
            while True:
                bridge.next_step(2.0)
    finally:
        bridge.close()
        companion.close()
        coord.close()


def test_a_participant_may_not_report_another_ones_links_nor_join_late():
    coord = Coordinator("127.0.0.1", 0, ("bridge", "operator"))
    bridge = LockstepClient(coord.url, "bridge")
    try:
        bridge.hello({"companion>bridge": 5})
        with pytest.raises(LockstepError, match="does not send on"):
            _pump_until(coord, lambda: False, timeout_s=2.0)
    finally:
        bridge.close()
        coord.close()
    coord = Coordinator("127.0.0.1", 0, ("bridge", "operator"))
    bridge = LockstepClient(coord.url, "bridge")
    late = LockstepClient(coord.url, "operator")
    try:
        bridge.hello({})
        _pump_until(coord, lambda: coord.registered == {"bridge"})
        coord.send_step(0, 0.01)
        late.hello({})
        with pytest.raises(LockstepError, match="after the simulation started"):
            _pump_until(coord, lambda: False, timeout_s=2.0)
    finally:
        bridge.close()
        late.close()
        coord.close()


def test_counted_link_hands_over_exactly_the_announced_datagrams():
    port = _free_udp_port()
    receiver = CountedMavlink(open_mavlink(f"udpin:127.0.0.1:{port}", source_system=1, source_component=191))
    sender = CountedMavlink(open_mavlink(f"udpout:127.0.0.1:{port}", source_system=255, source_component=190))
    try:
        # a udpin endpoint that has not heard its peer sends nothing, and does not count it
        receiver.conn.mav.heartbeat_send(mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        assert receiver.sent == 0
        for i in range(3):
            sender.conn.mav.named_value_int_send(i, b"n", i)
        assert sender.sent == 3
        receiver.allow = 2
        wait_for_units(lambda: receiver.received, 2, receiver.wait_readable, "test", timeout_s=2.0)
        got = []
        while (msg := receiver.conn.recv_msg()) is not None:
            got.append(msg.value)
        assert got == [0, 1]          # the third waits for the step that announces it
        receiver.allow = 3
        wait_for_units(lambda: receiver.received, 3, receiver.wait_readable, "test", timeout_s=2.0)
        assert receiver.conn.recv_msg().value == 2
        assert receiver.conn.recv_msg() is None
        # the receiver has heard its peer: now its datagrams leave, and count
        receiver.conn.mav.heartbeat_send(mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        assert receiver.sent == 1
        with pytest.raises(LockstepError, match="3 of 4 units"):
            wait_for_units(lambda: receiver.received, 4, receiver.wait_readable, "test", timeout_s=0.2)
    finally:
        receiver.conn.close()
        sender.conn.close()

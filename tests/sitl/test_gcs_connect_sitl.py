"""QGroundControl's connect sequence, replayed in order with pymavlink against SITL + bridge, directly and
through the companion's ground-station endpoint: every request answered (100 %).

The sequence and the answers a ground station waits for, from QGroundControl's sources
(InitialConnectStateMachine: autopilot version, component information, standard modes, parameters, mission,
geofence, rally; Vehicle.cc: the protocol version request, home position; the gimbal controller's request):
the table is in firmware_bridge/README.md ("Ground stations").
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import flight_harness
import pytest

from harness.demo.parts import BridgePart, CompanionPart, SitlPart
from quadlink.mavlink import mavlink
from quadlink.mavlink.connection import open_mavlink

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(300)]

A, U = mavlink.MAV_RESULT_ACCEPTED, mavlink.MAV_RESULT_UNSUPPORTED
COMPONENT_INFORMATION, COMPONENT_METADATA, AVAILABLE_MODES = 395, 397, 435   # not in common.xml's dialect
GIMBAL_MANAGER_INFORMATION = 280


class Client:
    """A ground station on one UDP socket: a reader thread queues the vehicle's messages."""

    def __init__(self, url: str) -> None:
        self.conn = open_mavlink(url, 255, 190)
        self.enc = mavlink.MAVLink(None, 255, 190)
        self.inbox: queue.Queue = queue.Queue()
        self.lock = threading.Lock()
        self._stop = threading.Event()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        while not self._stop.is_set():
            m = self.conn.recv_match(blocking=True, timeout=0.1)
            if m is not None and m.get_srcSystem() == 1 and m.get_srcComponent() == 1 and \
                    m.get_type() not in ("HIGHRES_IMU", "ATTITUDE", "ATTITUDE_QUATERNION"):
                self.inbox.put(m)

    def send(self, msg: Any) -> None:
        with self.lock:
            buf = msg.pack(self.enc)
            self.enc.seq = (self.enc.seq + 1) % 256
            if hasattr(self.conn, "clients") and self.conn.clients:   # udpin: to the learnt peer
                for address in list(self.conn.clients):
                    self.conn.port.sendto(buf, address)
            else:
                self.conn.write(buf)

    def recv(self, kind: str, timeout_s: float, cond: Callable[[Any], bool] = lambda m: True) -> Any:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            try:
                m = self.inbox.get(timeout=0.1)
            except queue.Empty:
                continue
            if m.get_type() == kind and cond(m):
                return m
        return None

    def drain(self) -> None:
        while not self.inbox.empty():
            self.inbox.get_nowait()

    def close(self) -> None:
        self._stop.set()
        self._reader.join(timeout=2.0)
        self.conn.close()


def qgc_connect_sequence(c: Client) -> list[tuple[str, bool]]:
    """QGroundControl's requests in its order; (request, answered as QGC expects) for each."""
    results: list[tuple[str, bool]] = []

    def command(name: str, cmd: int, expect: int, reply: str | None, *params: float, compid: int = 1) -> None:
        p = list(params) + [0.0] * (7 - len(params))
        c.drain()
        c.send(c.enc.command_long_encode(1, compid, cmd, 0, *p))
        ack = c.recv("COMMAND_ACK", 5.0, lambda m: m.command == cmd)
        ok = ack is not None and ack.result == expect and ack.target_system == 255 and ack.target_component == 190
        if ok and reply is not None:
            ok = c.recv(reply, 5.0) is not None
        results.append((name, ok))

    c.send(c.enc.heartbeat_encode(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0))
    hb = c.recv("HEARTBEAT", 30.0)
    results.append(("HEARTBEAT (PX4 quadrotor)", hb is not None and hb.autopilot == mavlink.MAV_AUTOPILOT_PX4
                    and hb.type == mavlink.MAV_TYPE_QUADROTOR))
    command("REQUEST_MESSAGE AUTOPILOT_VERSION", mavlink.MAV_CMD_REQUEST_MESSAGE, A, "AUTOPILOT_VERSION",
            mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
    command("REQUEST_PROTOCOL_VERSION", mavlink.MAV_CMD_REQUEST_PROTOCOL_VERSION, A, "PROTOCOL_VERSION", 1,
            compid=0)
    command("REQUEST_MESSAGE COMPONENT_METADATA", mavlink.MAV_CMD_REQUEST_MESSAGE, U, None, COMPONENT_METADATA)
    command("REQUEST_MESSAGE COMPONENT_INFORMATION", mavlink.MAV_CMD_REQUEST_MESSAGE, U, None,
            COMPONENT_INFORMATION)
    command("REQUEST_MESSAGE AVAILABLE_MODES", mavlink.MAV_CMD_REQUEST_MESSAGE, U, None, AVAILABLE_MODES, 0)
    c.drain()
    c.send(c.enc.param_request_list_encode(1, 1))
    values: dict[str, float] = {}
    count = None
    deadline = time.monotonic() + 20.0
    while (count is None or len(values) < count) and time.monotonic() < deadline:
        m = c.recv("PARAM_VALUE", 1.0)
        if m is not None:
            values[m.param_id] = m.param_value
            count = m.param_count
    results.append(("PARAM_REQUEST_LIST", count is not None and len(values) == count))
    for mission_type, name in ((0, "mission"), (1, "fence"), (2, "rally")):
        c.drain()
        c.send(c.enc.mission_request_list_encode(1, 1, mission_type))
        got = c.recv("MISSION_COUNT", 5.0, lambda m, t=mission_type: m.mission_type == t)
        results.append((f"MISSION_REQUEST_LIST {name}", got is not None and got.count == 0
                        and got.target_component == 190))
    command("REQUEST_MESSAGE HOME_POSITION", mavlink.MAV_CMD_REQUEST_MESSAGE, U, None,
            mavlink.MAVLINK_MSG_ID_HOME_POSITION)
    command("REQUEST_MESSAGE GIMBAL_MANAGER_INFORMATION", mavlink.MAV_CMD_REQUEST_MESSAGE, U, None,
            GIMBAL_MANAGER_INFORMATION)
    # the SYS_STATUS QGC then shows: no phantom failure (every present sensor healthy on the ground but
    # vision/position control, which need the companion's odometry: absent here, so honestly unhealthy)
    s = c.recv("SYS_STATUS", 5.0)
    odometry = (mavlink.MAV_SYS_STATUS_SENSOR_VISION_POSITION | mavlink.MAV_SYS_STATUS_SENSOR_XY_POSITION_CONTROL
                | mavlink.MAV_SYS_STATUS_SENSOR_Z_ALTITUDE_CONTROL)
    results.append(("SYS_STATUS consistent", s is not None
                    and s.onboard_control_sensors_present == s.onboard_control_sensors_enabled
                    and (s.onboard_control_sensors_present & ~s.onboard_control_sensors_health & ~odometry) == 0))
    return results


class BridgeUnderTest:
    """SITL (lock-step at real-time pace, no camera) + bridge, its first endpoint a ground station's (``gcs_port``)
    and its second the companion's, and the companion's ground-station port (``vehicle_port``): the flight harness's
    :class:`flight_harness.Vehicle`."""

    def __init__(self, tmp: Path) -> None:
        self.parts = flight_harness.Vehicle(tmp, SitlPart(scenario=None, camera=False, truth=False, speed=1.0,
                                                    duration_s=None),
                                    BridgePart(outputs=("gcs_bridge", "autopilot")), CompanionPart())
        self.gcs_port, self.vehicle_port = self.parts.ports.gcs_bridge, self.parts.ports.vehicle

    def close(self) -> None:
        self.parts.close()


@pytest.fixture(scope="module")
def vehicle(tmp_path_factory: pytest.TempPathFactory) -> Any:
    v = BridgeUnderTest(tmp_path_factory.mktemp("gcs_connect"))
    yield v
    v.close()


@pytest.mark.parametrize("path", ["bridge", "companion"])
def test_qgroundcontrol_connect_sequence_is_answered_in_full(vehicle: BridgeUnderTest, path: str) -> None:
    url = f"udpin:127.0.0.1:{vehicle.gcs_port}" if path == "bridge" else f"udpout:127.0.0.1:{vehicle.vehicle_port}"
    client = Client(url)
    try:
        if path == "companion":   # the companion learns our address from what we send
            client.send(client.enc.heartbeat_encode(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0))
        # the first autopilot heartbeat (1 Hz of board time: slow while a loaded machine starts the lock-step SITL)
        assert client.recv("HEARTBEAT", 90.0) is not None, f"{path}: no autopilot heartbeat"
        results = qgc_connect_sequence(client)
    finally:
        client.close()
    unanswered = [name for name, ok in results if not ok]
    print(f"{path}: {len(results) - len(unanswered)}/{len(results)} answered")
    assert not unanswered, f"{path}: not answered as QGroundControl expects: {unanswered}"

"""Ground truth over MAVLink: positions, attitude, distances to surfaces, sim-time stamps."""

from __future__ import annotations

import math
import socket
import time

import numpy as np
import pytest

from quadlink.mavlink import mavlink
from quadlink.mavlink.tlog import read_tlog
from quadlink.vehicle import load_vehicle
from sim_sitl.config import RoomConfig, ScenarioConfig, SceneObject, SitlConfig, load_scenario
from sim_sitl.runner import Sitl, SitlOptions
from sim_sitl.truth import TRUTH_SYSID, TruthEncoder
from sim_sitl.world import World


def _decode(packets: list[bytes]) -> list:
    mav = mavlink.MAVLink(None)
    out = []
    for pkt in packets:
        out += mav.parse_buffer(pkt) or []
    return out


def test_truth_encoder_messages_and_units():
    enc = TruthEncoder()
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # yaw +90 deg (facing east)
    msgs = _decode(enc.encode(1.234, np.array([1.0, 2.0, -3.0]), np.array([0.1, 0.2, 0.3]), R,
                              np.array([0.0, 0.0, 0.5]), 0.456, math.inf))
    by = {m.get_type(): m for m in msgs if m.get_type() != "DISTANCE_SENSOR"}
    assert all(m.get_srcSystem() == TRUTH_SYSID for m in msgs)
    lp = by["LOCAL_POSITION_NED"]
    assert (lp.time_boot_ms, lp.x, lp.y, lp.z, lp.vz) == (1234, 1.0, 2.0, -3.0, pytest.approx(0.3))
    q = by["ATTITUDE_QUATERNION"]
    assert [q.q1, q.q2, q.q3, q.q4] == pytest.approx([math.cos(math.pi / 4), 0, 0, math.sin(math.pi / 4)], abs=1e-6)
    assert q.yawspeed == pytest.approx(0.5)
    dist = {m.id: m for m in msgs if m.get_type() == "DISTANCE_SENSOR"}
    assert dist[0].current_distance == 46 and dist[1].current_distance > dist[1].max_distance  # none in range
    assert "HEARTBEAT" in by


def test_nearest_surface_distances_in_the_arena():
    scenario = load_scenario("paper-arena")
    world = World(load_vehicle(), SitlConfig(), scenario, np.random.default_rng(0))
    try:
        column = next(o for o in scenario.objects if o.name == "column")
        # 1.0 m from the column's surface, 1.5 m above the floor (ceiling 1.5 m away)
        p = np.array([column.position_m[0] - column.radius_m - 1.0, column.position_m[1], -1.5])
        any_m, obstacle_m = world.nearest_distances(p)
        assert obstacle_m == pytest.approx(1.0, abs=0.01)
        assert any_m == pytest.approx(1.0, abs=0.01)
        p_low = p.copy()
        p_low[2] = -0.4  # the floor is the nearest surface; excluding it, the column still is
        any_m, obstacle_m = world.nearest_distances(p_low)
        assert any_m == pytest.approx(0.4, abs=0.005) and obstacle_m == pytest.approx(1.0, abs=0.01)
    finally:
        world.close()


def test_floor_type_objects_are_excluded_from_the_obstacle_distance():
    rug = SceneObject(kind="box", name="rug", position_m=(0.0, 0.0, -0.005), size_m=(2.0, 2.0, 0.01), surface="floor")
    scenario = ScenarioConfig(name="rug", room=RoomConfig(size_m=(10.0, 10.0)), objects=(rug,))
    world = World(load_vehicle(), SitlConfig(), scenario, np.random.default_rng(0))
    try:
        assert world.start_p_ned_m[2] == pytest.approx(-0.11, abs=0.002)  # resting on the rug
        any_m, obstacle_m = world.nearest_distances(np.array([0.0, 0.0, -0.5]))
        assert any_m == pytest.approx(0.49, abs=0.005) and obstacle_m == pytest.approx(5.0, abs=0.01)
    finally:
        world.close()


@pytest.mark.sitl
def test_truth_stream_over_udp_at_50_hz_in_sim_time(tmp_path):
    """The stream over UDP, and the same packets in the SITL's own truth tlog (``--truth-tlog``), in order."""
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.settimeout(0.5)
    port = rx.getsockname()[1]
    opts = SitlOptions(config=SitlConfig(scenario="empty"), port1=0, port2=0, camera=False, speed=4.0,
                       truth_url=f"udpout:127.0.0.1:{port}", duration_s=2.0, progress_every_s=60.0,
                       truth_tlog=tmp_path / "truth.tlog")
    sitl = Sitl(opts).start()
    packets = []
    try:
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and not sitl.wait(0.0):
            try:
                packets.append(rx.recv(2048))
            except TimeoutError:
                continue
        while True:
            try:
                packets.append(rx.recv(2048))
            except TimeoutError:
                break
    finally:
        sitl.stop()
        rx.close()
    msgs = _decode(packets)
    lp = [m for m in msgs if m.get_type() == "LOCAL_POSITION_NED"]
    assert len(lp) >= 95  # 2 s at 50 Hz
    t = np.array([m.time_boot_ms for m in lp])
    assert np.all(np.diff(t) == 20)
    assert abs(lp[-1].x) < 0.01 and abs(lp[-1].z) < 0.01  # resting at the start position (origin)
    d = [m for m in msgs if m.get_type() == "DISTANCE_SENSOR"]
    floor = [m.current_distance for m in d if m.id == 0]
    walls = [m.current_distance for m in d if m.id == 1]
    assert floor[-1] == pytest.approx(10, abs=1)  # CoM 10 cm above the floor (landing gear)
    assert walls[-1] == pytest.approx(500, abs=1)  # centre of the 10 m room
    logged = [bytes(m.get_msgbuf()) for _, m in read_tlog(tmp_path / "truth.tlog")]
    assert logged == packets and sitl.truth_tlog is not None and sitl.truth_tlog.failed is None

"""The bridge on the pybullet SITL (lock-step, real-time paced), driven by pymavlink like MAVProxy would.

The companion does not exist in these tests, so the velocity source is ODOMETRY built from the SITL's
ground truth (allowed in a test; the flight code never reads truth). Everything runs on free ports.
"""

from __future__ import annotations

import asyncio
import math
import queue
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from flight_harness import TruthReader, Vehicle

from harness.demo.parts import BridgePart, CompanionPart, SitlPart
from quadlink.frames import R_from_quat_wxyz, euler_from_R
from quadlink.mavlink import mavlink
from quadlink.mavlink.connection import open_mavlink

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(240)]

PX4_OFFBOARD = 6 << 16
PX4_LOITER = 4 << 16 | 3 << 24


#: the SITL of these tests: lock-step at real-time pace, no camera, its default scenario
BRIDGE_SITL = SitlPart(scenario=None, camera=False, speed=1.0, duration_s=None)


class Stack(TruthReader):
    """The SITL and the bridge (the flight harness's :class:`Vehicle`), the bridge sending MAVLink to ``gcs_port``
    and ``mavsdk_port``; the truth read in a thread."""

    def __init__(self, tmp: Path, sitl: SitlPart = BRIDGE_SITL) -> None:
        self.tmp = tmp
        self.vehicle = Vehicle(tmp, sitl, BridgePart(outputs=("gcs_bridge", "autopilot")))
        p = self.vehicle.ports
        self.ports = p
        self.gcs_port, self.mavsdk_port = p.gcs_bridge, p.autopilot
        self.params_file = self.vehicle.params_file
        try:
            super().__init__(p.truth)
        except BaseException:
            self.vehicle.close()
            raise

    def start_companion(self, part: CompanionPart) -> None:
        """The companion between the bridge's first endpoint (``gcs_port``) and the ground stations' port
        (``ports.vehicle``)."""
        self.vehicle.start_companion(part)

    def close(self) -> None:
        try:
            super().close()
        finally:
            self.vehicle.close()


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    s = Stack(tmp_path_factory.mktemp("bridge_sitl"))
    yield s
    s.close()


class Gcs:
    """A pymavlink client: one thread parses (pymavlink's mavfile is not thread-safe), sends use their own
    encoder under a lock and go out of the same UDP socket to the bridge's address."""

    def __init__(self, port: int) -> None:
        self.conn = open_mavlink(f"udpin:127.0.0.1:{port}", 255, 190)
        self.encoder = mavlink.MAVLink(None, 255, 190)
        self.lock = threading.Lock()
        self.inbox: queue.Queue = queue.Queue()
        self.texts: list[str] = []  # every STATUSTEXT that recv() went past
        self._stop = threading.Event()
        self._closed = False  # under self.lock: a sender thread still running after close() drops its message
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        while not self._stop.is_set():
            m = self.conn.recv_match(blocking=True, timeout=0.1)
            if m is not None and m.get_srcSystem() == 1 and m.get_type() not in ("HIGHRES_IMU", "ATTITUDE"):
                self.inbox.put(m)

    def send(self, msg) -> None:
        with self.lock:
            if self._closed:
                return
            buf = msg.pack(self.encoder)
            self.encoder.seq = (self.encoder.seq + 1) % 256
            for address in list(self.conn.clients):  # the bridge's udpout socket, learnt by the reader
                self.conn.port.sendto(buf, address)

    def recv(self, type_, timeout_s: float, cond=lambda m: True):
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            try:
                m = self.inbox.get(timeout=0.1)
            except queue.Empty:
                continue
            if m.get_type() == "STATUSTEXT":
                self.texts.append(m.text)
            if m.get_type() == type_ and cond(m):
                return m
        return None

    def command(self, command: int, *params: float) -> int:
        p = list(params) + [0.0] * (7 - len(params))
        self.send(self.encoder.command_long_encode(1, 1, command, 0, *p))
        ack = self.recv("COMMAND_ACK", 3.0, lambda m: m.command == command)
        assert ack is not None, f"no COMMAND_ACK for {command}"
        return ack.result

    def close(self) -> None:
        self._stop.set()
        self._reader.join(timeout=2.0)
        with self.lock:
            self._closed = True
            self.conn.close()


def test_heartbeat_and_parameter_download(stack, tmp_path):
    gcs = Gcs(stack.gcs_port)
    try:
        hb = gcs.recv("HEARTBEAT", 20.0)
        assert hb is not None and hb.type == mavlink.MAV_TYPE_QUADROTOR
        gcs.send(gcs.encoder.param_request_list_encode(1, 1))
        values = {}
        deadline = time.monotonic() + 10.0
        count = None
        while (count is None or len(values) < count) and time.monotonic() < deadline:
            m = gcs.recv("PARAM_VALUE", 1.0)
            if m is not None:
                values[m.param_id] = m.param_value
                count = m.param_count
        assert count is not None and len(values) == count
        gcs.send(gcs.encoder.param_set_encode(1, 1, b"MPC_LAND_SPEED", 0.5, mavlink.MAV_PARAM_TYPE_REAL32))
        echo = gcs.recv("PARAM_VALUE", 3.0, lambda m: m.param_id == "MPC_LAND_SPEED")
        assert echo is not None and echo.param_value == pytest.approx(0.5)
        gcs.send(gcs.encoder.param_request_read_encode(1, 1, b"MPC_LAND_SPEED", -1))
        again = gcs.recv("PARAM_VALUE", 3.0, lambda m: m.param_id == "MPC_LAND_SPEED")
        assert again is not None and again.param_value == pytest.approx(0.5)  # it sticks
        deadline = time.monotonic() + 5.0
        while "MPC_LAND_SPEED: 0.5" not in (stack.params_file.read_text() if stack.params_file.exists() else ""):
            assert time.monotonic() < deadline, "parameter not persisted"
            time.sleep(0.2)
    finally:
        gcs.close()


class Odometry(threading.Thread):
    """ODOMETRY at ~30 Hz from the SITL truth: local FRD frame, velocity in body FRD."""

    def __init__(self, stack: Stack, gcs: Gcs) -> None:
        super().__init__(daemon=True)
        self.stack, self.gcs = stack, gcs
        self.stop = threading.Event()

    def run(self) -> None:
        while not self.stop.wait(1.0 / 30.0):
            p, v, q = self.stack.state()
            R = R_from_quat_wxyz(q)
            v_q = R.T @ v
            self.gcs.send(self.gcs.encoder.odometry_encode(
                int(time.monotonic() * 1e6), mavlink.MAV_FRAME_LOCAL_FRD, mavlink.MAV_FRAME_BODY_FRD,
                *p, q, *v_q, 0, 0, 0, [math.nan] * 21, [math.nan] * 21, 0, 0, 100))


class Setpoints(threading.Thread):
    """SET_POSITION_TARGET_LOCAL_NED (type_mask 1479, MAV_FRAME_BODY_NED) at 20 Hz, like MAVSDK."""

    def __init__(self, gcs: Gcs) -> None:
        super().__init__(daemon=True)
        self.gcs = gcs
        self.v_body = (0.0, 0.0, 0.0)
        self.yaw_rate = 0.0
        self.stop = threading.Event()

    def run(self) -> None:
        while not self.stop.wait(0.05):
            self.gcs.send(self.gcs.encoder.set_position_target_local_ned_encode(
                0, 1, 1, mavlink.MAV_FRAME_BODY_NED, 1479, 0, 0, 0, *self.v_body, 0, 0, 0, 0, self.yaw_rate))


def wait_for(pred, timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not pred():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.1)


def test_arm_takeoff_offboard_body_velocity_and_land(stack):
    gcs = Gcs(stack.gcs_port)
    odom = Odometry(stack, gcs)
    sps = Setpoints(gcs)
    try:
        assert gcs.recv("HEARTBEAT", 20.0) is not None
        wait_for(lambda: stack.truth_count > 10, 10.0, "truth")
        odom.start()
        time.sleep(1.0)
        assert gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mavlink.MAV_RESULT_ACCEPTED
        assert gcs.recv("HEARTBEAT", 3.0, lambda m: m.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED) is not None
        assert gcs.command(mavlink.MAV_CMD_NAV_TAKEOFF, *([math.nan] * 7)) == mavlink.MAV_RESULT_ACCEPTED
        assert gcs.recv("HEARTBEAT", 20.0, lambda m: m.custom_mode == PX4_LOITER) is not None
        p, _, _ = stack.state()
        assert -p[2] == pytest.approx(1.0, abs=0.25)  # MIS_TAKEOFF_ALT, per the truth

        sps.start()
        time.sleep(1.0)
        assert gcs.command(mavlink.MAV_CMD_DO_SET_MODE, 1, 6, 0) == mavlink.MAV_RESULT_ACCEPTED
        assert gcs.recv("HEARTBEAT", 3.0, lambda m: m.custom_mode == PX4_OFFBOARD) is not None
        # a 90 degree turn, then "forward" and "right" in the body frame
        sps.yaw_rate = math.radians(30)
        time.sleep(3.0)
        sps.yaw_rate = 0.0
        time.sleep(1.0)
        for v_body, name in (((0.5, 0.0, 0.0), "forward"), ((0.0, 0.5, 0.0), "right")):
            p0, _, q = stack.state()
            yaw = euler_from_R(R_from_quat_wxyz(q))[2]
            expected = np.array([math.cos(yaw), math.sin(yaw)]) if name == "forward" else \
                np.array([-math.sin(yaw), math.cos(yaw)])
            t0 = stack.sim_time_s
            sps.v_body = v_body
            wait_for(lambda t0=t0: stack.sim_time_s - t0 >= 4.0, 30.0, "4 s of simulated time")
            commanded_m = 0.5 * (stack.sim_time_s - t0)  # simulated time: lock-step may run slower than wall
            sps.v_body = (0.0, 0.0, 0.0)
            time.sleep(1.5)
            p1, _, _ = stack.state()
            d = (p1 - p0)[:2]
            along = float(d @ expected)
            across = float(abs(d[0] * expected[1] - d[1] * expected[0]))
            assert commanded_m > 1.0
            assert along > 0.7 * commanded_m, f"{name}: moved {d} along {expected}, commanded {commanded_m:.2f} m"
            assert across < 0.5 * along, f"{name}: moved {d}, off the commanded direction {expected}"
            assert abs(p1[2] - p0[2]) < 0.3
        sps.stop.set()
        assert gcs.command(mavlink.MAV_CMD_NAV_LAND) == mavlink.MAV_RESULT_ACCEPTED
        assert gcs.recv("HEARTBEAT", 25.0, lambda m: not m.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED) \
            is not None
        p, _, _ = stack.state()
        assert abs(p[2]) < 0.15
    except Exception:   # a failed assertion; not Ctrl-C or a timeout, which should not wait for a landing
        _land_after_failure(gcs)
        raise
    finally:
        sps.stop.set()
        odom.stop.set()
        gcs.close()


async def _mavsdk_flight(stack: Stack) -> dict:
    from mavsdk.asyncio import ComponentType, Configuration, Mavsdk
    from mavsdk.asyncio.plugins.action.action import ActionAsync
    from mavsdk.asyncio.plugins.offboard.offboard import OffboardAsync, VelocityBodyYawspeed
    from mavsdk.asyncio.plugins.telemetry.telemetry import FlightMode, TelemetryAsync

    async def first(gen, timeout_s=5.0):
        return await asyncio.wait_for(anext(gen), timeout_s)

    async def until(gen, pred, timeout_s):
        async def scan():
            async for value in gen:
                if pred(value):
                    return value
        return await asyncio.wait_for(scan(), timeout_s)

    seen: dict = {}
    config = Configuration.create_with_component_type(ComponentType.GROUND_STATION)
    async with Mavsdk(config) as mavsdk:
        await mavsdk.add_any_connection(f"udpin://127.0.0.1:{stack.mavsdk_port}")
        system = await mavsdk.first_autopilot(timeout_s=20.0)
        assert system is not None, "MAVSDK did not discover the bridge"
        telemetry, action, offboard = TelemetryAsync(system), ActionAsync(system), OffboardAsync(system)
        seen["attitude"] = await first(telemetry.subscribe_attitude_euler())
        seen["battery"] = await first(telemetry.subscribe_battery())
        seen["mode0"] = await first(telemetry.subscribe_flight_mode())
        await action.arm()
        await until(telemetry.subscribe_armed(), bool, 5.0)
        await action.takeoff()
        await until(telemetry.subscribe_flight_mode(), lambda m: m == FlightMode.HOLD, 25.0)
        seen["takeoff_p"], _, _ = stack.state()
        await offboard.set_velocity_body(VelocityBodyYawspeed(0.0, 0.0, 0.0, 0.0))
        await offboard.start()
        seen["offboard_mode"] = await until(telemetry.subscribe_flight_mode(),
                                            lambda m: m == FlightMode.OFFBOARD, 5.0)
        _, _, q = stack.state()
        seen["yaw0"] = euler_from_R(R_from_quat_wxyz(q))[2]
        # a velocity square in the body frame: forward, right, backward, left, 0.5 m/s for 4 s each
        seen["corners"] = [stack.state()[0]]
        seen["commanded_m"] = []
        for forward, right in ((0.5, 0.0), (0.0, 0.5), (-0.5, 0.0), (0.0, -0.5)):
            t0 = stack.sim_time_s
            await offboard.set_velocity_body(VelocityBodyYawspeed(forward, right, 0.0, 0.0))
            while stack.sim_time_s - t0 < 4.0:  # simulated time: a loaded machine runs the lock-step SITL slower
                await asyncio.sleep(0.05)
            seen["commanded_m"].append(0.5 * (stack.sim_time_s - t0))
            seen["corners"].append(stack.state()[0])
        await offboard.set_velocity_body(VelocityBodyYawspeed(0.0, 0.0, 0.0, 0.0))
        await asyncio.sleep(1.5)
        seen["end"] = stack.state()[0]
        await action.land()
        await until(telemetry.subscribe_armed(), lambda armed: not armed, 30.0)
        seen["landed_p"], _, _ = stack.state()
    return seen


def test_mavsdk_arm_takeoff_offboard_velocity_square_land(stack):
    gcs = Gcs(stack.gcs_port)
    odom = Odometry(stack, gcs)  # the velocity source, from the truth (no companion in this test)
    try:
        assert gcs.recv("HEARTBEAT", 20.0) is not None
        wait_for(lambda: stack.truth_count > 10, 10.0, "truth")
        odom.start()
        seen = asyncio.run(asyncio.wait_for(_mavsdk_flight(stack), 150.0))
    finally:
        odom.stop.set()
        gcs.close()
    assert abs(seen["attitude"].roll_deg) < 5.0 and abs(seen["attitude"].pitch_deg) < 5.0
    assert seen["battery"].voltage_v > 9.0 and 0 <= seen["battery"].remaining_percent <= 100
    assert -seen["takeoff_p"][2] > 0.7
    yaw = seen["yaw0"]
    forward = np.array([math.cos(yaw), math.sin(yaw)])
    right = np.array([-math.sin(yaw), math.cos(yaw)])
    corners = np.array(seen["corners"])[:, :2]
    for leg, (expected, commanded_m) in enumerate(zip((forward, right, -forward, -right), seen["commanded_m"])):
        d = corners[leg + 1] - corners[leg]
        along = float(d @ expected)
        assert commanded_m > 1.0
        # the leg's corner is sampled while the vehicle is still turning the previous corner: generous bounds
        assert along > 0.6 * commanded_m, f"leg {leg}: moved {d}, expected {commanded_m:.2f} m along {expected}"
        assert abs(d[0] * expected[1] - d[1] * expected[0]) < 0.6 * along, f"leg {leg}: moved {d}"
    side = float(np.mean(seen["commanded_m"]))
    closure = float(np.linalg.norm(seen["end"][:2] - corners[0]))
    legs = np.linalg.norm(np.diff(corners, axis=0), axis=1)
    print(f"square: legs {np.round(legs, 2)} m for {side:.2f} m commanded, closure {closure:.2f} m")
    assert closure < 0.4 * side, f"the square does not close: {closure:.2f} m for {side:.2f} m sides"
    assert abs(seen["landed_p"][2]) < 0.15


class GatedOdometry(Odometry):
    """The companion on the ground: ODOMETRY flagged failed (quality 0, zero velocity) while the camera sees
    the floor closer than its minimum range; valid odometry from the truth once the truth height exceeds
    ``valid_above_m`` (latched), or never (``valid_above_m`` None). With ``lost_from``, valid until that event
    is set (odometry that fails as the vehicle lifts off), then gated as above."""

    def __init__(self, stack: Stack, gcs: Gcs, valid_above_m: float | None,
                 lost_from: threading.Event | None = None) -> None:
        super().__init__(stack, gcs)
        self.valid_above_m = valid_above_m
        self.valid_since_height_m: float | None = None
        self.lost_from = lost_from

    def run(self) -> None:
        while not self.stop.wait(1.0 / 30.0):
            p, v, q = self.stack.state()
            before_loss = self.lost_from is not None and not self.lost_from.is_set()
            if self.valid_since_height_m is None and self.valid_above_m is not None and -p[2] > self.valid_above_m \
                    and not before_loss:
                self.valid_since_height_m = float(-p[2])
            if self.valid_since_height_m is None and not before_loss:
                self.gcs.send(self.gcs.encoder.odometry_encode(
                    int(time.monotonic() * 1e6), mavlink.MAV_FRAME_LOCAL_FRD, mavlink.MAV_FRAME_BODY_FRD,
                    0, 0, 0, [1, 0, 0, 0], 0, 0, 0, 0, 0, 0, [math.nan] * 21, [math.nan] * 21, 0, 0, 0))
                continue
            v_q = R_from_quat_wxyz(q).T @ v
            self.gcs.send(self.gcs.encoder.odometry_encode(
                int(time.monotonic() * 1e6), mavlink.MAV_FRAME_LOCAL_FRD, mavlink.MAV_FRAME_BODY_FRD,
                *p, q, *v_q, 0, 0, 0, [math.nan] * 21, [math.nan] * 21, 0, 0, 100))


def _statustexts(gcs: Gcs) -> list[str]:
    gcs.recv("STATUSTEXT", 0.2, lambda m: False)  # drain the inbox into gcs.texts
    return list(gcs.texts)


class PeakHeight(threading.Thread):
    """The truth's highest point above ``p_ground_z`` (NED), sampled every 10 ms (wall) until stopped."""

    def __init__(self, stack: Stack, p_ground_z: float) -> None:
        super().__init__(daemon=True)
        self.stack, self.p_ground_z = stack, p_ground_z
        self.top_m = -math.inf
        self.stop = threading.Event()

    def run(self) -> None:
        while not self.stop.wait(0.01):
            self.top_m = max(self.top_m, self.p_ground_z - float(self.stack.state()[0][2]))


def _land(gcs: Gcs) -> None:
    assert gcs.command(mavlink.MAV_CMD_NAV_LAND) == mavlink.MAV_RESULT_ACCEPTED
    assert gcs.recv("HEARTBEAT", 25.0, lambda m: not m.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED) is not None


def _land_after_failure(gcs: Gcs) -> None:
    """A test failed, perhaps in the air: LAND (its odometry still flowing) and wait for the disarm, so the module's
    next flight starts on the ground (CI once began the next take-off 0.75 m up). Never raises: the failure that
    brought it here is the one to report."""
    try:
        gcs.command(mavlink.MAV_CMD_NAV_LAND)
        if gcs.recv("HEARTBEAT", 60.0, lambda m: not m.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED) is None:
            print("after the failure: still armed 60 s after LAND")
    except Exception as e:  # noqa: BLE001 - cleanup after a failure already being reported
        print(f"after the failure, LAND: {e!r}")


def test_takeoff_without_odometry_on_the_ground_climbs_open_loop_then_closed_loop(stack):
    """Odometry only once the truth is 0.4 m up: phase 1 on the accelerometer, phase 2 to the take-off height."""
    gcs = Gcs(stack.gcs_port)
    odom = GatedOdometry(stack, gcs, valid_above_m=0.4)
    try:
        assert gcs.recv("HEARTBEAT", 20.0) is not None
        wait_for(lambda: stack.truth_count > 10, 10.0, "truth")
        odom.start()
        time.sleep(1.0)
        p_ground, _, _ = stack.state()
        assert gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mavlink.MAV_RESULT_ACCEPTED
        # armed on the ground without odometry: no failsafe. Heartbeats follow board time, which runs slower
        # than the wall clock on a loaded machine, so wait for the armed one instead of taking the next one.
        hb = gcs.recv("HEARTBEAT", 15.0, lambda m: m.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
        assert hb is not None, "no armed heartbeat"
        hb = gcs.recv("HEARTBEAT", 5.0)  # and it stays armed, not critical, one heartbeat later
        assert hb is not None and hb.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        assert hb.system_status != mavlink.MAV_STATE_CRITICAL
        assert gcs.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, math.nan, math.nan, 1.2) \
            == mavlink.MAV_RESULT_ACCEPTED
        assert gcs.recv("HEARTBEAT", 25.0, lambda m: m.custom_mode == PX4_LOITER) is not None
        time.sleep(1.0)
        p, _, _ = stack.state()
        height = float(p_ground[2] - p[2])
        texts = _statustexts(gcs)
        print(f"open-loop take-off: odometry from {odom.valid_since_height_m:.2f} m (truth); LOITER at "
              f"{height:.2f} m for 1.2 m commanded; {texts}")
        assert odom.valid_since_height_m is not None
        # the blind climb's estimate at the hand-over (the bridge's "Odometry at X m"; the odometry is anchored to
        # it): with the board's baro filter modelled, 0.00-0.09 m below the truth (8 runs: 0.00-0.02 in 5, 0.07-0.09
        # in 3, a baro that read 0.03-0.12 m low as the motors spun up), the take-off ending at 1.20-1.30 m; fused
        # as if it were the height, 0.06-0.10 m below in every run (3) and the take-off ending at 1.27-1.31 m
        handover = [float(t.split("Odometry at ")[1].split(" m")[0]) for t in texts if t.startswith("Odometry at ")]
        assert handover and abs(handover[0] - odom.valid_since_height_m) < 0.15, (handover, texts)
        assert height == pytest.approx(1.2, abs=0.2)
        assert not any("Odometry lost" in t or "No odometry" in t for t in texts), texts
        _land(gcs)
    except Exception:   # a failed assertion; not Ctrl-C or a timeout, which should not wait for a landing
        _land_after_failure(gcs)
        raise
    finally:
        odom.stop.set()
        gcs.close()


def test_odometry_lost_at_lift_off_does_not_carry_the_climb_past_the_takeoff_height(stack):
    """The RealSense SITL flight's case (CI): BRG_ODOM_LOSS_T 2 s (as the flight harness sets it), odometry that
    stopped 1 s before the take-off (stale, not yet lost) and is back 0.2 m up. The take-off must end near its
    height and stay there: a closed loop on the stale odometry's frozen velocity once climbed 0.33 m past it at
    0.8 m/s."""
    gcs = Gcs(stack.gcs_port)
    lost = threading.Event()
    odom = GatedOdometry(stack, gcs, valid_above_m=0.2, lost_from=lost)
    peak: PeakHeight | None = None
    try:
        assert gcs.recv("HEARTBEAT", 20.0) is not None
        gcs.send(gcs.encoder.param_set_encode(1, 1, b"BRG_ODOM_LOSS_T", 2.0, mavlink.MAV_PARAM_TYPE_REAL32))
        assert gcs.recv("PARAM_VALUE", 5.0, lambda m: m.param_id == "BRG_ODOM_LOSS_T" and m.param_value == 2.0)
        wait_for(lambda: stack.truth_count > 10, 10.0, "truth")
        odom.start()
        time.sleep(1.0)
        p_ground, _, _ = stack.state()
        peak = PeakHeight(stack, float(p_ground[2]))
        peak.start()
        assert gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mavlink.MAV_RESULT_ACCEPTED
        assert gcs.recv("HEARTBEAT", 15.0, lambda m: m.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED) is not None
        lost.set()   # 1 s before the take-off: not yet lost (BRG_ODOM_LOSS_T 2 s), but stale
        time.sleep(1.0)
        assert gcs.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, math.nan, math.nan, 1.0) \
            == mavlink.MAV_RESULT_ACCEPTED
        assert gcs.recv("HEARTBEAT", 25.0, lambda m: m.custom_mode == PX4_LOITER) is not None
        time.sleep(4.0)
        p, _, _ = stack.state()
        height = float(p_ground[2] - p[2])
        texts = _statustexts(gcs)
        print(f"odometry lost at lift-off, back at {odom.valid_since_height_m}: top {peak.top_m:.2f} m, "
              f"{height:.2f} m 4 s after LOITER, for 1.0 m; {texts}")
        assert any("open loop" in t for t in texts) and any("closed loop" in t for t in texts), texts
        # on the board's own attitude (issue 29) the peak measured 1.10-1.17 m, and 1.21 m in CI, while the height
        # was anchored to the accelerometer's climb when the odometry came back (0.04 m at 0.20 m up in CI). On the
        # ground anchor taken at arming: 1.01-1.03 m, three runs beside two busy cores. The bound is back at 0.15 m
        assert peak.top_m < 1.0 + 0.15, f"climbed to {peak.top_m:.2f} m for a 1.0 m take-off"
        assert height == pytest.approx(1.0, abs=0.15)
        _land(gcs)
    except Exception:   # a failed assertion; not Ctrl-C or a timeout, which should not wait for a landing
        _land_after_failure(gcs)
        raise
    finally:
        if peak is not None:
            peak.stop.set()
        odom.stop.set()
        gcs.send(gcs.encoder.param_set_encode(1, 1, b"BRG_ODOM_LOSS_T", 0.5, mavlink.MAV_PARAM_TYPE_REAL32))
        gcs.recv("PARAM_VALUE", 5.0, lambda m: m.param_id == "BRG_ODOM_LOSS_T")
        gcs.close()


def test_takeoff_with_no_odometry_at_all_is_bounded_and_lands(stack):
    """The companion never gets odometry: the blind climb stops at BRG_TKO_OL_ALT (0.7 m estimated) and lands."""
    gcs = Gcs(stack.gcs_port)
    odom = GatedOdometry(stack, gcs, valid_above_m=None)
    peak: PeakHeight | None = None
    try:
        assert gcs.recv("HEARTBEAT", 20.0) is not None
        wait_for(lambda: stack.truth_count > 10, 10.0, "truth")
        odom.start()
        time.sleep(1.0)
        p_ground, _, _ = stack.state()
        peak = PeakHeight(stack, float(p_ground[2]))
        peak.start()
        assert gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mavlink.MAV_RESULT_ACCEPTED
        # wait for the armed heartbeat (board time may run slower than the wall clock), so a heartbeat from
        # before the arm cannot pass for the landing below
        assert gcs.recv("HEARTBEAT", 15.0, lambda m: m.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED) is not None
        assert gcs.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, math.nan, math.nan, 4.0) \
            == mavlink.MAV_RESULT_ACCEPTED
        texts: list[str] = []
        deadline = time.monotonic() + 60.0
        disarmed = None
        while disarmed is None and time.monotonic() < deadline:
            m = gcs.recv("HEARTBEAT", 1.0)
            if m is not None and not m.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED:
                disarmed = m
        texts = _statustexts(gcs)
        peak.stop.set()
        peak.join(timeout=2.0)
        p, _, _ = stack.state()
        print(f"no odometry: top {peak.top_m:.2f} m (bound 0.7 m estimated), landed at {p_ground[2] - p[2]:+.2f} m; "
              f"{texts}")
        assert disarmed is not None, "still armed after 60 s"
        assert any("No odometry in takeoff" in t for t in texts), texts
        assert 0.5 < peak.top_m <= 0.7 + 0.25
        assert abs(p[2] - p_ground[2]) < 0.15
    except Exception:   # a failed assertion; not Ctrl-C or a timeout, which should not wait for a landing
        _land_after_failure(gcs)
        raise
    finally:
        if peak is not None:
            peak.stop.set()
        odom.stop.set()
        gcs.close()


class TrajectorySetpoints(threading.Thread):
    """PX4-style position + velocity + acceleration setpoints (LOCAL_NED, yaw ignored) at 50 Hz along a line
    p_d(t) = p0 + v t (smooth start over ``ramp_s``: v_d = v s(t), a_d = v s'(t)), in simulated time."""

    MASK = mavlink.POSITION_TARGET_TYPEMASK_YAW_IGNORE | mavlink.POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE  # p, v, a

    def __init__(self, stack: Stack, gcs: Gcs, p0: np.ndarray) -> None:
        super().__init__(daemon=True)
        self.stack, self.gcs, self.p0 = stack, gcs, p0
        self.v = np.zeros(3)
        self.t0: float | None = None
        self.ramp_s = 2.0
        self.log: list[tuple[float, np.ndarray, np.ndarray]] = []  # (sim time, p_d, v_d)
        self.stop = threading.Event()

    def desired(self, t_sim: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if self.t0 is None:
            return self.p0, np.zeros(3), np.zeros(3)
        t, T = max(t_sim - self.t0, 0.0), self.ramp_s
        if t < T:  # s(t) = t^2/T - t^3/(3 T^2) integrated: smoothstep-like velocity ramp 0 -> v
            s, ds, dds = t ** 2 / T - t ** 3 / (3 * T ** 2), 2 * t / T - t ** 2 / T ** 2, 2 / T - 2 * t / T ** 2
        else:
            s, ds, dds = T - T / 3 + (t - T), 1.0, 0.0
        return self.p0 + self.v * s, self.v * ds, self.v * dds

    def run(self) -> None:
        while not self.stop.wait(0.02):
            t = self.stack.sim_time_s
            p, v, a = self.desired(t)
            self.log.append((t, p, v))
            self.gcs.send(self.gcs.encoder.set_position_target_local_ned_encode(
                0, 1, 1, mavlink.MAV_FRAME_LOCAL_NED, self.MASK, *p, *v, *a, 0, 0))


def test_geometric_tracker_flies_a_px4_trajectory_setpoint_stream(stack):
    """BRG_TRACKER = 1 set on the ground, take-off, then OFFBOARD on position + velocity + acceleration setpoints
    along a 0.5 m/s line: the SITL truth stays on the desired path (issue 19's wiring, over real links). Waits are
    long in wall time: lock-step runs several times slower than real time on a loaded machine."""
    gcs = Gcs(stack.gcs_port)
    odom = Odometry(stack, gcs)
    traj: TrajectorySetpoints | None = None
    try:
        assert gcs.recv("HEARTBEAT", 20.0) is not None
        gcs.send(gcs.encoder.param_set_encode(1, 1, b"BRG_TRACKER", 1.0, mavlink.MAV_PARAM_TYPE_REAL32))
        assert gcs.recv("PARAM_VALUE", 5.0, lambda m: m.param_id == "BRG_TRACKER" and m.param_value == 1.0)
        wait_for(lambda: stack.truth_count > 10, 10.0, "truth")
        odom.start()
        time.sleep(1.0)
        assert gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mavlink.MAV_RESULT_ACCEPTED
        assert gcs.command(mavlink.MAV_CMD_NAV_TAKEOFF, *([math.nan] * 7)) == mavlink.MAV_RESULT_ACCEPTED
        assert gcs.recv("HEARTBEAT", 60.0, lambda m: m.custom_mode == PX4_LOITER) is not None
        p0, _, _ = stack.state()
        traj = TrajectorySetpoints(stack, gcs, p0)
        traj.start()
        time.sleep(1.0)
        assert gcs.command(mavlink.MAV_CMD_DO_SET_MODE, 1, 6, 0) == mavlink.MAV_RESULT_ACCEPTED
        assert gcs.recv("HEARTBEAT", 15.0, lambda m: m.custom_mode == PX4_OFFBOARD) is not None, gcs.texts
        traj.v = np.array([0.5, 0.0, 0.0])
        traj.t0 = stack.sim_time_s
        errors_p, errors_v = [], []
        while stack.sim_time_s - traj.t0 < 8.0:
            time.sleep(0.05)
            p, v, _ = stack.state()
            p_d, v_d, _ = traj.desired(stack.sim_time_s)
            errors_p.append(p - p_d)
            errors_v.append(v - v_d)
        rmse_p = np.sqrt(np.mean(np.square(errors_p), axis=0))
        rmse_v = np.sqrt(np.mean(np.square(errors_v), axis=0))
        print(f"geometric tracker, 0.5 m/s line: position RMSE {rmse_p} m, velocity RMSE {rmse_v} m/s")
        p, _, _ = stack.state()
        assert p[0] - p0[0] > 2.5  # it flew the line (3.33 m desired after 8 s)
        assert np.all(rmse_p < 0.10), rmse_p
        assert np.all(rmse_v < 0.10), rmse_v
        traj.stop.set()
        assert gcs.command(mavlink.MAV_CMD_NAV_LAND) == mavlink.MAV_RESULT_ACCEPTED
        assert gcs.recv("HEARTBEAT", 90.0, lambda m: not m.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED) \
            is not None
    except Exception:   # a failed assertion; not Ctrl-C or a timeout, which should not wait for a landing
        _land_after_failure(gcs)
        raise
    finally:
        if traj is not None:
            traj.stop.set()
        odom.stop.set()
        gcs.close()

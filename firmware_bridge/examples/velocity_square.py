"""Fly a velocity square with MAVSDK through the bridge, and print what the SITL truth saw.

    quadlink sitl --lockstep --no-camera &
    quadlink bridge &
    python firmware_bridge/examples/velocity_square.py            # MAVSDK on udpin://127.0.0.1:14540

MAVSDK (the native 4.x binding) arms, takes off (MIS_TAKEOFF_ALT), starts OFFBOARD with
``set_velocity_body`` and flies forward, right, backward, left (``--speed`` m/s for ``--leg-s``
simulated seconds each), then lands. The bridge needs a velocity source: normally the companion's
ODOMETRY; without a companion, ``--truth-odometry`` (default on) turns the SITL's ground truth
(``udpin:127.0.0.1:14560``) into ODOMETRY sent to the bridge's ground-station endpoint
(``udpin:127.0.0.1:14550``) — a test aid, never for flight code. The truth corners are printed.
"""

from __future__ import annotations

import argparse
import asyncio
import math
import threading
import time

import numpy as np

from quadlink.frames import R_from_quat_wxyz, euler_from_R
from quadlink.mavlink import mavlink
from quadlink.mavlink.connection import open_mavlink


class TruthOdometry:
    """SITL truth -> ODOMETRY (LOCAL_FRD / BODY_FRD) at 30 Hz to the bridge; also the truth for the report."""

    def __init__(self, truth_url: str, bridge_url: str | None) -> None:
        self.truth = open_mavlink(truth_url, 255, 191)
        self.bridge = open_mavlink(bridge_url, 255, 192) if bridge_url else None
        self.encoder = mavlink.MAVLink(None, 255, 192)
        self.lock = threading.Lock()
        self.p = np.zeros(3)
        self.v = np.zeros(3)
        self.q = np.array([1.0, 0.0, 0.0, 0.0])
        self.sim_time_s = 0.0
        self.stop = threading.Event()
        self.threads = [threading.Thread(target=self._read, daemon=True)]
        if self.bridge is not None:
            self.threads += [threading.Thread(target=self._read_bridge, daemon=True),
                             threading.Thread(target=self._send, daemon=True)]
        for t in self.threads:
            t.start()

    def _read(self) -> None:
        while not self.stop.is_set():
            m = self.truth.recv_match(type=["LOCAL_POSITION_NED", "ATTITUDE_QUATERNION"], blocking=True, timeout=0.2)
            if m is None:
                continue
            with self.lock:
                if m.get_type() == "LOCAL_POSITION_NED":
                    self.p, self.v = np.array([m.x, m.y, m.z]), np.array([m.vx, m.vy, m.vz])
                    self.sim_time_s = m.time_boot_ms * 1e-3
                else:
                    self.q = np.array([m.q1, m.q2, m.q3, m.q4])

    def _read_bridge(self) -> None:
        assert self.bridge is not None
        while not self.stop.is_set():  # learn the bridge's address (and drop its telemetry)
            self.bridge.recv_match(blocking=True, timeout=0.2)

    def _send(self) -> None:
        assert self.bridge is not None
        while not self.stop.wait(1.0 / 30.0):
            with self.lock:
                p, v, q = self.p.copy(), self.v.copy(), self.q.copy()
            v_q = R_from_quat_wxyz(q).T @ v
            msg = self.encoder.odometry_encode(int(time.monotonic() * 1e6), mavlink.MAV_FRAME_LOCAL_FRD,
                                               mavlink.MAV_FRAME_BODY_FRD, float(p[0]), float(p[1]), float(p[2]),
                                               [float(x) for x in q], float(v_q[0]), float(v_q[1]),
                                               float(v_q[2]), 0, 0, 0,
                                               [math.nan] * 21, [math.nan] * 21, 0, 0, 100)
            buf = msg.pack(self.encoder)
            self.encoder.seq = (self.encoder.seq + 1) % 256
            for address in list(self.bridge.clients):
                self.bridge.port.sendto(buf, address)

    def state(self) -> tuple[np.ndarray, np.ndarray, float]:
        with self.lock:
            return self.p.copy(), self.q.copy(), self.sim_time_s

    def close(self) -> None:
        self.stop.set()
        for t in self.threads:
            t.join(timeout=2.0)
        self.truth.close()
        if self.bridge is not None:
            self.bridge.close()


async def fly(args: argparse.Namespace, truth: TruthOdometry) -> None:
    from mavsdk.asyncio import ComponentType, Configuration, Mavsdk
    from mavsdk.asyncio.plugins.action.action import ActionAsync
    from mavsdk.asyncio.plugins.offboard.offboard import OffboardAsync, VelocityBodyYawspeed
    from mavsdk.asyncio.plugins.telemetry.telemetry import FlightMode, TelemetryAsync

    async def until(gen, pred, timeout_s: float):
        async def scan():
            async for value in gen:
                if pred(value):
                    return value
        return await asyncio.wait_for(scan(), timeout_s)

    config = Configuration.create_with_component_type(ComponentType.GROUND_STATION)
    async with Mavsdk(config) as sdk:
        await sdk.add_any_connection(args.mavsdk_url)
        system = await sdk.first_autopilot(timeout_s=20.0)
        if system is None:
            raise SystemExit(f"no autopilot on {args.mavsdk_url} (is quadlink bridge running?)")
        telemetry, action, offboard = TelemetryAsync(system), ActionAsync(system), OffboardAsync(system)
        print("connected; arming")
        await action.arm()
        await until(telemetry.subscribe_armed(), bool, 5.0)
        await action.takeoff()
        await until(telemetry.subscribe_flight_mode(), lambda m: m == FlightMode.HOLD, 30.0)
        print(f"took off: truth height {-truth.state()[0][2]:.2f} m")
        await offboard.set_velocity_body(VelocityBodyYawspeed(0.0, 0.0, 0.0, 0.0))
        await offboard.start()
        p0, q0, _ = truth.state()
        yaw = euler_from_R(R_from_quat_wxyz(q0))[2]
        corners = [p0]
        for name, forward, right in (("forward", 1, 0), ("right", 0, 1), ("backward", -1, 0), ("left", 0, -1)):
            _, _, t0 = truth.state()
            await offboard.set_velocity_body(VelocityBodyYawspeed(forward * args.speed, right * args.speed, 0.0, 0.0))
            while truth.state()[2] - t0 < args.leg_s:
                await asyncio.sleep(0.05)
            corners.append(truth.state()[0])
            print(f"  {name:8s} leg done at truth N {corners[-1][0]:+.2f} E {corners[-1][1]:+.2f} "
                  f"D {corners[-1][2]:+.2f} m")
        await offboard.set_velocity_body(VelocityBodyYawspeed(0.0, 0.0, 0.0, 0.0))
        await asyncio.sleep(1.5)
        end = truth.state()[0]
        await offboard.stop()
        await action.land()
        await until(telemetry.subscribe_armed(), lambda armed: not armed, 40.0)
        c = np.array(corners)[:, :2]
        legs = np.linalg.norm(np.diff(c, axis=0), axis=1)
        print(f"landed. heading {math.degrees(yaw):.0f} deg; legs {np.round(legs, 2)} m "
              f"(commanded {args.speed * args.leg_s:.2f} m); closure {np.linalg.norm(end[:2] - c[0]):.2f} m")


def main() -> None:
    parser = argparse.ArgumentParser(description="Fly a velocity square through the bridge with MAVSDK.")
    parser.add_argument("--mavsdk-url", default="udpin://127.0.0.1:14540")
    parser.add_argument("--speed", type=float, default=0.5, help="m/s")
    parser.add_argument("--leg-s", type=float, default=4.0, help="simulated seconds per leg")
    parser.add_argument("--truth", default="udpin:127.0.0.1:14560", help="SITL ground-truth endpoint")
    parser.add_argument("--odometry-to", default="udpin:127.0.0.1:14550",
                        help="bridge endpoint to send truth ODOMETRY to ('none' when the companion runs)")
    args = parser.parse_args()
    truth = TruthOdometry(args.truth, None if args.odometry_to == "none" else args.odometry_to)
    try:
        asyncio.run(fly(args, truth))
    finally:
        truth.close()


if __name__ == "__main__":
    main()

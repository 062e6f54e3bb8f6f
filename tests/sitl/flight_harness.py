"""A reusable SITL flight harness for the safety layer (issue 14): start SITL + bridge + companion, fly
the vehicle from a pymavlink ground station through the companion's ground-station endpoint, and
measure the *true* clearance to every non-floor surface from the SITL truth stream and the scenario's
geometry (independently of the flight code: the clearance is computed here from the scene bodies).

Importable by the SITL tests (``from flight_harness import ...``) and runnable as a script::

    PYTHONPATH=. python tests/flight_harness.py push --x 700 --seconds 30 --offset 4000 [--realtime]
    PYTHONPATH=. python tests/flight_harness.py climb --seconds 15 --offset 4100

Geometry: the truth's LOCAL_POSITION_NED is relative to the start position (arena NED, not rotated),
so the arena position is ``start + p_local``. Distances are from the centre of mass (as paper 000's
Fig. 8) to the walls' and ceiling's inner faces and to the objects (yawed boxes, upright cylinders).
"""

from __future__ import annotations

import argparse
import contextlib
import math
import socket
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from mavsdk_classic import MavsdkServer, mavsdk_server  # noqa: F401 - re-exported for the flight tests
from numpy.typing import NDArray

from harness.cpu_share import CpuShare
from harness.demo.parts import BridgePart, CompanionPart, SitlPart
from harness.judge import ArenaGeometry, Clearance
from harness.ports import Ports, free_port_offset
from quadlink.frames import euler_from_quat_wxyz
from quadlink.ids import COMPANION_COMPONENT_ID, GROUND_COMPONENT_ID, GROUND_SYSTEM_ID, TRUTH_SENSOR_NON_FLOOR
from quadlink.mavlink import mavlink
from quadlink.mavlink.statustext import StatusTextAssembler

COMPANION_COMPID = COMPANION_COMPONENT_ID
# A process starved for 0.5 s on a loaded 2-core machine reads as a lost operator or ground station (wall
# clock): these flights test the safety layer, not the link timeouts (the arbiter's are unit-tested).
LOADED_MACHINE: dict[str, dict[str, object]] = {"modes": {"gcs_timeout_s": 2.0},
                                                "arbiter": {"operator_timeout_s": 2.0, "script_timeout_s": 2.0}}
MODE_TELEOP = mavlink.QUADLINK_TELEOP_MODE_TELEOP
MODE_HOLD = mavlink.QUADLINK_TELEOP_MODE_HOLD


# ---------------------------------------------------------------- the flight
@dataclass
class TruthSample:
    t_s: float
    p_arena_ned_m: NDArray[np.float64]
    yaw_rad: float
    clearance: Clearance
    mode: int
    sim_obstacle_m: float   # the SITL's own DISTANCE_SENSOR id 1 (objects and walls, pybullet)
    v_ned_m_s: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))   # true velocity


@dataclass
class FlightLog:
    samples: list[TruthSample] = field(default_factory=list)
    modes: list[tuple[float, int]] = field(default_factory=list)
    statustexts: list[str] = field(default_factory=list)
    acks: list[tuple[int, int, int]] = field(default_factory=list)   # (command, result, source compid)

    def flying(self, min_height_m: float = 0.3) -> list[TruthSample]:
        """The samples in the air (for mobility: how high, how far); never for clearance."""
        return [s for s in self.samples if s.clearance.floor_m > min_height_m]

    def min_surface(self, since_s: float = -math.inf) -> TruthSample | None:
        """The sample nearest a non-floor surface over the whole flight from ``since_s``, take-off and touchdown
        included (harness.judge: one judge, no blind spot)."""
        fl = [s for s in self.samples if s.t_s >= since_s]
        return min(fl, key=lambda s: s.clearance.surface_m) if fl else None

    def touchdown(self, since_s: float, floor_m: float = 0.12) -> tuple[float, float] | None:
        """(time, vertical speed in m/s) at the first truth sample after ``since_s`` with the centre of mass within
        ``floor_m`` of the floor (the body's half height is 0.10 m): the landing's impact speed, the fastest of
        the last 0.2 s before it. None if it never came down."""
        after = [s for s in self.samples if s.t_s >= since_s]
        for k, s in enumerate(after):
            if s.clearance.floor_m <= floor_m:
                before = [x for x in after[:k + 1] if x.t_s >= s.t_s - 0.2]
                return s.t_s, max(float(x.v_ned_m_s[2]) for x in before)
        return None

    def summary(self, since_s: float = -math.inf) -> str:
        s = self.min_surface(since_s)
        if s is None:
            return "never flew"
        c = s.clearance
        x, y, z = s.p_arena_ned_m
        return (f"min clearance {c.surface_m:.3f} m ({c.nearest_name}) at t={s.t_s:.1f} s, p=({x:.2f}, "
                f"{y:.2f}, {z:.2f}), mode {s.mode}; walls {c.wall_m:.3f} objects "
                f"{c.object_m:.3f} ceiling {c.ceiling_m:.3f}; min wall/object/ceiling over the flight "
                f"{min(x.clearance.wall_m for x in self.samples):.3f}/"
                f"{min(x.clearance.object_m for x in self.samples):.3f}/"
                f"{min(x.clearance.ceiling_m for x in self.samples):.3f}")

    def save_csv(self, path: Path) -> None:
        rows = [(s.t_s, *s.p_arena_ned_m, s.yaw_rad, s.clearance.wall_m, s.clearance.object_m, s.clearance.ceiling_m,
                 s.sim_obstacle_m, s.mode) for s in self.samples]
        np.savetxt(path, np.asarray(rows).reshape(-1, 10), delimiter=",",
                   header="t_s,x_m,y_m,z_m,yaw_rad,wall_m,object_m,ceiling_m,sim_obstacle_m,mode")


def _wait_tcp(port: int, check: Callable[[], object], timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        check()
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.5):
                return
        except OSError:
            time.sleep(0.5)
    raise TimeoutError(f"nothing listening on port {port} after {timeout_s:.0f} s")


# ---------------------------------------------------------------- the vehicle's processes (every SITL test's)
class Vehicle:
    """The vehicle's processes -- the SITL, and the bridge and the companion if asked, from the parts every flight
    starts from (:mod:`harness.demo.parts`) -- on the demo's ports shifted by ``offset`` (None: a free offset,
    :func:`harness.ports.free_port_offset`), in one :class:`harness.demo.orchestrator.Stack` (logs in
    ``out_dir/logs``, each part in its own process group, stopped in reverse order). Each part starts once the one
    before listens. ``bridge_params``: the bridge's parameter file's text (``out_dir/bridge_params.yaml``; the bridge
    writes PARAM_SETs back to it). A part that fails to start leaves nothing running. ``cpu_share``: the bridge and
    the companion run in this CPU share (:mod:`harness.cpu_share`)."""

    def __init__(self, out_dir: Path, sitl: SitlPart, bridge: BridgePart | None,
                 companion: CompanionPart | None = None, offset: int | None = None, bridge_params: str = "",
                 cpu_share: CpuShare | None = None) -> None:
        from harness.demo.orchestrator import Stack

        out_dir.mkdir(parents=True, exist_ok=True)
        self.out_dir = out_dir
        self.ports = Ports(free_port_offset() if offset is None else offset)
        self.stack = Stack(out_dir / "logs")
        self.params_file = out_dir / "bridge_params.yaml"
        self.cpu_share = cpu_share
        try:
            self._start_sitl(sitl)
            if bridge is not None:
                self.params_file.write_text(bridge_params)
                self._start_part(replace(bridge, params=self.params_file).spec(self.ports))
            if companion is not None:
                self.start_companion(companion)
        except BaseException:
            self.close()
            raise

    def _start_sitl(self, part: SitlPart) -> None:
        p = self.ports
        self.stack.start(part.spec(p))
        # the SITL's start-up is slow on a loaded machine (pybullet, the scene, simavr)
        _wait_tcp(p.mk1, self.stack.check, 120.0)
        _wait_tcp(p.mk2, self.stack.check, 60.0)
        if part.camera:
            _wait_tcp(p.camera, self.stack.check, 60.0)

    def start_companion(self, part: CompanionPart) -> None:
        """The companion (its tlog in ``out_dir/companion.tlog`` unless the part names one)."""
        if part.tlog is None:
            part = replace(part, tlog=self.out_dir / "companion.tlog")
        self._start_part(part.spec(self.ports))

    def _start_part(self, spec: Any) -> None:
        self.stack.start(spec)
        if self.cpu_share is not None:
            self.cpu_share.add(self.stack.running[-1].popen.pid)

    def check(self) -> None:
        """Raise if a part has died (its log's tail in the message)."""
        self.stack.check()

    def close(self) -> None:
        import signal as signals

        for r in self.stack.running:   # a stalled part must be able to stop
            with contextlib.suppress(OSError):
                r.popen.send_signal(signals.SIGCONT)
        self.stack.stop()


class TruthReader:
    """The SITL's truth stream read in a thread (for tests that fly from their own thread): the latest position,
    velocity and attitude, the simulated time and how many positions came."""

    def __init__(self, port: int) -> None:
        import threading

        from quadlink.mavlink.connection import open_mavlink

        self.truth = open_mavlink(f"udpin:127.0.0.1:{port}", 255, 0)
        self.lock = threading.Lock()
        self.p_ned, self.v_ned = np.zeros(3), np.zeros(3)
        self.q_wxyz = np.array([1.0, 0.0, 0.0, 0.0])
        self.truth_count = 0
        self.sim_time_s = 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._read, daemon=True, name="truth-reader")
        self._thread.start()

    def _read(self) -> None:
        while not self._stop.is_set():
            m = self.truth.recv_match(type=["LOCAL_POSITION_NED", "ATTITUDE_QUATERNION"], blocking=True,
                                      timeout=0.2)
            if m is None:
                continue
            with self.lock:
                if m.get_type() == "LOCAL_POSITION_NED":
                    self.p_ned, self.v_ned = np.array([m.x, m.y, m.z]), np.array([m.vx, m.vy, m.vz])
                    self.sim_time_s = m.time_boot_ms * 1e-3
                    self.truth_count += 1
                else:
                    self.q_wxyz = np.array([m.q1, m.q2, m.q3, m.q4])

    def state(self) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """(position NED, velocity NED, attitude quaternion wxyz), the latest."""
        with self.lock:
            return self.p_ned.copy(), self.v_ned.copy(), self.q_wxyz.copy()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self.truth.close()


class Flight:
    """A running stack and a ground station on the companion's endpoint. Use :func:`flight`."""

    def __init__(self, out_dir: Path, scenario: str, offset: int, lockstep: bool,
                 companion_config: Path | None, sitl_duration_s: float, camera: str = "tcp://127.0.0.1:{port}",
                 shipped_timeouts: bool = False, cpu_share: CpuShare | None = None, journal: bool = False,
                 sitl_config: Path | None = None) -> None:
        from quadlink.mavlink.connection import open_mavlink

        self.out_dir = out_dir
        out_dir.mkdir(parents=True, exist_ok=True)
        self.geometry = ArenaGeometry(scenario)
        self.ports = p = Ports(offset)
        self.lockstep = lockstep
        self.truth = open_mavlink(f"udpin:127.0.0.1:{p.truth}", 255, 0)
        self.gcs = open_mavlink(f"udpout:127.0.0.1:{p.vehicle}", GROUND_SYSTEM_ID, GROUND_COMPONENT_ID)
        self.log = FlightLog()
        self._statustexts = StatusTextAssembler()
        self.t_s = 0.0
        self.p_arena = self.geometry.start_ned_m.copy()
        self.yaw_rad = math.radians(self.geometry.scenario.start.yaw_deg)
        self.mode = 0
        self.flags = 0
        self.armed = False
        self.sim_obstacle_m = math.inf
        self._last_hb = 0.0
        # the vehicle rests on the floor with its centre half its collision box above it: the truth's local
        # z starts there (the start is on the floor in the scenarios used here)
        from sim_sitl.config import load_sitl_config
        self._rest_z = -load_sitl_config().physics.body_size_m[2] / 2.0
        # the bridge's and the companion's timeouts: as tests/test_companion_sitl.py, a loaded machine can stall
        # the lock-step IMU stream longer than the bridge's 0.5 s board-loss timeout; these flights are about the
        # companion (likewise its odometry-loss timeout: a starved companion stalls the odometry stream).
        # ``shipped_timeouts``: the bridge's and the companion's own values, as a user flies them (issue 29)
        relaxed = "" if shipped_timeouts else "BRG_BOARD_LOSS_T: 3.0\nBRG_ODOM_LOSS_T: 2.0\n"
        if companion_config is None:
            companion_config = companion_config_with(out_dir, **({} if shipped_timeouts else LOADED_MACHINE))
        try:   # a part that fails to start must not leave the others running or the sockets open
            self.vehicle = Vehicle(out_dir,
                                   SitlPart(scenario, lockstep, duration_s=sitl_duration_s, ready_after_s=2.0,
                                            config=None if sitl_config is None else str(sitl_config)),
                                   BridgePart(ready_after_s=1.0),
                                   CompanionPart(companion_config, camera=camera, ready_after_s=1.0,
                                                 journal=out_dir / "companion.qljn" if journal else None),
                                   offset=offset, bridge_params=relaxed, cpu_share=cpu_share)
        except BaseException:
            self.truth.close()
            self.gcs.close()
            raise
        self.stack = self.vehicle.stack

    # --- I/O
    def pump(self) -> None:
        while (m := self.truth.recv_msg()) is not None:
            kind = m.get_type()
            if kind == "LOCAL_POSITION_NED":
                self.t_s = m.time_boot_ms / 1e3
                self.p_arena = self.geometry.start_ned_m + np.array([m.x, m.y, m.z])
                # the start position is the vehicle's resting height: the truth's z is relative to it
                self.p_arena[2] += self._rest_z
                self.log.samples.append(TruthSample(self.t_s, self.p_arena.copy(), self.yaw_rad,
                                                    self.geometry.clearance(self.p_arena), self.mode,
                                                    self.sim_obstacle_m, np.array([m.vx, m.vy, m.vz])))
            elif kind == "ATTITUDE_QUATERNION":
                self.yaw_rad = euler_from_quat_wxyz([m.q1, m.q2, m.q3, m.q4])[2]
            elif kind == "DISTANCE_SENSOR" and m.id == TRUTH_SENSOR_NON_FLOOR:
                self.sim_obstacle_m = m.current_distance / 100.0
        while (m := self.gcs.recv_msg()) is not None:
            kind = m.get_type()
            if kind == "TELEOP_FEEDBACK":
                if not self.log.modes or self.log.modes[-1][1] != m.mode:
                    self.log.modes.append((m.time_usec / 1e6, m.mode))
                self.mode, self.flags = m.mode, m.flags
            elif kind == "HEARTBEAT" and m.get_srcComponent() == 1:
                self.armed = bool(m.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
            elif kind == "STATUSTEXT" and (text := self._statustexts.add(m)) is not None:
                self.log.statustexts.append(f"{self.t_s:.1f} {text}")
            elif kind == "COMMAND_ACK":
                self.log.acks.append((m.command, m.result, m.get_srcComponent()))


    def heartbeat(self) -> None:
        if time.monotonic() - self._last_hb > 1.0:
            self._last_hb = time.monotonic()
            self.gcs.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)

    def manual(self, x: int, y: int = 0, z: int = 500) -> None:
        self.gcs.mav.manual_control_send(1, x, y, z, 0, 0)

    def run_for(self, sim_s: float, control: Callable[[], None] | None, until: Callable[[], bool] | None = None,
                wall_s: float = 600.0, period_s: float = 0.02) -> None:
        """Call ``control`` every ``period_s`` (wall) for ``sim_s`` simulated seconds (or until ``until``)."""
        t_end_wall = time.monotonic() + wall_s
        t_end_sim: float | None = None
        while time.monotonic() < t_end_wall:
            self.stack.check()
            self.pump()
            if t_end_sim is None and self.t_s > 0:
                t_end_sim = self.t_s + sim_s
            if t_end_sim is not None and self.t_s >= t_end_sim:
                return
            if until is not None and until():
                return
            self.heartbeat()
            if control is not None:
                control()
            time.sleep(period_s)

    def take_off(self) -> None:
        """Wait for perception, take off through the companion (compid 191), wait for TELEOP."""
        hold = lambda: self.manual(0)  # noqa: E731
        self.run_for(2.0, hold)
        self.run_for(30.0, hold, until=lambda: bool(self.flags & 8))  # camera frames fresh
        self.run_for(1.0, hold)
        self.gcs.mav.command_long_send(1, COMPANION_COMPID, mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 0, 1.0)
        self.run_for(30.0, hold, until=lambda: self.mode == MODE_TELEOP and self.p_arena[2] < -0.7)
        if self.mode != MODE_TELEOP:
            raise AssertionError(f"companion not in teleop after takeoff (mode {self.mode}); "
                                 f"status: {self.log.statustexts[-5:]}")

    def signal_part(self, name: str, sig: int) -> None:
        """Send a part of the stack a signal (SIGKILL: it is gone and no longer checked; SIGSTOP: it stalls)."""
        import signal as signals

        r = next(r for r in self.stack.running if r.spec.name == name)
        r.popen.send_signal(sig)
        if sig == signals.SIGKILL:
            r.popen.wait(10.0)
            self.stack.running.remove(r)

    def close(self) -> None:
        try:
            self.vehicle.close()
        finally:
            self.truth.close()
            self.gcs.close()


@contextlib.contextmanager
def flight(out_dir: Path, scenario: str = "paper-arena", offset: int | None = None, lockstep: bool = True,
           companion_config: Path | None = None, sitl_duration_s: float = 400.0,
           camera: str = "tcp://127.0.0.1:{port}", shipped_timeouts: bool = False,
           cpu_share: CpuShare | None = None, journal: bool = False,
           sitl_config: Path | None = None) -> Iterator[Flight]:
    """A flight on the demo's ports shifted by ``offset`` (None: a free one, :func:`harness.ports.free_port_offset`);
    ``camera``: the companion's camera URL, ``{port}`` the SITL's camera stream port;
    ``shipped_timeouts``: the failsafe timeouts as shipped (else the loaded-machine margins, and the test says why);
    ``cpu_share``: the bridge and the companion run in this CPU share (harness.cpu_share); ``journal``: the companion
    journals its inputs to ``out_dir/companion.qljn`` (~12 MB/s); ``sitl_config``: the SITL's configuration file
    (None: configs/sitl.yaml; ``scenario`` still names the arena)."""
    f = Flight(out_dir, scenario, free_port_offset() if offset is None else offset, lockstep, companion_config,
               sitl_duration_s, camera, shipped_timeouts, cpu_share, journal, sitl_config)
    try:
        yield f
    finally:
        f.close()
        with contextlib.suppress(OSError):
            f.log.save_csv(out_dir / "truth_clearance.csv")


def companion_config_with(out_dir: Path, **sections: object) -> Path:
    """configs/companion.yaml with some keys replaced, in ``out_dir`` (the demo's writer)."""
    from harness.demo.cli import write_companion_config

    return write_companion_config(out_dir, **sections)


# ---------------------------------------------------------------- client scripts beside the flight
async def connect_classic(server: MavsdkServer, timeout_s: float = 60.0) -> Any:
    """A classic-API ``System`` connected to ``server`` (:func:`mavsdk_server`), which it starts.

    The server opens its gRPC port only once it has discovered the vehicle, and a gRPC channel that meets a closed
    port backs off before it tries again (1 s, x1.6 per failure, up to 120 s): a ``connect()`` begun before the
    discovery could still be waiting when its budget ran out although the server had long been listening (CI twice,
    on ``e9ba20b`` and ``ff7c74e``: stuck in connect, the server's log showing the vehicle discovered). So first
    wait here for the port to accept a connection, then connect: the channel's first try succeeds."""
    import asyncio

    from mavsdk_grpc import System

    server.start()
    port = server.port
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            _, writer = await asyncio.open_connection("127.0.0.1", port)
        except OSError:
            if time.monotonic() > deadline:
                raise TimeoutError(f"mavsdk_server's gRPC port {port} not open after {timeout_s:.0f} s") from None
            await asyncio.sleep(0.1)
            continue
        writer.close()
        with contextlib.suppress(OSError):
            await writer.wait_closed()
        break
    drone = System(mavsdk_server_address="127.0.0.1", port=port)
    await asyncio.wait_for(drone.connect(), max(1.0, deadline - time.monotonic()))
    return drone


class ClientScript:
    """A ground-station script (MAVSDK, either API) in its own thread and event loop while the harness flies on.

    The script names its steps (``script.step("takeoff")``); a step that lasts longer than ``step_budget_sim_s`` of
    simulated time (or ``step_budget_wall_s`` of wall time, should the simulation stall) fails the test with the
    step's name, the steps so far and the tails of ``logs`` -- rather than a hung call outliving the SITL.
    """

    def __init__(self, f: Flight, step_budget_sim_s: float = 60.0, step_budget_wall_s: float = 240.0,
                 logs: tuple[Path, ...] = ()) -> None:
        self.f = f
        self.step_budget_sim_s = step_budget_sim_s
        self.step_budget_wall_s = step_budget_wall_s
        self.logs = logs
        self.steps: list[tuple[float, str]] = []
        self._began_sim_s: float | None = None
        self._began_wall_s = time.monotonic()

    def step(self, name: str) -> None:
        self.steps.append((self.f.t_s, name))
        # before the harness has heard the SITL's clock (t = 0) the step's start is taken at the first reading: CI
        # once counted the simulated time the SITL had run before the script began as the step's (60 s in 29 s)
        self._began_sim_s = self.f.t_s if self.f.t_s > 0.0 else None
        self._began_wall_s = time.monotonic()

    async def sim_wait(self, seconds: float) -> None:
        import asyncio

        t0 = self.f.t_s
        while self.f.t_s - t0 < seconds:
            await asyncio.sleep(0.05)

    def run(self, script: Callable[[ClientScript], object], control: Callable[[], None] | None = None) -> None:
        """Run ``script(self)`` (a coroutine function) to its end; the harness's ``control`` every step meanwhile.
        Re-raises what the script raised."""
        import asyncio
        import threading

        outcome: dict[str, BaseException] = {}

        def target() -> None:
            try:
                asyncio.run(script(self))  # type: ignore[arg-type]
            except BaseException as exc:  # reported to the test thread
                outcome["error"] = exc

        self.f.pump()
        self.step("start")
        thread = threading.Thread(target=target, daemon=True, name="client-script")
        thread.start()
        while thread.is_alive():
            self.f.run_for(0.5, control, wall_s=1.0)
            if self._began_sim_s is None and self.f.t_s > 0.0:
                self._began_sim_s = self.f.t_s
            stuck_sim_s = 0.0 if self._began_sim_s is None else self.f.t_s - self._began_sim_s
            stuck_wall_s = time.monotonic() - self._began_wall_s
            if stuck_sim_s > self.step_budget_sim_s or stuck_wall_s > self.step_budget_wall_s:
                raise AssertionError(f"client script stuck in step {self.steps[-1][1]!r} for {stuck_sim_s:.0f} s "
                                     f"simulated ({stuck_wall_s:.0f} s wall); {self._report()}")
        if "error" in outcome:
            raise AssertionError(f"client script failed in step {self.steps[-1][1]!r}: {outcome['error']!r}; "
                                 f"{self._report()}") from outcome["error"]

    def _report(self) -> str:
        steps = ", ".join(f"{t:.1f} {name}" for t, name in self.steps)
        tails = []
        for path in self.logs:
            with contextlib.suppress(OSError):
                lines = path.read_text(errors="replace").splitlines()[-8:]
                tails.append(f"{path.name}: " + " | ".join(lines))
        return f"steps: {steps}; status: {self.f.log.statustexts[-6:]}; " + "; ".join(tails)


# ---------------------------------------------------------------- command line
def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("case", choices=["push", "climb"])
    ap.add_argument("--x", type=int, default=700, help="MANUAL_CONTROL x while pushing")
    ap.add_argument("--y", type=int, default=0)
    ap.add_argument("--z", type=int, default=500)
    ap.add_argument("--seconds", type=float, default=30.0)
    ap.add_argument("--offset", type=int, default=4000)
    ap.add_argument("--scenario", default="paper-arena")
    ap.add_argument("--realtime", action="store_true")
    ap.add_argument("--config", type=Path, default=None, help="companion config YAML")
    ap.add_argument("--room-height", type=float, default=None, help="companion reference.room_height_m "
                    "(and no max_height_m fence)")
    ap.add_argument("--out", type=Path, default=Path("/tmp/safety-flight"))
    a = ap.parse_args(argv)
    import logging

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    import signal

    def _stop(signum: int, frame: object) -> None:   # SIGTERM: stop the stack in the finally blocks
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, _stop)
    config = a.config
    if a.room_height is not None:
        config = companion_config_with(a.out, reference={"room_height_m": a.room_height, "max_height_m": None},
                                       **LOADED_MACHINE)
    with flight(a.out, a.scenario, a.offset, not a.realtime, config) as f:
        f.take_off()
        t0 = f.t_s
        if a.case == "push":
            f.run_for(a.seconds, lambda: f.manual(a.x, a.y, a.z))
        else:
            f.run_for(a.seconds, lambda: f.manual(0, 0, 1000))
        f.run_for(2.0, lambda: f.manual(0))
        print(f"{a.case} x={a.x} y={a.y} z={a.z} {a.seconds:.0f} s {'real time' if a.realtime else 'lock-step'}: "
              f"{f.log.summary(t0)}")
        print("modes:", f.log.modes[:12], "..." if len(f.log.modes) > 12 else "")
        print("\n".join(f.log.statustexts[-10:]))
    return 0


if __name__ == "__main__":
    sys.exit(main())

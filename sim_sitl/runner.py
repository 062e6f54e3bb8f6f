"""``Sitl``: wires the simulated vehicle to its ports and to the wall clock (one owner of time per process).

One thread runs the simulation. Per board tick (2 ms of sim time, :meth:`Sitl._step` on the tick's
result) it queues the IMU frame on port 2's serial line and the due telemetry on port 1's, renders and
publishes the camera when due, sends ground truth when due and drains the serial lines to the clients
(:mod:`sim_sitl.ports`). Between chunks it waits as :mod:`sim_sitl.pacing` decides: real time (``speed``
x the injected wall clock) or, in lock-step, for one setpoint per 10 ms chunk while a port-1 client is
sending them and for the camera clients' ack of each frame. Every wait keeps serving the serial ports
(new clients, setpoints, requests, slow clients' backlogs) and is bounded by ``lockstep_timeout_s``.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from quadlink.camera import CameraStreamServer
from quadlink.frames import euler_from_R
from quadlink.mk.flags import BoardError
from quadlink.mk.messages import ImuSample, encode_message
from quadlink.vehicle import load_vehicle
from sim_sitl.board import BoardTelemetry, Port1Protocol
from sim_sitl.config import SitlConfig, load_scenario
from sim_sitl.pacing import RealTimePacer, SetpointGate, wait_serving
from sim_sitl.ports import SerialPort, SitlPorts
from sim_sitl.serial_line import SerialLine
from sim_sitl.truth import TruthEncoder, UdpTruthSink
from sim_sitl.vehicle_sim import SimVehicle, TickResult
from sim_sitl.world import RigidState

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SitlOptions:
    config: SitlConfig = field(default_factory=SitlConfig)
    scenario: str | None = None  # overrides config.scenario
    host: str = "127.0.0.1"
    port1: int = 5760  # 0 = ephemeral
    port2: int = 5761
    camera_port: int = 5762
    camera: bool = True
    camera_res: tuple[int, int] | None = None  # (width, height); None = vehicle config
    truth_url: str | None = "udpout:127.0.0.1:14560"
    pty: bool = False
    lockstep: bool = False
    speed: float | None = None  # None: real time (1.0), or unpaced while lock-step consumers gate; 0: unpaced
    duration_s: float | None = None  # sim seconds
    progress_every_s: float = 5.0

@dataclass
class SitlStats:
    sim_time_s: float = 0.0
    wall_time_s: float = 0.0
    imu_frames_offered: int = 0
    imu_frames_dropped: int = 0
    port1_frames_dropped: int = 0
    port1_frames_late: int = 0
    camera_frames: int = 0
    camera_render_s: float = 0.0  # wall time in render + noise model
    camera_render_cpu_s: float = 0.0  # process CPU time in render + noise model (time.process_time)
    setpoints: int = 0
    lockstep_timeouts: int = 0
    camera_ack_timeouts: int = 0

    @property
    def real_time_factor(self) -> float:
        return self.sim_time_s / self.wall_time_s if self.wall_time_s > 0 else 0.0


class Sitl:
    """The simulated vehicle with its ports. ``start()`` runs it in a thread; ``stop()`` ends it.

    ``clock`` is the wall clock every wait and pacing decision reads (sim time is the vehicle's own).
    """

    def __init__(self, options: SitlOptions | None = None, clock: Callable[[], float] = time.monotonic) -> None:
        self.options = opts = options or SitlOptions()
        self._clock = clock
        cfg = opts.config
        self.vehicle = load_vehicle(cfg.vehicle)
        self.scenario = load_scenario(opts.scenario or cfg.scenario)
        self.rng = np.random.default_rng(cfg.seed)
        self.sim = SimVehicle(self.vehicle, cfg, self.scenario, self.rng)
        self.stats = SitlStats()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.camera = None
        try:
            self.ports = SitlPorts(opts.host, opts.port1, opts.port2, opts.pty,
                                   opts.camera_port if opts.camera else None, opts.truth_url)
            if opts.camera:
                from sim_sitl.camera_sim import RgbdCamera

                w, h = opts.camera_res or (self.vehicle.camera.width_px, self.vehicle.camera.height_px)
                self.camera = RgbdCamera(self.sim.world, self.vehicle.camera, cfg.camera_noise,
                                         np.random.default_rng(cfg.seed + 1), w, h, cfg.camera.renderer)
        except BaseException:
            self.close()
            raise
        link = cfg.link
        self.line1 = SerialLine(link.baud, link.bits_per_byte, link.tx_buffer_bytes, link.late_after_s)
        self.line2 = SerialLine(link.baud, link.bits_per_byte, link.tx_buffer_bytes, link.late_after_s)
        self.protocol = Port1Protocol()
        self.truth_encoder = TruthEncoder()
        self._truth_period_s = 1.0 / cfg.truth_rate_hz
        self._next_truth_s = 0.0
        self._camera_period_s = 1.0 / self.vehicle.camera.rate_hz
        self._next_camera_s = 0.0
        self._camera_seq = 0
        self._imu_saturated = False
        self._last_imu_counts = (512,) * 6
        self.gate = SetpointGate()
        self._reported_drops = (0, 0)

    # ------------------------------------------------------------------ endpoints
    @property
    def port1(self) -> SerialPort:
        return self.ports.port1

    @property
    def port2(self) -> SerialPort:
        return self.ports.port2

    @property
    def camera_server(self) -> CameraStreamServer | None:
        return self.ports.camera if hasattr(self, "ports") else None

    @property
    def truth(self) -> UdpTruthSink | None:
        return self.ports.truth

    @property
    def endpoints(self) -> dict[str, str]:
        return self.ports.endpoints

    def log_endpoints(self) -> None:
        o = self.options
        log.info("SITL scenario %s, vehicle %s (%s frame, %.2f kg), %s", self.scenario.name, self.vehicle.name,
                 self.vehicle.frame, self.vehicle.mass_kg,
                 "lock-step" if o.lockstep else ("as fast as possible" if o.speed is not None and o.speed <= 0
                                                  else f"real time x{o.speed or 1.0:g}"))
        for name, url in self.endpoints.items():
            log.info("  %-10s %s", name, url)

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> Sitl:
        self._thread = threading.Thread(target=self._run_guarded, name="sitl", daemon=True)
        self._thread.start()
        return self

    def request_stop(self) -> None:
        """Ask the loop to end (safe from a signal handler or another thread).

        Event.set() takes a non-reentrant lock: a second signal landing inside the first handler's set()
        deadlocked the SITL on shutdown. is_set() is lock-free, so a repeated request returns at once.
        """
        if not self._stop.is_set():
            self._stop.set()

    def stop(self, timeout_s: float = 5.0) -> None:
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout_s)
        self.close()

    def wait(self, timeout_s: float | None = None) -> bool:
        """Wait for the run to end (duration reached); True if it ended."""
        if self._thread is None:
            return True
        self._thread.join(timeout_s)
        return not self._thread.is_alive()

    def close(self) -> None:
        if hasattr(self, "ports"):
            self.ports.close()
        if self._thread is None or not self._thread.is_alive():
            self.sim.close()

    def _run_guarded(self) -> None:
        try:
            self.run()
        except Exception:  # the thread must report, not vanish
            log.exception("SITL loop failed")
            raise

    # ------------------------------------------------------------------ loop
    def run(self) -> None:
        """Run until ``stop()`` or the duration (blocking)."""
        o = self.options
        cfg = self.options.config
        clock = self._clock
        pacer = RealTimePacer(speed=o.speed if o.speed is not None else 1.0)
        chunk_ticks = max(1, round(cfg.lockstep_chunk_s / self.sim.tick_s)) if o.lockstep else 1
        start_wall = clock()
        pacer.rebase(start_wall, self.sim.t_s)
        last_progress = start_wall
        last_progress_stats = (0.0, 0, 0)
        was_gated = False
        while not self._stop.is_set():
            if o.duration_s is not None and self.sim.t_s >= o.duration_s - 1e-9:
                break
            for _ in range(chunk_ticks):
                pending_frame = self._step(self.sim.tick())
                if pending_frame is not None:
                    self._await_camera_ack(pending_frame)
            now = clock()
            self.stats.sim_time_s = self.sim.t_s
            self.stats.wall_time_s = now - start_wall
            gated = o.lockstep and (self.gate.gated or self.ports.camera_client_count > 0)
            if o.lockstep and self.gate.gated:
                self._await_setpoint()
            if gated and o.speed is None:
                was_gated = True
            elif was_gated:  # consumers left: pace from here, do not sleep off the time gained while gated
                was_gated = False
                pacer.rebase(now, self.sim.t_s)
            if gated and o.speed is None:
                self._serve_serial(0.0)  # lock-step alone paces
            else:
                behind = pacer.fell_behind
                wait_s = pacer.wait_s(self.sim.t_s, clock())
                if pacer.fell_behind and not behind:
                    log.warning("cannot keep %.1fx real time; continuing as fast as possible", pacer.speed)
                self._serve_for(wait_s)
            if now - last_progress >= o.progress_every_s:
                self._progress(now - last_progress, last_progress_stats)
                last_progress = now
                last_progress_stats = (self.sim.t_s, self.stats.imu_frames_offered, self.stats.camera_frames)
        self.stats.wall_time_s = clock() - start_wall
        log.info("SITL stopped at sim time %.2f s (real-time factor %.2f)", self.sim.t_s,
                 self.stats.real_time_factor)

    def _progress(self, wall_dt: float, prev: tuple[float, int, int]) -> None:
        sim_dt = self.sim.t_s - prev[0]
        rtf = sim_dt / wall_dt if wall_dt > 0 else 0.0
        imu_hz = (self.stats.imu_frames_offered - prev[1]) / sim_dt if sim_dt > 0 else 0.0
        cam_hz = (self.stats.camera_frames - prev[2]) / sim_dt if sim_dt > 0 else 0.0
        self.stats.port1_frames_dropped = self.line1.stats.frames_dropped
        drops = (self.line1.stats.frames_dropped, self.line2.stats.frames_dropped)
        if drops != self._reported_drops:
            log.warning("serial link over budget: %d port-1 and %d port-2 frames dropped so far (TX buffer full at "
                        "%d baud); ask for fewer or slower streams", drops[0], drops[1], self.options.config.link.baud)
            self._reported_drops = drops
        log.info("sim %.1f s  rtf %.2f  imu %.0f Hz  camera %.1f Hz  setpoints %d  link drops p1 %d p2 %d "
                 "(late p1 %d)  clients p1 %d p2 %d cam %d", self.sim.t_s, rtf, imu_hz, cam_hz, self.stats.setpoints,
                 self.line1.stats.frames_dropped, self.line2.stats.frames_dropped, self.line1.stats.frames_late,
                 self.port1.tcp_client_count, self.port2.tcp_client_count, self.ports.camera_client_count)

    def _step(self, res: TickResult) -> int | None:
        """Everything the board and the sensors emit in the tick that starts at ``res.t_s``.

        Returns the sequence number of a camera frame published in lock-step (its ack is awaited by the
        caller, after this tick's serial bytes have left), else None.
        """
        t = res.t_s
        imu_cfg = self.vehicle.imu
        sample = ImuSample.from_si(res.imu.accel_q_m_s2, res.imu.gyro_q_rad_s, imu_cfg, res.tick)
        counts = sample.accel_counts + sample.gyro_counts
        if min(counts) == 0 or max(counts) == 1023:
            self._imu_saturated = True
        self._last_imu_counts = counts
        self.stats.imu_frames_offered += 1
        if not self.line2.offer(encode_message(sample), t):
            self.stats.imu_frames_dropped += 1
        if self.protocol.anything_due(t, res.firmware.armed):
            for frame in self.protocol.poll(self._telemetry(res)):
                self.line1.offer(frame, t)
        pending = None
        if self.camera is not None and t + 1e-9 >= self._next_camera_s:
            self._next_camera_s += self._camera_period_s
            pending = self._render_camera(res.state, t)
        if self.truth is not None and t + 1e-9 >= self._next_truth_s:
            self._next_truth_s += self._truth_period_s
            self._send_truth(res.state, t)
        t_end = t + self.sim.tick_s
        self.ports.write_serial(self.line1.drain(t_end), self.line2.drain(t_end))
        return pending

    def _telemetry(self, res: TickResult) -> BoardTelemetry:
        fw = self.sim.firmware
        roll, pitch, yaw = euler_from_R(res.state.R_ned_q)
        mv = self.sim.battery_mv()
        b = self.vehicle.battery
        errors = fw.error_flags
        if mv < b.cells * 3.5 * 1000:
            errors |= BoardError.BATTERY_LOW
        if self._imu_saturated:
            errors |= BoardError.IMU_SATURATED
        if self.protocol.rx_frames_dropped:
            errors |= BoardError.RX_FRAMES_DROPPED
        return BoardTelemetry(
            t_s=res.t_s, imu_sample_count=res.tick + 1, armed=res.firmware.armed,
            flight_state=res.firmware.flight_state, failsafe=res.firmware.failsafe, battery_mv=mv,
            error_flags=errors, last_setpoint_seq=fw.command.seq, roll_rad=roll, pitch_rad=pitch, yaw_rad=yaw,
            thrust_fraction=fw.command.thrust if res.firmware.armed else 0.0,
            motor_thrust_n=tuple(float(x) for x in res.state.motor_thrust_n),  # type: ignore[arg-type]
            imu_counts=self._last_imu_counts)

    def _render_camera(self, state: RigidState, t_s: float) -> int | None:
        """Render and publish the frame of ``t_s``; its seq if lock-step must wait for its acks."""
        server = self.ports.camera
        assert self.camera is not None and server is not None
        if server.client_count == 0:
            return None  # nobody watching: do not pay for rendering
        t0, cpu0 = self._clock(), time.process_time()
        frame = self.camera.render(state, self._camera_seq, t_s)
        self.stats.camera_render_s += self._clock() - t0
        self.stats.camera_render_cpu_s += time.process_time() - cpu0
        server.publish(frame)
        self.stats.camera_frames += 1
        seq = self._camera_seq
        self._camera_seq += 1
        return seq if self.options.lockstep and server.client_count > 0 else None

    def _send_truth(self, state: RigidState, t_s: float) -> None:
        assert self.truth is not None
        any_m, obstacle_m = self.sim.world.nearest_distances(state.p_ned_m)
        p_local = state.p_ned_m - self.sim.world.start_p_ned_m
        self.truth.send(self.truth_encoder.encode(t_s, p_local, state.v_ned_m_s, state.R_ned_q,
                                                  state.omega_q_rad_s, any_m, obstacle_m))

    # ------------------------------------------------------------------ serial I/O and the waits
    def _serve_serial(self, timeout_s: float = 0.0) -> int:
        """Wait up to ``timeout_s`` for serial input and handle it at the current sim time.

        Accepts clients, flushes slow clients' backlogs, feeds port 1's bytes to the board's protocol
        (requests are answered on the simulated wire, setpoints reach the firmware), discards port 2's
        input. Returns the number of setpoints taken.
        """
        data = self.ports.poll(timeout_s).port1
        if not data:
            return 0
        t = self.sim.t_s
        commands, replies = self.protocol.on_bytes(data, t)
        for frame in replies:
            self.line1.offer(frame, t)
        for cmd in commands:
            self.sim.on_setpoint(cmd)
        if commands:
            self.stats.setpoints += len(commands)
            if self.options.lockstep and self.gate.on_setpoints(len(commands)):
                log.info("lock-step: port-1 client is sending setpoints; waiting for one per %.0f ms chunk",
                         self.options.config.lockstep_chunk_s * 1000)
        return len(commands)

    def _serve_for(self, wait_s: float) -> None:
        """Serve the serial ports now and keep serving them for ``wait_s`` seconds (real-time pacing)."""
        deadline = self._clock() + wait_s
        self._serve_serial()
        while not self._stop.is_set():
            remaining = deadline - self._clock()
            if remaining <= 0:
                break
            self._serve_serial(min(remaining, 0.1))  # a signal handler only sets the stop flag: look at it often

    def _await_camera_ack(self, seq: int) -> None:
        """Lock-step: wait for every camera client's ack of frame ``seq``, serving the serial ports meanwhile."""
        server = self.ports.camera
        assert server is not None
        timeout_s = self.options.config.lockstep_timeout_s
        done = wait_serving(lambda block_s: server.wait_acks(seq, block_s), lambda: self._serve_serial(), timeout_s,
                            self._clock, self._stop.is_set)
        if done is False:
            self.stats.camera_ack_timeouts += 1
            log.warning("lock-step: camera frame %d not acknowledged within %.1f s; proceeding", seq, timeout_s)

    def _await_setpoint(self) -> None:
        """Lock-step: wait for the setpoint that pays for the next chunk (serving the serial ports)."""
        timeout_s = self.options.config.lockstep_timeout_s

        def ready(block_s: float) -> bool:
            if self.gate.credit > 0 or not self.port1.has_peer:
                return True
            self._serve_serial(block_s)
            return self.gate.credit > 0

        done = wait_serving(ready, lambda: None, timeout_s, self._clock, self._stop.is_set, slice_s=0.05)
        if done is None:
            return
        if self.gate.take():
            return
        if not self.port1.has_peer:
            self.gate.release()
            log.info("lock-step: port-1 client gone; running free")
        elif done is False:
            self.stats.lockstep_timeouts += 1
            self.gate.release()
            log.warning("lock-step: no setpoint within %.1f s at sim time %.2f s; proceeding without waiting "
                        "until setpoints resume", timeout_s, self.sim.t_s)


def parse_resolution(text: str) -> tuple[int, int]:
    try:
        w, h = (int(x) for x in text.lower().split("x"))
    except ValueError as exc:
        raise ValueError(f"bad resolution {text!r} (use WIDTHxHEIGHT, e.g. 320x240)") from exc
    if (w, h) not in ((320, 240), (640, 480)):
        raise ValueError(f"camera resolution {text} not supported (320x240 or 640x480)")
    if not math.isclose(w / h, 4 / 3):
        raise ValueError("aspect must be 4:3")
    return w, h

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
from pathlib import Path

import numpy as np

from quadlink.camera import CameraStreamServer
from quadlink.lockstep import DEFAULT_DONE_TIMEOUT_S, PARTICIPANTS, Coordinator, LockstepError, wait_for_units
from quadlink.mavlink.tlog import TlogWriter
from quadlink.mk.flags import BoardError
from quadlink.mk.messages import ImuSample, encode_message
from quadlink.vehicle import load_vehicle
from sim_sitl.avr_board import AvrBoard, elf_path
from sim_sitl.board import BoardTelemetry, Port1Protocol
from sim_sitl.config import SitlConfig, load_scenario
from sim_sitl.pacing import RealTimePacer, SetpointGate, wait_serving
from sim_sitl.ports import SerialPort, SitlPorts
from sim_sitl.serial_line import SerialLine
from sim_sitl.truth import TruthEncoder, UdpTruthSink
from sim_sitl.vehicle_sim import SimVehicle, TickResult
from sim_sitl.world import RigidState

log = logging.getLogger(__name__)

DISARMED_END_S = 2.0  # deterministic lock-step: simulated seconds on the ground, disarmed, before the run ends


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
    # every truth packet also written here, as sent (a judge reads it whole: a listener's UDP socket may drop
    # packets when its process is starved); None: not recorded
    truth_tlog: Path | None = None
    pty: bool = False
    lockstep: bool = False
    speed: float | None = None  # None: real time (1.0), or unpaced while lock-step consumers gate; 0: unpaced
    duration_s: float | None = None  # sim seconds
    progress_every_s: float = 5.0
    # the deterministic lock-step (quadlink.lockstep): serve the coordinator on this port (0 = ephemeral) and
    # step only with every one of these participants; None: the plain lock-step or real time
    lockstep_port: int | None = None
    lockstep_participants: tuple[str, ...] = PARTICIPANTS
    lockstep_done_timeout_s: float = DEFAULT_DONE_TIMEOUT_S
    # deterministic lock-step: once the operator has left, end after DISARMED_END_S disarmed or this many simulated
    # seconds after it left (the flight's end is then simulated time, not when a supervisor noticed); None: at
    # duration_s
    end_after_operator_s: float | None = None

@dataclass
class SitlStats:
    sim_time_s: float = 0.0
    wall_time_s: float = 0.0
    imu_frames_offered: int = 0
    imu_frames_dropped: int = 0
    port1_frames_dropped: int = 0
    port1_frames_late: int = 0
    camera_frames: int = 0
    camera_frames_dropped: int = 0   # lost by the camera model before publication (the Xtion model's drops)
    camera_render_s: float = 0.0  # wall time in render + noise model
    camera_render_cpu_s: float = 0.0  # process CPU time in render + noise model (time.process_time)
    setpoints: int = 0
    steps: int = 0  # deterministic lock-step steps answered by every participant
    lockstep_timeouts: int = 0
    camera_ack_timeouts: int = 0

    @property
    def real_time_factor(self) -> float:
        return self.sim_time_s / self.wall_time_s if self.wall_time_s > 0 else 0.0


class Sitl:
    """The simulated vehicle with its ports. ``start()`` runs it in a thread; ``stop()`` ends it.

    ``clock`` is the wall clock every wait and pacing decision reads (sim time is the vehicle's own).
    """

    def __init__(self, options: SitlOptions | None = None, clock: Callable[[], float] = time.monotonic,
                 unix_clock: Callable[[], float] = time.time) -> None:
        self.options = opts = options or SitlOptions()
        self._clock = clock
        self.unix_clock = unix_clock   # the truth tlog's record stamps only
        cfg = opts.config
        self.vehicle = load_vehicle(cfg.vehicle)
        self.scenario = load_scenario(opts.scenario or cfg.scenario)
        self.rng = np.random.default_rng(cfg.seed)
        self.sim = SimVehicle(self.vehicle, cfg, self.scenario, self.rng)
        self.avr: AvrBoard | None = None  # --board avr: the firmware binary flies (sim_sitl/avr_board.py)
        if cfg.board == "avr":
            try:
                self.avr = AvrBoard(elf_path(cfg.firmware_elf), self.vehicle, cfg.baro,
                                    np.random.default_rng(cfg.seed + 2), self.sim.tick_s, cfg.link.late_after_s)
            except BaseException:
                self.sim.close()
                raise
            self.sim.board = self.avr
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
        self.truth_tlog: TlogWriter | None = None
        if opts.truth_tlog is not None:
            try:
                self.truth_tlog = TlogWriter(opts.truth_tlog)
            except OSError:
                self.close()
                raise
        self._truth_period_s = 1.0 / cfg.truth_rate_hz
        self._next_truth_s = 0.0
        self._camera_period_s = 1.0 / self.vehicle.camera.rate_hz
        self._next_camera_s = 0.0
        self._camera_seq = 0
        self._imu_saturated = False
        self._last_imu_counts = (512,) * 6
        self.gate = SetpointGate()
        self._reported_drops = (0, 0)
        self.coordinator: Coordinator | None = None
        self._port1_in = bytearray()   # deterministic lock-step: port-1 bytes read, not yet applied
        self._port1_in_total = 0       # ... and how many were ever read
        self._port1_applied = 0
        self._bytes_out = [0, 0]       # bytes written to port 1 and port 2
        self._operator_left_s: float | None = None
        self._disarmed_since_s: float | None = None
        self._was_gated = False   # the plain lock-step's consumers gated the last chunk (_pace)
        if opts.lockstep_port is not None:
            try:
                self.coordinator = Coordinator(opts.host, opts.lockstep_port, opts.lockstep_participants)
            except OSError:
                self.close()
                raise

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
        ep = dict(self.ports.endpoints)
        if self.coordinator is not None:
            ep["lock-step"] = self.coordinator.url
        return ep

    def log_endpoints(self) -> None:
        o = self.options
        log.info("SITL scenario %s, vehicle %s (%s frame, %.2f kg), board %s, %s", self.scenario.name,
                 self.vehicle.name, self.vehicle.frame, self.vehicle.mass_kg,
                 f"avr ({self.avr.mcu_elf})" if self.avr is not None else "model",
                 f"deterministic lock-step with {', '.join(o.lockstep_participants)}" if self.coordinator
                 else "lock-step" if o.lockstep else ("as fast as possible" if o.speed is not None and o.speed <= 0
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
        if getattr(self, "truth_tlog", None) is not None:
            self.truth_tlog.close()  # type: ignore[union-attr]   # later writes are ignored
        if getattr(self, "coordinator", None) is not None:
            self.coordinator.close()  # type: ignore[union-attr]
        if self._thread is None or not self._thread.is_alive():
            self.sim.close()
            if getattr(self, "avr", None) is not None:
                self.avr.close()  # type: ignore[union-attr]

    def _run_guarded(self) -> None:
        try:
            self.run()
        except Exception:  # the thread must report, not vanish
            log.exception("SITL loop failed")
            raise

    # ------------------------------------------------------------------ loop
    def run(self) -> None:
        """The one loop, whatever owns time (blocking): per chunk of ticks, the inputs due (in the deterministic
        lock-step, exactly the bytes the bridge had sent by its last DONE), the ticks (each one's serial bytes out;
        in the plain lock-step a camera frame's acks awaited), then what paces the next chunk (:meth:`_pace`: the
        wall clock, or the plain lock-step's setpoint gate; :meth:`_lockstep_step`: STEP to every participant and
        their DONE); until :meth:`stop`, the duration, or the deterministic run's end (:meth:`_end_reason`)."""
        o, cfg, clock, coord = self.options, self.options.config, self._clock, self.coordinator
        plain_lockstep = o.lockstep and coord is None
        chunk_ticks = max(1, round(cfg.lockstep_chunk_s / self.sim.tick_s)) if o.lockstep or coord else 1
        pacer = RealTimePacer(speed=o.speed if o.speed is not None else 1.0)
        if coord is not None:
            self._await_registration(coord)
        start_wall = last_progress = clock()
        pacer.rebase(start_wall, self.sim.t_s)
        last_progress_stats = (0.0, 0, 0)
        self._was_gated = False
        index = 0
        reason: str | None = None
        while not self._stop.is_set():
            reason = self._end_reason(coord)
            if reason is not None:
                break
            if coord is not None:
                self._apply_port1(coord.sent.get("bridge>sitl"))
            for _ in range(chunk_ticks):
                pending_frame = self._step(self.sim.tick())
                if pending_frame is not None and plain_lockstep:
                    self._await_camera_ack(pending_frame)
            if coord is not None:
                self._lockstep_step(coord, index)
                self.stats.steps = index = index + 1
                now = clock()
            else:
                now = clock()
                self._pace(pacer, now)
            self.stats.sim_time_s, self.stats.wall_time_s = self.sim.t_s, now - start_wall
            if now - last_progress >= o.progress_every_s:
                self._progress(now - last_progress, last_progress_stats)
                last_progress = now
                last_progress_stats = (self.sim.t_s, self.stats.imu_frames_offered, self.stats.camera_frames)
        self.stats.wall_time_s = clock() - start_wall
        steps = f" after {self.stats.steps} lock-step steps" if coord is not None else ""
        log.info("SITL stopped at sim time %.2f s%s (%s; real-time factor %.2f)", self.sim.t_s, steps,
                 reason or "stopped", self.stats.real_time_factor)
        if coord is not None:
            coord.close(reason or "stopped")

    def _await_registration(self, coord: Coordinator) -> None:
        """The deterministic lock-step (:mod:`quadlink.lockstep`): no simulated time passes until every participant
        has registered (serving port 1 meanwhile)."""
        log.info("lock-step: waiting for %s to register on %s", ", ".join(self.options.lockstep_participants),
                 coord.url)
        while not self._stop.is_set() and not coord.all_registered():
            coord.poll(0.02)
            self._poll_port1()

    def _lockstep_step(self, coord: Coordinator, index: int) -> None:
        """The deterministic lock-step's end of a chunk: what was sent on each link, STEP ``index`` to everyone,
        and every participant's DONE before the next chunk. A participant too slow (``lockstep_done_timeout_s`` of
        wall time) ends the run with :class:`LockstepError`: a flight that is no longer deterministic must fail,
        not go on as another flight."""
        camera = self.ports.camera
        coord.sent.update({"sitl>bridge.cmd": self._bytes_out[0], "sitl>bridge.imu": self._bytes_out[1],
                           "sitl>companion.camera": camera.frames_published if camera is not None else 0})
        coord.send_step(index, self.sim.t_s)
        self._await_done(coord, index)

    def _pace(self, pacer: RealTimePacer, now: float) -> None:
        """Free-running: serve the serial ports until the next chunk is due on the wall clock (``speed`` x real
        time), or, in the plain lock-step, until its setpoint has paid for it (and the camera's acks: a consumer
        gates the run; when the consumers leave, pacing resumes from here, not sleeping off the time gained)."""
        o = self.options
        gated = o.lockstep and (self.gate.gated or self.ports.camera_client_count > 0)
        if o.lockstep and self.gate.gated:
            self._await_setpoint()
        if gated and o.speed is None:
            self._was_gated = True
        elif self._was_gated:
            self._was_gated = False
            pacer.rebase(now, self.sim.t_s)
        if gated and o.speed is None:
            self._serve_serial(0.0)  # lock-step alone paces
            return
        behind = pacer.fell_behind
        wait_s = pacer.wait_s(self.sim.t_s, self._clock())
        if pacer.fell_behind and not behind:
            log.warning("cannot keep %.1fx real time; continuing as fast as possible", pacer.speed)
        self._serve_for(wait_s)

    def _end_reason(self, coord: Coordinator | None) -> str | None:
        """Why the run ends now (None: it goes on); decided on simulated time and state only: the duration, or in
        the deterministic lock-step the operator's leaving and the landing after it."""
        o, t = self.options, self.sim.t_s
        if coord is not None and o.end_after_operator_s is not None and "operator" in coord.left:
            if self._operator_left_s is None:
                self._operator_left_s = t
                log.info("the operator left at sim time %.2f s", t)
            if not self.armed:
                if self._disarmed_since_s is None:
                    self._disarmed_since_s = t
                if t >= self._disarmed_since_s + DISARMED_END_S - 1e-9:
                    # a little on the ground: the bridge's 1 Hz heartbeat and the logs show the landing too
                    return f"the operator left and the vehicle has been disarmed since {self._disarmed_since_s:.2f} s"
                return None
            self._disarmed_since_s = None
            if t >= self._operator_left_s + o.end_after_operator_s - 1e-9:
                return f"still armed {o.end_after_operator_s:g} s after the operator left"
            return None
        if o.duration_s is not None and t >= o.duration_s - 1e-9:
            return f"duration {o.duration_s:.1f} s"
        return None

    def _await_done(self, coord: Coordinator, index: int) -> None:
        """Every participant's DONE of step ``index`` (serving the serial ports: slow clients' backlogs, input
        kept for the next chunk)."""
        deadline = self._clock() + self.options.lockstep_done_timeout_s
        while not coord.all_done(index):
            if self._stop.is_set():
                return
            if self._clock() >= deadline:
                raise LockstepError(f"lock-step: step {index} (sim time {self.sim.t_s:.2f} s) not answered within "
                                    f"{self.options.lockstep_done_timeout_s:.0f} s by "
                                    f"{', '.join(coord.waiting_for(index))}")
            coord.poll(0.001)
            self._poll_port1()

    def _poll_port1(self, timeout_s: float = 0.0) -> None:
        """Read the serial ports' input into the port-1 buffer (applied at the next chunk, not now)."""
        data = self.ports.poll(timeout_s).port1
        if data:
            self._port1_in += data
            self._port1_in_total += len(data)

    def _apply_port1(self, expected_total: int | None) -> None:
        """Apply exactly the port-1 bytes the bridge had sent by its last DONE, waiting for any still in flight;
        bytes that came early wait for their step. In this mode port 1 is the bridge's alone (another client's
        bytes would count as the bridge's)."""
        what = "MK port-1 bytes from the bridge"
        wait_for_units(lambda: self._port1_in_total, expected_total, self._poll_port1, what,
                       self.options.lockstep_done_timeout_s, self._clock)
        n = len(self._port1_in) if expected_total is None else expected_total - self._port1_applied
        data, self._port1_in = bytes(self._port1_in[:n]), self._port1_in[n:]
        self._port1_applied += len(data)
        if data:
            self._on_port1(data)

    @property
    def armed(self) -> bool:
        """The board's arm state (the AVR board's LED pin, or the Python model's flag)."""
        return self.avr.armed if self.avr is not None else self.sim.firmware.armed

    def _on_port1(self, data: bytes) -> int:
        """Port 1's bytes at the current sim time: requests answered on the simulated wire, setpoints to the
        firmware (the AVR board: all of them to USART0's receiver). Returns the number of setpoints."""
        if self.avr is not None:
            n = self.avr.on_port1(data)
            self.stats.setpoints += n
            return n
        t = self.sim.t_s
        commands, replies = self.protocol.on_bytes(data, t)
        for frame in replies:
            self.line1.offer(frame, t)
        for cmd in commands:
            self.sim.on_setpoint(cmd)
        self.stats.setpoints += len(commands)
        return len(commands)

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
        if self.avr is not None:
            imu, busy = self.avr.imu_stream.stats, self.avr.loop.busy_cycles
            log.info("board avr: I frames lost %d late %d; loop busy max %.0f %% of the tick (last %d ticks)",
                     imu.lost, imu.late, 100.0 * max(busy, default=0) / self.avr.cycles_per_tick, len(busy))
            busy.clear()
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
        if self.avr is not None:
            out1, out2 = self.avr.take_port_bytes()  # the UARTs paced them: not through the serial lines
            imu = self.avr.imu_stream.stats
            self.stats.imu_frames_offered, self.stats.imu_frames_dropped = imu.frames, imu.lost
        else:
            out1, out2 = self._model_board_bytes(res)
        pending = None
        if self.camera is not None and t + 1e-9 >= self._next_camera_s:
            self._next_camera_s += self._camera_period_s
            pending = self._render_camera(res.state, t)
        if (self.truth is not None or self.truth_tlog is not None) and t + 1e-9 >= self._next_truth_s:
            self._next_truth_s += self._truth_period_s
            self._send_truth(res.state, t)
        self._bytes_out[0] += len(out1)
        self._bytes_out[1] += len(out2)
        self.ports.write_serial(out1, out2)
        return pending

    def _model_board_bytes(self, res: TickResult) -> tuple[bytes, bytes]:
        """The Python board's tick: the ``I`` frame on port 2, due telemetry on port 1, and the bytes both serial
        lines carried by the tick's end."""
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
        t_end = t + self.sim.tick_s
        return self.line1.drain(t_end), self.line2.drain(t_end)

    def _telemetry(self, res: TickResult) -> BoardTelemetry:
        fw = self.sim.firmware
        att = self.sim.sensing.attitude   # what the board reports is its own estimate, not the truth
        roll, pitch, yaw = att.roll_rad, att.pitch_rad, att.yaw_rad
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
            imu_counts=self._last_imu_counts, baro=self.sim.sensing.baro)

    def _render_camera(self, state: RigidState, t_s: float) -> int | None:
        """Render and publish the frame of ``t_s``; its seq if lock-step must wait for its acks."""
        server = self.ports.camera
        assert self.camera is not None and server is not None
        if server.client_count == 0:
            return None  # nobody watching: do not pay for rendering
        t0, cpu0 = self._clock(), time.process_time()
        frame = self.camera.capture(state, self._camera_seq, t_s)   # None: the driver lost it (the Xtion model)
        self.stats.camera_render_s += self._clock() - t0
        self.stats.camera_render_cpu_s += time.process_time() - cpu0
        seq = self._camera_seq
        self._camera_seq += 1   # a lost frame leaves a gap in the numbers, as a driver's frame counter does
        if frame is None:
            self.stats.camera_frames_dropped += 1
            return None
        server.publish(frame)
        self.stats.camera_frames += 1
        gated = self.options.lockstep and self.coordinator is None  # the deterministic steps wait for more than acks
        return seq if gated and server.client_count > 0 else None

    def _send_truth(self, state: RigidState, t_s: float) -> None:
        any_m, obstacle_m = self.sim.world.nearest_distances(state.p_ned_m)
        p_local = state.p_ned_m - self.sim.world.start_p_ned_m
        packets = self.truth_encoder.encode(t_s, p_local, state.v_ned_m_s, state.R_ned_q, state.omega_q_rad_s,
                                            any_m, obstacle_m)
        if self.truth is not None:
            self.truth.send(packets)
        if self.truth_tlog is not None:
            stamp_s = self.unix_clock()
            for packet in packets:
                self.truth_tlog.write(packet, stamp_s)

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
        n = self._on_port1(data)
        if self.options.lockstep and self.gate.on_setpoints(n):
            log.info("lock-step: port-1 client is sending setpoints; waiting for one per %.0f ms chunk",
                     self.options.config.lockstep_chunk_s * 1000)
        return n

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

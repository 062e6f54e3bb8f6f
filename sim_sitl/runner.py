"""``Sitl``: wires the simulated vehicle to its ports and clocks (the only I/O of the SITL).

One thread runs the simulation and does all port I/O with non-blocking sockets (the camera stream
server of ``quadlink.camera`` runs its own accept/ack threads). Per board tick (2 ms of sim time) it
steps the vehicle, queues the IMU frame on port 2's serial line and the due telemetry on port 1's,
renders the camera when due, sends ground truth when due, drains the serial lines to the clients and
reads what the clients sent. Between chunks it waits: real time (``speed`` x wall clock) or, in
lock-step, for one setpoint per 10 ms chunk while a port-1 client is sending them and for the camera
clients' acks at each frame (each wait bounded by ``lockstep_timeout_s``, then a warning).
"""

from __future__ import annotations

import logging
import math
import os
import select
import socket
import threading
import time
import tty
from dataclasses import dataclass, field

import numpy as np

from firmware_bridge.mk_messages import (
    ERROR_BATTERY_LOW,
    ERROR_IMU_SATURATED,
    ERROR_RX_FRAMES_DROPPED,
    ImuSample,
    encode_message,
)
from quadlink.camera import CameraStreamServer
from quadlink.errors import LinkError
from quadlink.frames import euler_from_R
from quadlink.vehicle import load_vehicle
from sim_sitl.board import BoardTelemetry, Port1Protocol
from sim_sitl.config import SitlConfig, load_scenario
from sim_sitl.serial_line import SerialLine
from sim_sitl.truth import TruthEncoder, UdpTruthSink
from sim_sitl.vehicle_sim import SimVehicle

log = logging.getLogger(__name__)

MAX_CLIENT_BACKLOG_BYTES = 1 << 18


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


class _Conn:
    def __init__(self, sock: socket.socket | None, fd: int, name: str) -> None:
        self.sock = sock
        self.fd = fd
        self.name = name
        self.out = bytearray()
        self.alive = True

    def fileno(self) -> int:
        return self.fd


class _Port:
    """A serial port's far end: TCP listener (+ optional pty), all clients share the line."""

    def __init__(self, label: str, host: str, port: int, use_pty: bool) -> None:
        self.label = label
        try:
            self.listener = socket.create_server((host, port))
        except OSError as exc:
            raise LinkError(f"{label}: cannot listen on tcp {host}:{port}: {exc}") from exc
        self.listener.setblocking(False)
        self.address = self.listener.getsockname()[:2]
        self.conns: list[_Conn] = []
        self.pty_path: str | None = None
        self._pty_slave: int | None = None
        self.bytes_dropped = 0
        if use_pty:
            master, slave = os.openpty()
            tty.setraw(slave)
            os.set_blocking(master, False)
            self._pty_slave = slave
            self.pty_path = os.ttyname(slave)
            self.conns.append(_Conn(None, master, f"pty {self.pty_path}"))

    @property
    def url(self) -> str:
        return f"socket://{self.address[0]}:{self.address[1]}"

    @property
    def tcp_client_count(self) -> int:
        return sum(1 for c in self.conns if c.sock is not None and c.alive)

    def accept(self) -> None:
        while True:
            try:
                sock, addr = self.listener.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                return
            sock.setblocking(False)
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self.conns.append(_Conn(sock, sock.fileno(), f"{addr[0]}:{addr[1]}"))
            log.info("%s: client %s connected", self.label, f"{addr[0]}:{addr[1]}")

    def write(self, data: bytes) -> None:
        if not data:
            return
        for c in self.conns:
            if not c.alive:
                continue
            c.out += data
            self._flush(c)

    def _flush(self, c: _Conn) -> None:
        try:
            n = c.sock.send(c.out) if c.sock is not None else os.write(c.fd, c.out)
            del c.out[:n]
        except (BlockingIOError, InterruptedError):
            pass
        except OSError as exc:
            if c.sock is not None:
                self._drop(c, f"send failed: {exc}")
            else:
                c.out.clear()  # pty with nobody reading: bytes fall on the floor as on a wire
        if len(c.out) > MAX_CLIENT_BACKLOG_BYTES:
            if c.sock is not None:
                self._drop(c, "not reading (backlog full)")
            else:
                self.bytes_dropped += len(c.out)
                c.out.clear()

    def _drop(self, c: _Conn, why: str) -> None:
        c.alive = False
        log.info("%s: client %s disconnected (%s)", self.label, c.name, why)
        if c.sock is not None:
            c.sock.close()

    def read_all(self, readable: set[int] | None = None) -> bytes:
        """Bytes from every client (only those in ``readable`` when given, as reported by select)."""
        data = bytearray()
        for c in self.conns:
            if not c.alive or (readable is not None and c.fd not in readable):
                continue
            while True:
                try:
                    chunk = c.sock.recv(4096) if c.sock is not None else os.read(c.fd, 4096)
                except (BlockingIOError, InterruptedError):
                    break
                except OSError as exc:
                    if c.sock is not None:
                        self._drop(c, str(exc))
                    break
                if not chunk:
                    if c.sock is not None:
                        self._drop(c, "closed by peer")
                    break
                data += chunk
        self.conns = [c for c in self.conns if c.alive]
        return bytes(data)

    def fds(self) -> list[int]:
        return [self.listener.fileno()] + [c.fd for c in self.conns if c.alive]

    def close(self) -> None:
        for c in self.conns:
            if c.sock is not None:
                c.sock.close()
            else:
                os.close(c.fd)
        self.conns = []
        if self._pty_slave is not None:
            os.close(self._pty_slave)
            self._pty_slave = None
        self.listener.close()


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
    """The simulated vehicle with its ports. ``start()`` runs it in a thread; ``stop()`` ends it."""

    def __init__(self, options: SitlOptions | None = None) -> None:
        self.options = opts = options or SitlOptions()
        cfg = opts.config
        self.vehicle = load_vehicle(cfg.vehicle)
        self.scenario = load_scenario(opts.scenario or cfg.scenario)
        self.rng = np.random.default_rng(cfg.seed)
        self.sim = SimVehicle(self.vehicle, cfg, self.scenario, self.rng)
        self.stats = SitlStats()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._ports: list[_Port] = []
        self.camera = None
        self.camera_server: CameraStreamServer | None = None
        self.truth: UdpTruthSink | None = None
        try:
            self.port1 = _Port("port 1", opts.host, opts.port1, opts.pty)
            self._ports.append(self.port1)
            self.port2 = _Port("port 2", opts.host, opts.port2, opts.pty)
            self._ports.append(self.port2)
            if opts.camera:
                from sim_sitl.camera_sim import RgbdCamera

                w, h = opts.camera_res or (self.vehicle.camera.width_px, self.vehicle.camera.height_px)
                self.camera = RgbdCamera(self.sim.world, self.vehicle.camera, cfg.camera_noise,
                                         np.random.default_rng(cfg.seed + 1), w, h, cfg.camera.renderer)
                try:
                    self.camera_server = CameraStreamServer(opts.host, opts.camera_port)
                except OSError as exc:
                    raise LinkError(f"camera stream: cannot listen on tcp {opts.host}:{opts.camera_port}: {exc}") \
                        from exc
            if opts.truth_url:
                self.truth = UdpTruthSink(opts.truth_url)
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
        self._lockstep_gated = False
        self._setpoint_credit = 0
        self._reported_drops = (0, 0)

    # ------------------------------------------------------------------ endpoints
    @property
    def endpoints(self) -> dict[str, str]:
        ep = {"port1": self.port1.url, "port2": self.port2.url}
        if self.port1.pty_path:
            ep["port1_pty"] = self.port1.pty_path
            ep["port2_pty"] = self.port2.pty_path or ""
        if self.camera_server is not None:
            ep["camera"] = f"tcp://{self.camera_server.host}:{self.camera_server.port}"
        if self.truth is not None:
            ep["truth"] = self.truth.url
        return ep

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
        for port in self._ports:
            port.close()
        self._ports = []
        if self.camera_server is not None:
            self.camera_server.close()
            self.camera_server = None
        if self.truth is not None:
            self.truth.close()
            self.truth = None
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
        speed = o.speed if o.speed is not None else 1.0
        unpaced = o.speed is not None and (o.speed <= 0 or math.isinf(o.speed))  # as fast as possible
        chunk_ticks = max(1, round(cfg.lockstep_chunk_s / self.sim.tick_s)) if o.lockstep else 1
        wall0 = start_wall = time.monotonic()
        sim0 = self.sim.t_s
        last_progress = wall0
        last_progress_stats = (0.0, 0, 0)
        was_gated = False
        behind_warned = False
        while not self._stop.is_set():
            if o.duration_s is not None and self.sim.t_s >= o.duration_s - 1e-9:
                break
            for _ in range(chunk_ticks):
                self._tick()
            now = time.monotonic()
            self.stats.sim_time_s = self.sim.t_s
            self.stats.wall_time_s = now - start_wall
            gated = o.lockstep and (self._lockstep_gated or
                                    (self.camera_server is not None and self.camera_server.client_count > 0))
            if o.lockstep and self._lockstep_gated:
                self._wait_for_setpoint()
            if gated and o.speed is None:
                was_gated = True
            elif was_gated:  # consumers left: pace from here, do not sleep off the time gained while gated
                was_gated = False
                wall0, sim0 = now, self.sim.t_s
            if unpaced:
                self._service_io(0.0)
            elif not gated or o.speed is not None:
                target = wall0 + (self.sim.t_s - sim0) / speed
                if target - now < -0.5:  # cannot keep up: do not try to catch up in a burst
                    if not behind_warned:
                        log.warning("cannot keep %.1fx real time (sim %.2f s behind); continuing as fast as possible",
                                    speed, (now - target) * speed)
                        behind_warned = True
                    wall0, sim0 = now, self.sim.t_s
                    target = now
                self._service_io(max(0.0, target - time.monotonic()))
            else:
                self._service_io(0.0)
            if now - last_progress >= o.progress_every_s:
                self._progress(now - last_progress, last_progress_stats)
                last_progress = now
                last_progress_stats = (self.sim.t_s, self.stats.imu_frames_offered, self.stats.camera_frames)
        self.stats.wall_time_s = time.monotonic() - start_wall
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
                 self.port1.tcp_client_count, self.port2.tcp_client_count,
                 self.camera_server.client_count if self.camera_server else 0)

    def _tick(self) -> None:
        res = self.sim.tick()
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
        if self.camera is not None and t + 1e-9 >= self._next_camera_s:
            self._next_camera_s += self._camera_period_s
            self._render_camera(res.state, t)
        if self.truth is not None and t + 1e-9 >= self._next_truth_s:
            self._next_truth_s += self._truth_period_s
            self._send_truth(res.state, t)
        t_end = t + self.sim.tick_s
        self.port2.write(self.line2.drain(t_end))
        self.port1.write(self.line1.drain(t_end))

    def _telemetry(self, res) -> BoardTelemetry:  # noqa: ANN001
        fw = self.sim.firmware
        roll, pitch, yaw = euler_from_R(res.state.R_ned_q)
        mv = self.sim.battery_mv()
        b = self.vehicle.battery
        errors = fw.error_flags
        if mv < b.cells * 3.5 * 1000:
            errors |= ERROR_BATTERY_LOW
        if self._imu_saturated:
            errors |= ERROR_IMU_SATURATED
        if self.protocol.rx_frames_dropped:
            errors |= ERROR_RX_FRAMES_DROPPED
        return BoardTelemetry(
            t_s=res.t_s, imu_sample_count=res.tick + 1, armed=res.firmware.armed,
            flight_state=res.firmware.flight_state, failsafe=res.firmware.failsafe, battery_mv=mv,
            error_flags=errors, last_setpoint_seq=fw.command.seq, roll_rad=roll, pitch_rad=pitch, yaw_rad=yaw,
            thrust_fraction=fw.command.thrust if res.firmware.armed else 0.0,
            motor_thrust_n=tuple(float(x) for x in res.state.motor_thrust_n),  # type: ignore[arg-type]
            imu_counts=self._last_imu_counts)

    def _render_camera(self, state, t_s: float) -> None:  # noqa: ANN001
        assert self.camera is not None and self.camera_server is not None
        if self.camera_server.client_count == 0:
            return  # nobody watching: do not pay for rendering
        t0, cpu0 = time.perf_counter(), time.process_time()
        frame = self.camera.render(state, self._camera_seq, t_s)
        self.stats.camera_render_s += time.perf_counter() - t0
        self.stats.camera_render_cpu_s += time.process_time() - cpu0
        self.camera_server.publish(frame)
        self.stats.camera_frames += 1
        if self.options.lockstep and self.camera_server.client_count > 0:
            if not self.camera_server.wait_acks(self._camera_seq, self.options.config.lockstep_timeout_s):
                self.stats.camera_ack_timeouts += 1
                log.warning("lock-step: camera frame %d not acknowledged within %.1f s; proceeding",
                            self._camera_seq, self.options.config.lockstep_timeout_s)
        self._camera_seq += 1

    def _send_truth(self, state, t_s: float) -> None:  # noqa: ANN001
        assert self.truth is not None
        any_m, obstacle_m = self.sim.world.nearest_distances(state.p_ned_m)
        p_local = state.p_ned_m - self.sim.world.start_p_ned_m
        self.truth.send(self.truth_encoder.encode(t_s, p_local, state.v_ned_m_s, state.R_ned_q,
                                                  state.omega_q_rad_s, any_m, obstacle_m))

    # ------------------------------------------------------------------ I/O
    def _handle_rx(self, timeout_s: float = 0.0) -> int:
        """Wait up to ``timeout_s`` for input, accept clients, read port 1 (port 2 input is discarded).

        Returns the number of setpoints taken.
        """
        fds = [fd for port in self._ports for fd in port.fds()]
        try:
            readable = set(select.select(fds, [], [], timeout_s)[0])
        except (OSError, ValueError):  # a descriptor closed under us: look at everything once
            readable = set(fds)
        if not readable:
            return 0
        for port in self._ports:
            if port.listener.fileno() in readable:
                port.accept()
        self.port2.read_all(readable)
        data = self.port1.read_all(readable)
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
            self._setpoint_credit = min(self._setpoint_credit + len(commands), 3)
            if self.options.lockstep and not self._lockstep_gated:
                log.info("lock-step: port-1 client is sending setpoints; waiting for one per %.0f ms chunk",
                         self.options.config.lockstep_chunk_s * 1000)
                self._lockstep_gated = True
        return len(commands)

    def _service_io(self, wait_s: float) -> None:
        """Handle I/O now and keep handling it for ``wait_s`` seconds (real-time pacing)."""
        deadline = time.monotonic() + wait_s
        self._handle_rx()
        while not self._stop.is_set():
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                break
            self._handle_rx(min(remaining, 0.1))  # a signal handler only sets the stop flag: look at it often

    def _wait_for_setpoint(self) -> None:
        deadline = time.monotonic() + self.options.config.lockstep_timeout_s
        while self._setpoint_credit <= 0 and not self._stop.is_set():
            if self.port1.tcp_client_count == 0 and not self.port1.pty_path:
                self._lockstep_gated = False
                log.info("lock-step: port-1 client gone; running free")
                return
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                self.stats.lockstep_timeouts += 1
                self._lockstep_gated = False
                log.warning("lock-step: no setpoint within %.1f s at sim time %.2f s; proceeding without waiting "
                            "until setpoints resume", self.options.config.lockstep_timeout_s, self.sim.t_s)
                return
            self._handle_rx(min(remaining, 0.05))
        self._setpoint_credit = max(0, self._setpoint_credit - 1)


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

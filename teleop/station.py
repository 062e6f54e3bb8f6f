"""The ground station process: its lifecycle and the snapshots its threads share.

:class:`Station` wires the haptic device, the force law, the vehicle link and the operator view to
clocks and sockets. Concurrency model: a few threads sharing immutable snapshots (replaced atomically
under one lock), a queue for button presses, one stop event; every wait has a timeout.

* force loop, 1 kHz (``device.force_rate_hz``, :mod:`teleop.force_loop`): poll device -> eq. (15) -> set
  force; in its own process for a device spec (``ForceProcess``), else a thread here (the interpreter's
  switch interval lowered to 0.5 ms while it runs).
* the station's loop, 50 Hz (:meth:`Station._loop` over :mod:`teleop.link`): MAVLink in, MANUAL_CONTROL /
  HEARTBEAT / commands out, warnings, CSV log (:mod:`teleop.recording`), the status line and the end checks. One
  loop over either event source: the wall clock's turns (:meth:`Station.start`, its own thread; :meth:`Station.run`
  waits for it) or the lock-step's STEPs.
* view loop, camera rate (:meth:`Station._view_loop` over :mod:`teleop.view_loop`): the companion's
  operator images and their :class:`quadlink.operator_image.OperatorImageMeta` -> pan-scan compensation
  -> rendered view -> web page (:mod:`teleop.view.server`) and optional video.

Deterministic lock-step (``quadlink teleop --lockstep tcp://HOST:PORT``, :mod:`quadlink.lockstep`): the station
is the ``operator`` participant and runs single-threaded (:meth:`Station.start_lockstep`,
:meth:`Station.run_lockstep`: the same loop): no thread, no force process, no view. Per STEP of the SITL, on its
simulated time ``t``: the force loop's ticks up to ``t`` at ``force_rate_hz`` of simulated time (the device, eq. (15),
the script), then exactly the companion datagrams the step announces, then the link's ticks due at
``mapping.rate_hz`` of simulated time (MANUAL_CONTROL, commands, HEARTBEAT, TIMESYNC), then DONE. The
station's clock is the step's time, so nothing it sends depends on the wall clock or on scheduling.
"""

from __future__ import annotations

import logging
import math
import queue
import re
import sys
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any, Protocol

import cv2
import numpy as np
from numpy.typing import NDArray

from quadlink.camera import CameraStreamClient
from quadlink.client import GroundClient, Signing, connect
from quadlink.errors import ConfigError, ProtocolError, QuadlinkError
from quadlink.journal import JournalWriter
from quadlink.lockstep import DEFAULT_INPUT_TIMEOUT_S, CountedMavlink, LockstepClient, Step, wait_for_units
from quadlink.mavlink.security import read_key
from teleop.commands import CommandResult, CommandTracker
from teleop.config import TeleopConfig
from teleop.delay import LinkDelay
from teleop.devices.base import HapticDevice
from teleop.force import link_ok
from teleop.force_loop import (
    DeviceSpec,
    ForceLoop,
    ForceProcess,
    ForceSnapshot,
    MotionInput,
    PeriodRecorder,
    run_force_loop,
)
from teleop.journal import Kind as JKind
from teleop.journal import encode_step, journal_link
from teleop.link import VehicleLink
from teleop.mapping import ManualControl
from teleop.recording import CsvLog, open_video
from teleop.telemetry import FLAG_GCS_LINK_OK, FLAG_ODOMETRY_OK, MODE_NAMES, Telemetry, min_obstacle_m
from teleop.view.server import ViewHub, ViewServer
from teleop.view_loop import OperatorView, image_meta

log = logging.getLogger(__name__)

LOCKSTEP_NAME = "operator"
LINK_IN = "companion>operator"     # the companion's datagrams to us (lock-step input link)
LINK_OUT = "operator>companion"    # ours to the companion (lock-step output link)
_EPS_S = 1e-9                      # simulated-time comparisons of tick schedules


def warnings_for(tel: Telemetry, link_is_ok: bool, t_s: float, cfg: TeleopConfig) -> list[str]:
    """Warnings shown on the page and in the terminal (pure)."""
    out = []
    if not link_is_ok:
        out.append("VEHICLE LINK LOST" if tel.feedback is not None else "no vehicle link yet")
    fb = tel.feedback
    heard = tel.autopilot_heartbeat_t_s
    if link_is_ok and heard is not None and t_s - heard > cfg.network.heartbeat_timeout_s:
        # the companion talks, the flight controller's bridge behind it has gone quiet (its heartbeat comes through
        # the companion): the vehicle's own failsafes are all that fly it now
        out.append(f"AUTOPILOT SILENT {t_s - heard:.0f} s")
    if fb is not None and link_is_ok:
        if not fb.flags & FLAG_ODOMETRY_OK:
            out.append("odometry not tracking")
        if not fb.flags & FLAG_GCS_LINK_OK:
            out.append("companion does not see our commands")
    dist = min_obstacle_m(tel)
    if dist is not None and dist < cfg.view.obstacle_warning_m:
        out.append(f"OBSTACLE {dist:.2f} m")
    if tel.battery_v is not None and tel.battery_v < cfg.view.battery_warning_v:
        out.append(f"BATTERY LOW {tel.battery_v:.1f} V")
    if tel.last_statustext and tel.statustext_t_s is not None and t_s - tel.statustext_t_s < 10.0:
        out.append(f"vehicle: {tel.last_statustext}")
    return out


class Station:
    def __init__(self, cfg: TeleopConfig, device: HapticDevice | DeviceSpec, vehicle_url: str,
                 image_stream_url: str | None,
                 http_port: int | None, record_path: str | None = None, log_csv: str | None = None,
                 clock: Callable[[], float] = time.perf_counter, exit_at_script_end: bool = True,
                 journal: JournalWriter | None = None) -> None:
        self.cfg = cfg
        self.journal = journal   # the lock-stepped loop's turns (teleop.journal)
        self.device = device
        self.vehicle_url = vehicle_url
        self.image_stream_url = image_stream_url
        self.http_port = http_port
        self.record_path = record_path
        self.log_csv = log_csv
        self.clock = clock
        self.exit_at_script_end = exit_at_script_end
        self.stop_event = threading.Event()
        self._lock = threading.Lock()
        self._force: ForceSnapshot | None = None
        self._motion: MotionInput | None = None
        self._force_proc: ForceProcess | None = None
        self._telemetry = Telemetry()
        self._command = ManualControl(0, 0, 500, 0)
        self._buttons: queue.Queue[str] = queue.Queue(maxsize=100)
        self._acks: deque[str] = deque(maxlen=6)
        self._warnings: list[str] = []
        self._pan_scan_hz = 0.0
        self._delay = LinkDelay()   # TIMESYNC round trip to the companion (the link thread's snapshot)
        self.force_periods = PeriodRecorder()
        self.commands = CommandTracker(cfg.commands)
        self.hub = ViewHub()
        self.server: ViewServer | None = None
        self.client: GroundClient | None = None   # the vehicle link (opened by start / start_lockstep)
        self._conn: Any = None                    # its pymavlink mavfile (counted in the lock-step)
        self._threads: list[threading.Thread] = []
        self._switch_interval = sys.getswitchinterval()
        self.manual_control_sent = 0
        self.view_frames = 0
        self.bad_image_meta = 0   # operator images whose metadata did not decode
        self.error: BaseException | None = None
        self._lockstep: LockstepClient | None = None
        self._counted: CountedMavlink | None = None
        self.lockstep_steps = 0   # STEPs answered
        self._duration_s: float | None = None   # the loop ends this long after its first turn (None: never)
        self._status_period_s = 2.0
        self._started_s = 0.0                   # the station's clock at start()

    # ---- lifecycle -------------------------------------------------------------------------
    def start(self) -> None:
        self._started_s = self.clock()
        if isinstance(self.device, DeviceSpec):   # before any thread: the force loop in its own process
            self._force_proc = ForceProcess(self.device, self.cfg)
        self._open_link()
        if self.http_port is not None:
            period_ms = max(int(1000 / 30), 20)
            self.server = ViewServer(self.hub, self.cfg.network.http_host, self.http_port, period_ms)
        if self._force_proc is None:
            sys.setswitchinterval(0.0005)   # the force thread waits at most this long for the GIL
            self._spawn("force-loop", self._force_thread)
        self._spawn("station-loop", lambda: self._loop(_WallTurns(self)))
        if self.image_stream_url is not None or self.server is not None or self.record_path:
            self._spawn("view-loop", self._view_loop)

    def _open_link(self) -> None:
        net = self.cfg.network
        # everything this station sends is signed; what it gets may not be
        signing = None if net.signing_key_file is None else Signing(read_key(net.signing_key_file), net.signing_link_id)
        # the client's clock is the station's (late-bound: the lock-step replaces it): its COMMAND_STAMPs and its
        # TIMESYNC answers are on the same clock
        self.client = connect(self.vehicle_url, net.source_system, net.source_component,
                              target_system=self.cfg.mapping.target_system,
                              target_component=self.cfg.commands.companion_component,
                              signing=signing, clock=lambda: self.clock())
        self._conn = self.client.conn
        if signing is not None:
            log.info("vehicle link signed (key %s, link id %d)", net.signing_key_file, net.signing_link_id)
        log.info("vehicle link %s (MANUAL_CONTROL at %.0f Hz to sysid %d)", self.vehicle_url, self.cfg.mapping.rate_hz,
                 self.cfg.mapping.target_system)

    def start_lockstep(self, url: str) -> None:
        """Join the SITL's deterministic lock-step as ``operator`` (instead of :meth:`start`): the vehicle link
        opened and counted, the coordinator greeted; nothing is sent before the first STEP, no thread started.
        The station's clock becomes the step's simulated time."""
        if not isinstance(self.device, HapticDevice):
            raise ConfigError("lock-step: the device must run in the station's process (a HapticDevice)")
        if self.image_stream_url is not None or self.http_port is not None or self.record_path:
            raise ConfigError("lock-step: no operator view (image stream, web page, video) in a lock-stepped station")
        self._open_link()
        self._counted = CountedMavlink(self._conn)
        self._lockstep = LockstepClient(url, LOCKSTEP_NAME)
        self.clock = self._lockstep.clock
        if self.journal is not None:   # what pymavlink is handed in a step, what is sent, the clock's readings
            journal_link(self.journal, self._conn)
            self.clock = self.journal.clock(self._lockstep.clock, JKind.CLOCK)
            with self.journal.event(JKind.INIT):
                pass
        self._lockstep.hello({LINK_OUT: self._counted.sent})

    def start_replay(self, conn: Any, clock: Callable[[], float]) -> None:
        """For a journal's replay (:mod:`teleop.replay`, instead of :meth:`start_lockstep`): the vehicle link is
        ``conn`` (:func:`quadlink.mavlink.connection.open_replay_mavlink`), counted as in the lock-step, and the
        station's clock is ``clock`` (the journal's readings)."""
        if not isinstance(self.device, HapticDevice):
            raise ConfigError("replay: the device must run in the station's process (a HapticDevice)")
        self.client = GroundClient(conn, self.cfg.mapping.target_system, self.cfg.commands.companion_component,
                                   clock=lambda: self.clock())
        self._conn = conn
        self._counted = CountedMavlink(conn)
        self.clock = clock

    def run_turns(self, turns: Turns, duration_s: float | None = None) -> None:
        """The station's loop over ``turns`` until they end or the loop does (a journal's replay)."""
        assert self.client is not None, "start_replay() first"
        self._duration_s = duration_s
        self._loop(turns)

    def run_lockstep(self, duration_s: float | None = None, status_period_s: float = 2.0,
                     input_timeout_s: float = DEFAULT_INPUT_TIMEOUT_S) -> None:
        """Answer STEPs until stopped (Ctrl-C, quit button, script end, ``duration_s`` of simulated time); the
        last step is answered before returning. :class:`quadlink.lockstep.LockstepError`: the coordinator is
        gone or an announced datagram did not come."""
        assert self._lockstep is not None and self._counted is not None and self.client is not None and \
            isinstance(self.device, HapticDevice), "start_lockstep() first"
        self._duration_s, self._status_period_s = duration_s, status_period_s
        self._loop(_LockstepTurns(self, input_timeout_s))
        if self.error is not None:
            raise QuadlinkError(f"ground station stopped: {self.error}")

    def _loop(self, turns: Turns) -> None:
        """The station's one loop, over either event source (``turns``): the wall clock's turns every link period
        (:meth:`start`; the force loop and the view run in their own loops) or the lock-step's STEPs
        (:meth:`start_lockstep`; the force loop's ticks run here, before the step's datagrams). Per turn at time
        ``t``: the device's ticks due (lock-step), the vehicle's datagrams, the link's ticks due (MANUAL_CONTROL,
        commands, HEARTBEAT, TIMESYNC), the end checks (duration, script end, the force process), warnings and
        the status line."""
        client = self.client
        assert client is not None, "the vehicle link is opened by start() or start_lockstep()"
        link = VehicleLink(self)
        csv_log = CsvLog(self.log_csv) if self.log_csv else None
        t_first: float | None = None
        next_status = math.inf
        shown_warnings: set[str] = set()
        tel = self.telemetry
        try:
            while not self.stop_event.is_set():
                t = turns.next_time()
                if t is None:
                    continue
                if t_first is None:
                    t_first, next_status = t, t + self._status_period_s
                turns.run_device(t)
                played = self.exit_at_script_end and self.device_finished   # as far as the device has played
                tel = turns.receive(link, tel, t)
                for _ in range(turns.link_ticks_due(t, t_first)):
                    link.tick(client, t, tel, csv_log, t_first)
                # the script's end once its last presses went out (they wait for the link's next tick)
                finished = ((self._duration_s is not None and t - t_first >= self._duration_s)
                            or (played and self._buttons.empty()))
                turns.done()
                if self._force_proc is not None and not self._force_proc.alive:
                    raise QuadlinkError("the force process died (see its log above)")
                shown_warnings = self._log_warnings(shown_warnings)
                if t >= next_status:
                    next_status = t + self._status_period_s
                    log.info("%s", self.status_line())
                if finished:
                    log.info("%s at %.2f s; %s", "script finished" if self.device_finished else "duration reached",
                             t, turns.leaving)
                    break
        finally:
            if csv_log is not None:
                csv_log.close()
            self.stop_event.set()   # the station's loop is over: the others stop with it

    def receive_step(self, link: VehicleLink, tel: Telemetry, t: float, allow: int | None, what: str,
                     input_timeout_s: float) -> Telemetry:
        """Handle the companion's datagrams up to the link's count ``allow`` (None: what is there), at ``t``: a
        lock-step's or a journal's turn."""
        counted, ground = self._counted, self.client
        assert counted is not None and ground is not None
        counted.allow = allow
        state = [tel]

        def receive() -> None:
            state[0] = link._receive(ground, state[0], t)
            while link.receive_limited:
                state[0] = link._receive(ground, state[0], t)

        def pump(block_s: float) -> None:
            counted.wait_readable(block_s)
            receive()

        receive()
        wait_for_units(lambda: counted.received, allow, pump, what, input_timeout_s)
        receive()   # the last datagram's further messages (pymavlink parses one message per call)
        with self._lock:
            self._telemetry = state[0]
        return state[0]

    def _log_warnings(self, shown: set[str]) -> set[str]:
        with self._lock:   # STATUSTEXTs are logged when they arrive; the others when they appear
            warnings = {_warning_kind(w): w for w in self._warnings if not w.startswith("vehicle: ")}
        for kind in set(warnings) - shown:
            log.warning("%s", warnings[kind])
        return set(warnings)

    def _spawn(self, name: str, target: Callable[[], None]) -> None:
        def guarded() -> None:
            try:
                target()
            except Exception as exc:  # noqa: BLE001 - a dying loop must stop the station, not hang it
                log.exception("%s failed: %s", name, exc)
                self.error = exc
                self.stop_event.set()

        thread = threading.Thread(target=guarded, name=name, daemon=True)
        thread.start()
        self._threads.append(thread)

    def run(self, duration_s: float | None = None, status_period_s: float = 2.0) -> None:
        """Block until the station's loop (started by :meth:`start`) stops: Ctrl-C, quit button, script end,
        ``duration_s`` from now; it prints the status lines."""
        self._status_period_s = status_period_s
        self._duration_s = None if duration_s is None else duration_s + (self.clock() - self._started_s)
        while not self.stop_event.wait(0.1):
            pass
        if self.error is not None:
            raise QuadlinkError(f"ground station stopped: {self.error}")

    def close(self) -> None:
        self.stop_event.set()
        for thread in self._threads:
            thread.join(timeout=3.0)
        sys.setswitchinterval(self._switch_interval)
        if self._force_proc is not None:
            self._force_proc.close()
        elif isinstance(self.device, HapticDevice):
            try:
                self.device.set_force(np.zeros(3))
            finally:
                self.device.close()
        if self.server is not None:
            self.server.close()
        if self._lockstep is not None:   # after the last DONE: the coordinator sees the operator leave
            self._lockstep.close()
        if self.client is not None:
            self.client.close()

    # ---- snapshots -------------------------------------------------------------------------
    def vehicle_time_s(self) -> float | None:
        """The vehicle's clock (TELEOP_FEEDBACK time_usec, simulated time in the SITL), None before any."""
        fb = self.telemetry.feedback
        return None if fb is None else fb.time_usec * 1e-6

    @property
    def datagrams_handed(self) -> int:
        """Vehicle datagrams the counted link (lock-step or replay) has handed to the MAVLink parser so far."""
        assert self._counted is not None, "the station runs without a counted link (not lock-stepped or replayed)"
        return self._counted.handed

    @property
    def telemetry(self) -> Telemetry:
        with self._lock:
            return self._telemetry

    @property
    def force(self) -> ForceSnapshot | None:
        if self._force_proc is not None:
            return self._force_proc.snapshot()
        with self._lock:
            return self._force

    @property
    def device_finished(self) -> bool:
        if self._force_proc is not None:
            return self._force_proc.finished
        return isinstance(self.device, HapticDevice) and self.device.finished

    def force_periods_s(self) -> NDArray[np.float64]:
        """Periods of the force loop so far (s), for the jitter figure."""
        return self._force_proc.periods_s() if self._force_proc is not None else self.force_periods.periods_s()

    @property
    def command(self) -> ManualControl:
        with self._lock:
            return self._command

    def status(self) -> dict[str, Any]:
        t = self.clock()
        force = self.force
        with self._lock:
            tel, cmd, warnings, acks = self._telemetry, self._command, list(self._warnings), list(self._acks)
            delay = self._delay
        fb = tel.feedback
        ok = link_ok(fb.t_recv_s if fb else None, t, self.cfg.force.link_timeout_s)
        return {
            "link_ok": ok,
            "link": "ok" if ok else ("lost" if fb else "waiting"),
            "mode": MODE_NAMES.get(fb.mode, str(fb.mode)) if fb else "-",
            "armed": tel.armed,
            "battery_v": tel.battery_v,
            "min_obstacle_m": min_obstacle_m(tel),
            "pan_scan_on": bool(fb and fb.pan_scan_on),
            "pan_scan_hz": self._pan_scan_hz,
            "command": f"x {cmd.x:+5d} y {cmd.y:+5d} z {cmd.z:4d} r {cmd.r:+5d}",
            "force_n": [round(float(v), 3) for v in force.tau_d_n] if force else [0.0, 0.0, 0.0],
            "q_m": [round(float(v), 4) for v in force.device.q_m] if force else [0.0, 0.0, 0.0],
            "link_gain": force.link_gain if force else 0.0,
            "warnings": warnings,
            "acks": acks,
            "view_frames": self.view_frames,
            **delay.status(),
            "passivity": _passivity_status(force),
        }

    def status_line(self) -> str:
        s = self.status()
        bat = f"{s['battery_v']:.1f} V" if s["battery_v"] is not None else "- V"
        obst = f"{s['min_obstacle_m']:.2f} m" if s["min_obstacle_m"] is not None else "none"
        f = s["force_n"]
        rtt = "-" if s["rtt_ms"] is None else f"{s['rtt_ms']:.0f} ms"
        return (f"link {s['link']} rtt {rtt} | mode {s['mode']} | {'armed' if s['armed'] else 'disarmed'} | "
                f"bat {bat} | "
                f"obstacle {obst} | {s['command']} | q [{s['q_m'][0]:+.3f} {s['q_m'][1]:+.3f} {s['q_m'][2]:+.3f}] m"
                f" | force [{f[0]:+.2f} {f[1]:+.2f} {f[2]:+.2f}] N")

    # ---- force loop (1 kHz): in-process variant ------------------------------------------
    def _force_thread(self) -> None:
        assert isinstance(self.device, HapticDevice)
        run_force_loop(self.device, self.cfg, _ThreadIO(self), self.clock)

    # ---- vehicle link (50 Hz): teleop.link ---------------------------------------------------
    def _set_link_state(self, tel: Telemetry, cmd: ManualControl, t: float, delay: LinkDelay | None = None) -> None:
        """The link loop's results of one tick, published atomically to the other threads and the page."""
        ok = link_ok(tel.feedback.t_recv_s if tel.feedback else None, t, self.cfg.force.link_timeout_s)
        warnings = warnings_for(tel, ok, t, self.cfg)
        with self._lock:
            self._telemetry, self._command, self._warnings = tel, cmd, warnings
            if delay is not None:
                self._delay = delay
        self.hub.set_status(self.status())

    def _ack(self, result: CommandResult | None) -> None:
        if result is None:
            return
        (log.info if result.accepted else log.warning)("command %s", result.text)
        with self._lock:
            self._acks.append(result.text)

    # ---- view loop (camera rate): teleop.view_loop -------------------------------------------
    def _view_loop(self) -> None:
        view = OperatorView(self.cfg)
        client = CameraStreamClient(self.image_stream_url) if self.image_stream_url else None
        if client is not None:
            log.info("operator view: image stream %s", self.image_stream_url)
        video: cv2.VideoWriter | None = None
        last_render = -math.inf
        try:
            while not self.stop_event.is_set():
                frame = client.read(timeout_s=0.2) if client is not None else None
                if client is None:
                    self.stop_event.wait(0.2)
                t = self.clock()
                if frame is None:
                    if t - last_render >= 0.5:   # keep the page alive (status, force) without images
                        self._publish(view.waiting(t, self.status(), "waiting for the image stream"))
                        last_render = t
                    continue
                assert client is not None
                try:
                    meta = image_meta(frame)
                except ProtocolError as exc:   # not the companion's metadata: say so, never guess
                    self.bad_image_meta += 1
                    if self.bad_image_meta == 1 or self.bad_image_meta % 100 == 0:
                        log.error("operator image %d rejected (%d so far): %s", frame.seq, self.bad_image_meta, exc)
                    self._publish(view.waiting(t, self.status(), "image metadata rejected (see log)"))
                    client.ack(frame.seq)
                    continue
                out = view.on_image(frame, meta, self._operator_yaw_rate_cmd(), self.status())
                self._publish(out.image_bgr)
                last_render = t
                self.view_frames += 1
                if self.record_path:
                    if video is None:
                        video = open_video(self.record_path, out.image_bgr.shape[1], out.image_bgr.shape[0])
                    video.write(out.image_bgr)
                client.ack(frame.seq)
        finally:
            if client is not None:
                client.close()
            if video is not None:
                video.release()
                log.info("recorded operator view to %s", self.record_path)

    def _operator_yaw_rate_cmd(self) -> float:
        """The operator's part of the commanded yaw rate (latest TELEOP_FEEDBACK), 0 without a link."""
        fb = self.telemetry.feedback
        if fb is None or not link_ok(fb.t_recv_s, self.clock(), self.cfg.force.link_timeout_s):
            return 0.0
        return fb.yaw_rate_cmd_rad_s - fb.pan_scan_yaw_rate_rad_s

    def _publish(self, img: NDArray[np.uint8]) -> None:
        ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, self.cfg.view.jpeg_quality])
        if ok:
            self.hub.publish(buf.tobytes())


def _passivity_status(force: ForceSnapshot | None) -> dict[str, float] | None:
    """The force port's energy account for ``status.json`` (teleop.passivity), None before the first tick."""
    p = force.passivity if force is not None else None
    if p is None:
        return None
    return {"observed_j": round(p.observed_j, 5), "min_observed_j": round(p.min_observed_j, 5),
            "output_j": round(p.output_j, 5), "dissipated_j": round(p.dissipated_j, 5),
            "damping_n_s_m": round(p.damping_n_s_m, 3)}


def _warning_kind(text: str) -> str:
    """A warning without its numbers ('OBSTACLE 0.41 m' and 'OBSTACLE 0.39 m' are one warning)."""
    return re.sub(r"[-+]?\d+(\.\d+)?", "#", text)


class _ThreadIO:
    """The in-process force loop's link to the station."""

    def __init__(self, station: Station) -> None:
        self.station = station

    def motion(self) -> MotionInput | None:
        return self.station._motion

    def publish(self, snapshot: ForceSnapshot) -> None:
        with self.station._lock:
            self.station._force = snapshot

    def button(self, name: str) -> None:
        try:
            self.station._buttons.put_nowait(name)
        except queue.Full:
            log.warning("button %s dropped (queue full)", name)

    def record_period(self, t_s: float) -> None:
        self.station.force_periods.record(t_s)

    def stop_requested(self) -> bool:
        return self.station.stop_event.is_set()


class Turns(Protocol):
    """An event source of :meth:`Station._loop`: the wall clock's turns, the lock-step's STEPs or a journal's
    turns (:mod:`teleop.replay`)."""

    leaving: str   # what the end of the loop means for it (logged)

    def next_time(self) -> float | None:
        """Wait for the next turn; its time on the station's clock (None: no turn this time)."""

    def run_device(self, t: float) -> None:
        """The device's and the force law's ticks due up to ``t`` (if they run in this loop)."""

    def receive(self, link: VehicleLink, tel: Telemetry, t: float) -> Telemetry:
        """The vehicle's datagrams of this turn, handled at ``t``."""

    def link_ticks_due(self, t: float, t_first: float) -> int:
        """How many link ticks are due at ``t`` (the loop's first turn at ``t_first``)."""

    def done(self) -> None:
        """The turn is over."""


class _WallTurns:
    """Free-running: a turn every link period on the station's clock (more than ten periods late, the schedule
    restarts from now), the datagrams readable then, one link tick per turn. The force loop (a thread or the force
    process) and the view run in their own loops."""

    leaving = "stopping"

    def __init__(self, station: Station) -> None:
        self.station = station
        self.period_s = 1.0 / station.cfg.mapping.rate_hz
        self._next_s: float | None = None

    def next_time(self) -> float | None:
        st = self.station
        if self._next_s is None:
            self._next_s = st.clock()
        else:
            self._next_s += self.period_s
            if st.clock() - self._next_s > 10 * self.period_s:
                self._next_s = st.clock()
            if st.stop_event.wait(max(self._next_s - st.clock(), 0.0)):
                return None
        return st.clock()

    def run_device(self, t: float) -> None:
        pass

    def receive(self, link: VehicleLink, tel: Telemetry, t: float) -> Telemetry:
        assert self.station.client is not None
        return link._receive(self.station.client, tel, t)

    def link_ticks_due(self, t: float, t_first: float) -> int:
        return 1

    def done(self) -> None:
        pass


class SteppedTicks:
    """The ticks of a stepped station (the lock-step's, a journal's replay): the device's and the force law's at
    ``force_rate_hz`` and the link's at ``mapping.rate_hz``, both of the steps' simulated time, counted from the
    first step (tick i is due at ``t_first + i / rate``)."""

    def __init__(self, station: Station) -> None:
        assert isinstance(station.device, HapticDevice)
        self.force = ForceLoop(station.device, station.cfg, _ThreadIO(station))
        self.force_rate_hz = station.cfg.device.force_rate_hz
        self.link_period_s = 1.0 / station.cfg.mapping.rate_hz
        self.n_force = self.n_link = 0   # ticks run so far
        self.t_first: float | None = None

    def first(self, t: float) -> None:
        if self.t_first is None:
            self.t_first = t

    def run_device(self, t: float) -> None:
        assert self.t_first is not None
        while self.t_first + self.n_force / self.force_rate_hz <= t + _EPS_S:
            self.force.tick(self.t_first + self.n_force / self.force_rate_hz)
            self.n_force += 1

    def link_ticks_due(self, t: float, t_first: float) -> int:
        due = 0
        while t_first + (self.n_link + due) * self.link_period_s <= t + _EPS_S:
            due += 1
        self.n_link += due
        return due


class _LockstepTurns:
    """The deterministic lock-step: a turn per STEP of the SITL, at its simulated time ``t``: the force loop's ticks
    up to ``t`` at ``force_rate_hz`` of simulated time, exactly the companion datagrams the step announces, the
    link's ticks due at ``mapping.rate_hz`` of simulated time, then DONE. With a journal, each turn is its STEP
    event."""

    leaving = "leaving the lock-step"

    def __init__(self, station: Station, input_timeout_s: float) -> None:
        assert station._lockstep is not None and station._counted is not None
        self.station = station
        self.client, self.counted = station._lockstep, station._counted
        self.input_timeout_s = input_timeout_s
        self.ticks = SteppedTicks(station)
        self.step: Step | None = None

    def next_time(self) -> float | None:
        self.step = self.client.next_step()
        if self.step is None:
            return None
        self.ticks.first(self.step.t_s)
        if self.station.journal is not None:
            self.station.journal.begin(JKind.STEP, encode_step(self.step.t_s))
        return self.step.t_s

    def run_device(self, t: float) -> None:
        self.ticks.run_device(t)

    def receive(self, link: VehicleLink, tel: Telemetry, t: float) -> Telemetry:
        assert self.step is not None
        return self.station.receive_step(link, tel, t, self.step.count(LINK_IN),
                                         f"{LINK_IN} at step {self.step.index}", self.input_timeout_s)

    def link_ticks_due(self, t: float, t_first: float) -> int:
        return self.ticks.link_ticks_due(t, t_first)

    def done(self) -> None:
        self.client.done({LINK_OUT: self.counted.sent})
        self.station.lockstep_steps += 1
        if self.station.journal is not None:
            self.station.journal.end()

"""The bridge process: MK ports and MAVLink endpoints wired to the pure :class:`~firmware_bridge.autopilot.Autopilot`.

Concurrency model: a few reader threads (MK port 1, MK port 2, one per MAVLink endpoint;
:mod:`firmware_bridge.links`) that only read with a timeout and put what they got on one queue; the main
thread owns the autopilot and does all decoding, control and writing. Every wait has a timeout;
:meth:`BridgeDaemon.stop` (or Ctrl-C in the CLI) ends all threads within ~0.2 s.

Time (the system contract): the board's IMU sample counter is the clock. Sample k is at board
time k * 2 ms (the 12-bit counter is unwrapped, and aligned with ``BoardStatus.imu_sample_count``);
the 100 Hz control step runs on every 5th sample, so in lock-step SITL the bridge answers each 10 ms
chunk with exactly one setpoint. Only while the IMU stream is silent does a wall-clock fallback
advance time and clock the control step (failsafes must still run).

Deterministic lock-step (``--lockstep tcp://HOST:PORT``, :mod:`quadlink.lockstep`): the bridge joins the SITL's
coordinator as participant ``"bridge"`` and its one loop (:meth:`BridgeDaemon.run`) takes its inputs from the
coordinator's steps instead of the readers' queue. On ``STEP k`` it waits (bounded) until the readers have
delivered what the step announces (companion datagrams on MAVLink endpoint 0, MK port-1 and port-2 bytes), holds
back companion datagrams that came early, handles the step's inputs in a fixed order (endpoint 0, the other
endpoints, MK port 1, MK port 2, whose IMU samples clock the control step: one setpoint per chunk), runs the
housekeeping once and answers ``DONE k`` with what it has sent (MK port-1 bytes, endpoint-0 datagrams). Its clock
is the step's simulated time, not the wall clock: the board-time fallback, the telemetry streams, the refusal and
version-request timers and the parameter saving all run on it, the IMU never goes stale, and SYSTEM_TIME carries
no Unix time (0, "unknown"), so the same inputs give the same bytes on any machine. Nothing is written on MK port
1 or endpoint 0 outside a step (only the main thread writes). The reader threads still stamp their reads with the
wall clock, which only feeds the in-process latency statistic."""

from __future__ import annotations

import collections
import contextlib
import functools
import logging
import math
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from firmware_bridge.autopilot import Autopilot, BoardCommand, Outbound
from firmware_bridge.journal import JournalWriter, encode_input
from firmware_bridge.journal import Kind as JKind
from firmware_bridge.links import LinkReaders, SentDatagrams, StreamHolder
from firmware_bridge.params import DEFAULT_PARAMS_PATH, ParamTable, load_param_file, save_param_file
from firmware_bridge.step_inputs import (
    COMPANION_ENDPOINT,
    LINK_COMPANION_IN,
    LINK_COMPANION_OUT,
    LINK_MK_CMD_IN,
    LINK_MK_IMU_IN,
    LINK_MK_OUT,
    LOCKSTEP_NAME,
    StepInputs,
)
from firmware_bridge.telemetry import encode_sw_version
from quadlink.errors import ConfigError, LinkError, ProtocolError
from quadlink.links import ByteStream, open_stream
from quadlink.lockstep import (
    DEFAULT_INPUT_TIMEOUT_S,
    LockstepClient,
    LockstepEnded,
    LockstepError,
    wait_for_units,
)
from quadlink.mavlink import mavlink
from quadlink.mavlink.connection import open_mavlink
from quadlink.mavlink.security import SecurityConfig, enable_signing
from quadlink.mavlink.tlog import TlogWriter
from quadlink.mk import messages as mk
from quadlink.mk.protocol import ADDR_FC, FrameDecoder, encode_frame
from quadlink.realtime import MAX_PRIORITY
from quadlink.vehicle import VehicleConfig

log = logging.getLogger(__name__)

IMU_PERIOD_S = 0.002
CONTROL_DECIMATION = 5  # 500 Hz IMU / 5 = 100 Hz setpoints
# an IMU sample whose bytes were read this long before its turn: the bridge is behind its IMU (a starved CPU). It
# does not queue on: the samples are merged, as many as it is behind, at most IMU_MERGE_MAX (see _on_imu_frame;
# under IMU_DT_MAX_S, the estimators' longest step). Never in lock-step
IMU_BEHIND_S = 0.02
IMU_MERGE_MAX = 25   # 50 ms
COUNTER_MODULO = 4096
TICK_S = 0.01  # autopilot.tick period (telemetry streams, failsafes, version requests, parameter saving)
# lock-step: steps are 10 ms of simulated time apart, but t_k - t_(k-1) in floating point may be a hair under
# 0.01 s; without this slack the tick would skip steps (deterministically, but irregularly)
LOCKSTEP_TICK_SLACK_S = 1e-6


@dataclass(frozen=True)
class BridgeConfig:
    """``configs/bridge.yaml``; the CLI's flags override the links and ids."""

    mk_cmd_url: str = "socket://127.0.0.1:5760"
    mk_imu_url: str = "socket://127.0.0.1:5761"
    mavlink_urls: tuple[str, ...] = ("udpout:127.0.0.1:14540", "udpout:127.0.0.1:14550")
    sysid: int = 1
    compid: int = 1
    vehicle: str = "vehicle"
    params_file: str = str(DEFAULT_PARAMS_PATH)
    imu_stale_s: float = 0.25  # no IMU for this long (wall) -> wall-clock fallback for the control step
    reconnect_interval_s: float = 1.0
    status_log_interval_s: float = 10.0
    version_request_attempts: int = 5
    realtime_priority: int = 0  # >0: SCHED_FIFO at this priority (1-99) for the IMU path's latency tail on a
                                # busy board (needs CAP_SYS_NICE; refused -> a warning, normal priority)
    # signing on the ground-station links (indices into mavlink_urls; link 0, the companion's, is internal);
    # the sender allowlist applies on every link (the companion forwards ground stations' commands)
    security: SecurityConfig = field(default_factory=SecurityConfig)
    ground_station_links: tuple[int, ...] = (1,)
    # the deterministic lock-step (quadlink.lockstep): the SITL's coordinator, tcp://HOST:PORT; None: free-running
    lockstep_url: str | None = None

    def __post_init__(self) -> None:
        if not 1 <= self.sysid <= 255 or not 1 <= self.compid <= 255:
            raise ValueError("sysid and compid must be 1..255")
        if not 0 <= self.realtime_priority <= MAX_PRIORITY:
            raise ValueError(f"realtime_priority must be 0 (off) or 1..{MAX_PRIORITY}")


@dataclass
class BridgeStats:
    imu_samples: int = 0
    imu_gaps: int = 0
    imu_merged: int = 0       # samples merged into a later one (the bridge behind its IMU)
    setpoints_sent: int = 0
    mavlink_in: int = 0
    mavlink_out: int = 0
    send_errors: int = 0
    wall_clock_steps: int = 0
    refused_senders: int = 0  # state-changing messages from system ids not on the allowlist


class _Stopped(Exception):
    """:meth:`BridgeDaemon.stop` was called while a lock-step step waited for its inputs."""


class BridgeDaemon:
    """The bridge process. ``clock`` is the wall clock (seconds, monotonic): the daemon's time source when
    free-running; in lock-step mode (``config.lockstep_url``) the daemon's :attr:`clock` is the current step's
    simulated time instead, and the wall clock only bounds waits and stamps reads for the latency statistic.

    ``journal``: every input the main thread handles, every housekeeping turn, the clocks read and the bytes written
    in them (:mod:`firmware_bridge.journal`). ``daemon_clock``: the daemon's clock whatever the mode (a journal's
    replay gives back the recorded readings). ``tlog``: every packet sent on the ground-station links
    (``config.ground_station_links``), as sent: what a ground station there receives, lossless."""

    def __init__(self, config: BridgeConfig, vehicle: VehicleConfig, params_path: Path | None = None,
                 clock: Callable[[], float] = time.monotonic, unix_clock: Callable[[], float] = time.time,
                 stream_opener: Callable[[str], ByteStream] = open_stream,
                 mavlink_opener: Callable[..., Any] = open_mavlink, journal: JournalWriter | None = None,
                 daemon_clock: Callable[[], float] | None = None, tlog: TlogWriter | None = None) -> None:
        self.config = config
        self.vehicle = vehicle
        self.lockstep_mode = config.lockstep_url is not None
        self.journal = journal
        self._reader_clock = clock   # the reader threads' (never journaled: only the main thread writes the journal)
        # what the ground-station links were sent, as sent; stamped on the Unix clock, never journaled (the stamps
        # change nothing the bridge does)
        self.tlog = tlog
        self._tlog_clock = unix_clock
        self._step_t_s = 0.0  # lock-step: the current step's simulated time
        own_clock = daemon_clock or (self._step_clock if self.lockstep_mode else clock)
        if journal is not None:
            clock, own_clock = journal.clock(clock, JKind.WALL), journal.clock(own_clock, JKind.CLOCK)
            unix_clock = journal.clock(unix_clock, JKind.UNIX)
        self._wall_clock = clock
        self.clock: Callable[[], float] = own_clock
        with self._event(JKind.INIT):
            self._init_state(config, vehicle, params_path, unix_clock, stream_opener, mavlink_opener)

    def _event(self, kind: JKind,
               payload: Callable[[], bytes] | None = None) -> contextlib.AbstractContextManager[None]:
        """The journal's record of one event (a no-op without a journal)."""
        if self.journal is None:
            return contextlib.nullcontext()
        return self.journal.event(kind, payload() if payload is not None else b"")

    def _init_state(self, config: BridgeConfig, vehicle: VehicleConfig, params_path: Path | None,
                    unix_clock: Callable[[], float], stream_opener: Callable[[str], ByteStream],
                    mavlink_opener: Callable[..., Any]) -> None:
        self.params_path = (params_path or Path(config.params_file)).expanduser()
        self.params = ParamTable(load_param_file(self.params_path))
        # lock-step: no wall-clock Unix time in SYSTEM_TIME (0 is MAVLink's "unknown"), or flights would differ
        self.autopilot = Autopilot(vehicle, self.params, config.sysid, config.compid,
                                   unix_clock=None if self.lockstep_mode else unix_clock)
        self._stream_opener = stream_opener
        self._mavlink_opener = mavlink_opener
        self.stats = BridgeStats()
        # IMU bytes read -> HIGHRES_IMU sent, inside this process (the bridge's own share of the latency)
        self._imu_latency_s: collections.deque[float] = collections.deque(maxlen=5000)
        self._queue: queue.Queue[tuple[Any, ...]] = queue.Queue(maxsize=20000)
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self.cmd: StreamHolder | None = None
        self.imu: StreamHolder | None = None
        self.mavlinks: list[Any] = []
        # lock-step
        self.lockstep: LockstepClient | None = None
        self._step_inputs = StepInputs()
        self._companion_sent: SentDatagrams | None = None
        self._tick_slack_s = LOCKSTEP_TICK_SLACK_S if self.lockstep_mode else 0.0
        self._cmd_decoder = FrameDecoder()
        self._imu_decoder = FrameDecoder()
        self._mk_dropped_seen = 0
        # clock state
        self._imu_index: int | None = None  # unwrapped sample index
        # while behind: the samples merged so far, and the sums of their accel and gyro
        self._merged_n = 0
        self._merged_sum = np.zeros(6)
        self._last_imu_wall: float | None = None
        self._now_s = 0.0
        self._time_offset_s = 0.0
        self._wall_origin = self.clock()
        self._last_control_wall = -1.0
        self._last_tick_wall = -1.0
        self._control_block = -1
        self._seq = 0
        self._version_requests = 0
        self._last_version_request = -1e9
        self._last_status_log = self.clock()
        self._last_param_save = -1e9
        self.allowlist = config.security.allowlist(config.sysid)
        self._refusal_next_s: dict[tuple[int, str], float] = {}

    # ------------------------------------------------------------------ lifecycle
    def open(self) -> None:
        """Open every link (raises :class:`LinkError` naming the first that fails) and start the readers."""
        c = self.config
        log.info("MK port 1 (commands/telemetry): %s", c.mk_cmd_url)
        self.cmd = StreamHolder(c.mk_cmd_url, self._stream_opener)
        log.info("MK port 2 (IMU): %s", c.mk_imu_url)
        try:
            self.imu = StreamHolder(c.mk_imu_url, self._stream_opener)
        except LinkError:
            self.cmd.drop()
            raise
        try:
            for url in c.mavlink_urls:
                self.mavlinks.append(self._mavlink_opener(url, c.sysid, c.compid))
            self.enable_signing()
        except (LinkError, ConfigError):
            self.close()
            raise
        log.info("MAVLink endpoints: %s (sysid %d compid %d)", ", ".join(c.mavlink_urls), c.sysid, c.compid)
        log.info("parameters: %s (%d)", self.params_path, len(self.params))
        if c.lockstep_url is not None:
            self._join_lockstep(c.lockstep_url)
        readers = LinkReaders(self._put, self._stop, self._reader_clock, c.reconnect_interval_s)
        self._threads = readers.start(self.cmd, self.imu, self.mavlinks)

    def _join_lockstep(self, url: str) -> None:
        """Register with the coordinator before anything is sent (the counts start at what was sent: zero)."""
        if len(self.mavlinks) > COMPANION_ENDPOINT:
            self._companion_sent = SentDatagrams(self.mavlinks[COMPANION_ENDPOINT])
        try:
            self.lockstep = LockstepClient(url, LOCKSTEP_NAME)
            self.lockstep.hello(self.lockstep_sent())
        except LinkError:  # LockstepError, or a bad URL
            self.close()
            raise
        log.info("deterministic lock-step: joined %s as %r; the clock is the simulated time", url, LOCKSTEP_NAME)

    def enable_signing(self) -> None:
        """MAVLink 2 signing (pymavlink's, on each link's own codec: what it sends is signed, what it receives
        checked, replays refused) on the ground-station links, when a key is configured."""
        c = self.config
        key = c.security.key()
        if key is None:
            return
        signed = [i for i in c.ground_station_links if 0 <= i < len(self.mavlinks)]
        for i in signed:
            enable_signing(self.mavlinks[i].mav, key, c.security.require_signing, link_id=i)
        log.info("MAVLink 2 signing (%s) on %s", "required" if c.security.require_signing else "optional",
                 ", ".join(c.mavlink_urls[i] for i in signed) or "no link")

    def stop(self) -> None:
        """Ask the daemon to end; safe from a signal handler (no lock taken once a stop is pending)."""
        if not self._stop.is_set():
            self._stop.set()

    def close(self) -> None:
        self._stop.set()
        if self.lockstep is not None:
            self.lockstep.close()
        for t in self._threads:
            t.join(timeout=1.0)
        # a last disarmed setpoint is not sent on purpose: the board's own link-loss failsafe handles a
        # bridge that goes away in flight, and a disarm here would cut motors in the air
        for holder in (self.cmd, self.imu):
            if holder is not None:
                holder.drop()
        for conn in self.mavlinks:
            try:
                conn.close()
            except OSError:
                pass
        self._save_params(force=True)

    # ------------------------------------------------------------------ the reader threads' queue
    def _put(self, item: tuple[Any, ...]) -> None:
        try:
            self._queue.put(item, timeout=0.1)
        except queue.Full:
            log.warning("bridge input queue full; dropping %s input", item[0])

    # ------------------------------------------------------------------ the loop
    def run(self, duration_s: float | None = None) -> None:
        """The one loop, whatever the event source: take the next inputs (:meth:`_next_inputs`: what the readers
        queued, or the lock-step's STEP), handle each, run one housekeeping turn, tell the source (:meth:`_done`);
        until :meth:`stop`, ``duration_s`` of the daemon's clock (in lock-step: simulated time), or the
        simulation's end. Lock-step: :class:`LockstepError` when the coordinator is lost (closed without an end
        message) or an announced input did not come. A journal's replay hands the same handlers their events
        (:mod:`firmware_bridge.replay`)."""
        end = None if duration_s is None else self.clock() + duration_s
        try:
            while not self._stop.is_set():
                inputs = self._next_inputs()
                if inputs is None:   # a lock-step wait slice passed without a STEP: look at the stop flag again
                    continue
                for item in inputs:
                    self.handle_input(item)
                self.housekeeping_turn()
                self._done()
                if end is not None and self.clock() >= end:
                    break
        except _Stopped:
            pass
        except LockstepEnded as exc:
            log.info("lock-step: %s", exc)
        except LockstepError as exc:
            client = self.lockstep
            log.warning("lock-step ended at step %s: %s",
                        client.step.index if client is not None and client.step is not None else "(none)", exc)
            raise
        finally:
            if self.lockstep is not None:
                self.lockstep.close()

    def _next_inputs(self) -> list[tuple[Any, ...]] | None:
        """The inputs of the next turn. Free-running: the item the readers queued within 5 ms, if any. Lock-step:
        the next STEP's inputs, each link's up to its announced count (waiting, bounded, for those in flight), in
        the canonical order, its time the daemon's clock; None when no STEP came within a wait slice."""
        if self.lockstep is None:
            try:
                return [self._queue.get(timeout=0.005)]
            except queue.Empty:
                return []
        step = self.lockstep.next_step()  # None after STEP_WAIT_SLICE_S: look at the stop flag again
        if step is None:
            return None
        self._step_t_s = step.t_s
        wait = functools.partial(wait_for_units, pump=self._pump, timeout_s=DEFAULT_INPUT_TIMEOUT_S,
                                 clock=self._wall_clock)
        for link, what in ((LINK_COMPANION_IN, "datagrams on MAVLink endpoint 0"),
                           (LINK_MK_CMD_IN, "bytes on MK port 1"), (LINK_MK_IMU_IN, "bytes on MK port 2")):
            wait(functools.partial(self._step_inputs.received, link), step.count(link),
                 what=f"step {step.index}: {link} {what}")
        self._pump(0.0)  # what else has arrived (the endpoints outside the lock-step)
        return self._step_inputs.take(step)

    def _done(self) -> None:
        """Lock-step: DONE for the step, with what was sent on the lock-step's links."""
        if self.lockstep is not None:
            self.lockstep.done(self.lockstep_sent())

    # ------------------------------------------------------------------ the deterministic lock-step
    def _step_clock(self) -> float:
        """The lock-step clock: the current step's simulated time (0 before the first step)."""
        return self._step_t_s

    def lockstep_sent(self) -> dict[str, int]:
        """Units sent so far on the bridge's lock-step output links (cumulative; see :mod:`quadlink.lockstep`)."""
        return {LINK_MK_OUT: self.cmd.bytes_written if self.cmd is not None else 0,
                LINK_COMPANION_OUT: self._companion_sent.count if self._companion_sent is not None else 0}

    def _pump(self, block_s: float) -> None:
        """Sort what the readers queued into the step inputs, waiting up to ``block_s`` for the first item;
        errors (``link``, ``mavbad``) are handled as they come."""
        if self._stop.is_set():
            raise _Stopped
        try:
            item = self._queue.get(timeout=block_s) if block_s > 0 else self._queue.get_nowait()
        except queue.Empty:
            return
        while True:
            if not self._step_inputs.add(item):
                self.handle_input(item)
            try:
                item = self._queue.get_nowait()
            except queue.Empty:
                return

    # ------------------------------------------------------------------ handling
    def handle_input(self, item: tuple[Any, ...]) -> None:
        """One item of the readers' queue (both loops and a journal's replay come through here)."""
        with self._event(JKind.INPUT, lambda: encode_input(item)):
            self._dispatch(item)

    def housekeeping_turn(self) -> None:
        """One turn of the periodic tasks (both loops and a journal's replay come through here)."""
        with self._event(JKind.HOUSEKEEPING):
            self._housekeeping()

    def attach_links(self, mk_cmd: Any, mavlinks: list[Any]) -> None:
        """Links opened elsewhere instead of :meth:`open`'s, with no reader threads: MK port 1 (``write(data)
        -> bool``, ``drop()``, ``bytes_written``) and the MAVLink endpoints (``.mav``, ``write``, ``close``), in
        :attr:`BridgeConfig.mavlink_urls`' order. A journal's replay hands the events in itself."""
        if self.cmd is not None or self.mavlinks:
            raise RuntimeError("attach_links: the bridge's links are already open")
        self.cmd, self.mavlinks = mk_cmd, list(mavlinks)

    def _dispatch(self, item: tuple[Any, ...]) -> None:
        kind = item[0]
        if kind == "imu":
            for frame in self._imu_decoder.feed(item[1]):
                if frame.command == mk.ImuSample.COMMAND:
                    self._on_imu_frame(frame.payload, item[2])
            self._count_mk_drops()
        elif kind == "cmd":
            for frame in self._cmd_decoder.feed(item[1]):
                self._on_cmd_frame(frame)
            self._count_mk_drops()
        elif kind == "mav":
            conn = self.mavlinks[item[1]]
            try:
                msgs = conn.mav.parse_buffer(item[2]) or []
            except Exception as exc:  # noqa: BLE001 - pymavlink raises bare MAVError/struct.error/...: never fatal
                self.autopilot.note_malformed("mavlink_bad", self.now_s(), f"{type(exc).__name__}: {exc}")
                msgs = []
            for msg in msgs:
                self.stats.mavlink_in += 1
                if msg.get_type() != "BAD_DATA" and not self.allowlist.permits(msg):
                    self._send(self._refuse_sender(msg, item[1]))
                    continue
                self._send(self.autopilot.handle_mavlink(self.now_s(), msg, item[1]))
        elif kind == "mavbad":
            self.autopilot.note_malformed("mavlink_bad", self.now_s(), item[2])
        elif kind == "link":
            log.warning("MK %s link: %s", item[1], item[2])
            if "reconnected" in item[2] and item[1] == "cmd":
                self._version_requests = 0

    def _refuse_sender(self, msg: Any, link: int) -> list[Outbound]:
        """A state-changing message from a system id not on the allowlist (issue 16: a forced disarm from sysid
        77 was accepted): not executed; a command gets COMMAND_ACK DENIED, the sender a STATUSTEXT every 2 s."""
        self.stats.refused_senders += 1
        mav, src, kind = self.autopilot.mav, msg.get_srcSystem(), msg.get_type()
        out: list[Outbound] = []
        if kind in ("COMMAND_LONG", "COMMAND_INT"):
            out.append(Outbound(mav.command_ack_encode(msg.command, mavlink.MAV_RESULT_DENIED, 0, 0, src,
                                                       msg.get_srcComponent()), link))
        now = self.clock()
        if now >= self._refusal_next_s.get((src, kind), -1.0):
            self._refusal_next_s[(src, kind)] = now + 2.0
            log.warning("%s from sysid %d refused (not on the allowlist)", kind, src)
            out.append(Outbound(mav.statustext_encode(mavlink.MAV_SEVERITY_WARNING,
                                                      f"{kind} from sysid {src} refused".encode()[:50]), link))
        return out

    def _count_mk_drops(self) -> None:
        dropped = self._cmd_decoder.stats.frames_dropped + self._imu_decoder.stats.frames_dropped
        while self._mk_dropped_seen < dropped:
            self._mk_dropped_seen += 1
            self.autopilot.note_malformed("mk_bad", self.now_s(), "MK frame dropped by the decoder")

    def now_s(self) -> float:
        """Board time: the last IMU sample's time, advanced by the wall clock only while the IMU is silent.

        Time handed to the autopilot never goes back: after a silent spell the board time carries the
        offset the wall clock added (``_time_offset_s``), so timers stay continuous.
        """
        wall = self.clock()
        if self._imu_index is None:
            now = wall - self._wall_origin
        else:
            now = self._imu_index * IMU_PERIOD_S + self._time_offset_s
            assert self._last_imu_wall is not None
            if not self.lockstep_mode and wall - self._last_imu_wall > self.config.imu_stale_s:
                now += wall - self._last_imu_wall
        if now < self._now_s:
            self._time_offset_s += self._now_s - now
            now = self._now_s
        self._now_s = now
        return now

    def _on_imu_frame(self, payload: bytes, read_wall: float) -> None:
        try:
            sample = mk.ImuSample.unpack(payload)
        except (ProtocolError, ValueError) as exc:
            self.autopilot.note_malformed("mk_bad", self.now_s(), f"IMU frame: {exc}")
            return
        counter = sample.sample_counter
        if self._imu_index is None:
            status = self.autopilot.board_status
            base = status.imu_sample_count if status is not None else counter
            self._imu_index = _align(base, counter)
        else:
            delta = (counter - self._imu_index) % COUNTER_MODULO
            if delta == 0:
                self.autopilot.note_malformed("mk_bad", self.now_s(), "repeated IMU sample")
                return
            if delta > 1:
                self.stats.imu_gaps += 1
            self._imu_index += delta
        self._last_imu_wall = self.clock()
        self.stats.imu_samples += 1
        imu_cfg = self.vehicle.imu
        accel, gyro = sample.accel_m_s2(imu_cfg), sample.gyro_rad_s(imu_cfg)
        lag_s = 0.0 if self.lockstep_mode else self._wall_clock() - read_wall
        if lag_s > IMU_BEHIND_S or self._merged_n:
            # behind its IMU the bridge would fly on data ever older (held to 0.15 core it queued 4 s of it): the
            # samples are merged, as many as it is behind (at least a control period's, at most IMU_MERGE_MAX),
            # into their mean rate and specific force at the last one's time (the estimators integrate over the
            # stamps' interval; the companion integrates HIGHRES_IMU by stamp too), estimated, streamed and
            # controlled once; back in time, what was merged goes with the next sample and each runs again
            self._merged_sum[:3] += accel
            self._merged_sum[3:] += gyro
            self._merged_n += 1
            want = min(IMU_MERGE_MAX, max(CONTROL_DECIMATION, round(lag_s / IMU_PERIOD_S)))
            if lag_s > IMU_BEHIND_S and self._merged_n < want:
                return
            self.stats.imu_merged += self._merged_n - 1
            mean = self._merged_sum / self._merged_n
            accel, gyro = mean[:3], mean[3:]
            self._merged_n = 0
            self._merged_sum = np.zeros(6)
        now = self.now_s()
        out = self.autopilot.on_imu(now, self._imu_index * 2000, accel, gyro)
        self._send(out)
        if out:
            self._imu_latency_s.append(self._wall_clock() - read_wall)
        block = self._imu_index // CONTROL_DECIMATION
        if block != self._control_block:
            self._control_block = block
            self._control(now)

    def _on_cmd_frame(self, frame: Any) -> None:
        now = self.now_s()
        try:
            if frame.command == mk.BoardStatus.COMMAND:
                status = mk.BoardStatus.unpack(frame.payload)
                if self._imu_index is not None and \
                        abs(status.imu_sample_count - self._imu_index) > COUNTER_MODULO // 2:
                    self._imu_index = _align(status.imu_sample_count, self._imu_index % COUNTER_MODULO)
                self._send(self.autopilot.on_board_status(now, status))
            elif frame.command == mk.BaroAltitude.COMMAND:
                baro = mk.BaroAltitude.unpack(frame.payload)
                self.autopilot.on_board_baro(baro.altitude_m, baro.valid and not baro.saturated, baro.climb_m_s)
            elif frame.command == mk.Version.COMMAND:
                version = mk.Version.unpack(frame.payload)
                text = f"FlightCtrl {version.version_str} (protocol {version.proto_major}.{version.proto_minor})"
                self._version_requests = self.config.version_request_attempts  # done
                self.autopilot.on_board_version(
                    text, encode_sw_version(version.sw_major, version.sw_minor, version.sw_patch))
        except (ProtocolError, ValueError) as exc:
            self.autopilot.note_malformed("mk_bad", now, f"'{frame.command}' frame: {exc}")

    def _control(self, now: float) -> None:
        command = self.autopilot.control_step(now)
        self._write_setpoint(command)
        self._last_control_wall = self.clock()

    def _write_setpoint(self, command: BoardCommand) -> None:
        assert self.cmd is not None
        try:
            sp = mk.AttitudeSetpoint(command.roll_rad, command.pitch_rad, command.yaw_rate_rad_s, command.thrust,
                                     command.armed, self._seq)
            frame = encode_frame(ADDR_FC, sp.COMMAND, sp.pack())
        except (ProtocolError, ValueError) as exc:
            log.error("cannot encode setpoint %s: %s", command, exc)
            return
        if self._write_mk(frame):
            self.stats.setpoints_sent += 1
            self._seq = (self._seq + 1) % 256

    def _housekeeping(self) -> None:
        wall = self.clock()
        # wall-clock fallback: the IMU went silent (or never spoke while we are armed); failsafes must run.
        # Not before the first sample otherwise, so a lock-step SITL gets exactly one setpoint per chunk.
        # Never in the deterministic lock-step: simulated time only passes with the SITL's chunks, and their
        # IMU samples clock the control step.
        if self.lockstep_mode:
            imu_silent = False
        elif self._last_imu_wall is None:
            imu_silent = self.autopilot.armed_cmd
        else:
            imu_silent = wall - self._last_imu_wall > self.config.imu_stale_s
        if imu_silent and wall - self._last_control_wall >= 0.01:
            self.stats.wall_clock_steps += 1
            self._control(self.now_s())
        if wall - self._last_tick_wall >= TICK_S - self._tick_slack_s:
            self._last_tick_wall = wall
            self._send(self.autopilot.tick(self.now_s()))
            self._request_version(wall)
            self._save_params()
        if wall - self._last_status_log >= self.config.status_log_interval_s:
            self._last_status_log = wall
            ap = self.autopilot
            p50, p99 = self.imu_latency_ms()
            log.info("t=%.1fs mode %s armed %s in_air %s odom %s board %s | imu %d (gaps %d, merged %d) setpoints %d "
                     "mav in %d out %d | bad mav %d mk %d | odometry gated %d by the drag %d (off it at most %.2f m/s) "
                     "| imu->mavlink in-process p50 %.3f p99 %.3f ms",
                     self.now_s(), ap.mode.name, ap.armed, ap.in_air, ap.odom_ok, ap.board_link_ok,
                     self.stats.imu_samples, self.stats.imu_gaps, self.stats.imu_merged, self.stats.setpoints_sent,
                     self.stats.mavlink_in,
                     self.stats.mavlink_out, ap.counters["mavlink_bad"], ap.counters["mk_bad"],
                     ap.counters["odometry_gated"], ap.counters["odometry_drag_gated"],
                     ap.state.drag_disagreement_max_m_s, p50, p99)

    def imu_latency_ms(self) -> tuple[float, float]:
        """p50 and p99 (ms) of IMU bytes read -> HIGHRES_IMU handed to the sockets, last 5000 samples."""
        if not self._imu_latency_s:
            return math.nan, math.nan
        p50, p99 = np.percentile(np.fromiter(self._imu_latency_s, float), [50, 99]) * 1e3
        return float(p50), float(p99)

    def _request_version(self, wall: float) -> None:
        if self._version_requests >= self.config.version_request_attempts or wall - self._last_version_request < 2.0:
            return
        assert self.cmd is not None
        self._last_version_request = wall
        self._version_requests += 1
        self._write_mk(encode_frame(ADDR_FC, mk.VersionRequest.COMMAND, mk.VersionRequest().pack()))
        if self._version_requests == self.config.version_request_attempts:
            log.warning("board did not answer the version request (%d tries)", self._version_requests)

    def _save_params(self, force: bool = False) -> None:
        wall = self.clock()
        if self.params.dirty and (force or wall - self._last_param_save > 1.0):
            try:
                save_param_file(self.params_path, self.params.values)
                self.params.dirty = False
                self._last_param_save = wall
            except OSError as exc:
                log.error("cannot save parameters to %s: %s", self.params_path, exc)

    def _write_mk(self, frame: bytes) -> bool:
        """A frame for MK port 1: written?"""
        assert self.cmd is not None
        ok = self.cmd.write(frame)
        if self.journal is not None:
            self.journal.mk_write(frame, ok)
        return ok

    def _send(self, out: list[Outbound]) -> None:
        for item in out:
            indices = range(len(self.mavlinks)) if item.link is None else range(item.link, item.link + 1)
            for i in indices:
                if i >= len(self.mavlinks):
                    continue
                conn = self.mavlinks[i]
                try:
                    conn.mav.send(item.msg)
                    if self.journal is not None:
                        self.journal.mavlink_sent(i, item.msg.get_msgbuf())
                    if self.tlog is not None and i in self.config.ground_station_links:
                        self.tlog.write(item.msg.get_msgbuf(), self._tlog_clock())
                    self.stats.mavlink_out += 1
                except (OSError, RuntimeError) as exc:  # RuntimeError: pymavlink udpin's client set changed
                    self.stats.send_errors += 1
                    if self.stats.send_errors in (1, 100, 10000):
                        log.warning("MAVLink send failed (%d so far): %s", self.stats.send_errors, exc)


def _align(reference: int, counter: int) -> int:
    """The integer closest to ``reference`` that is congruent to ``counter`` modulo 4096."""
    base = reference - (reference % COUNTER_MODULO) + (counter % COUNTER_MODULO)
    candidates = (base - COUNTER_MODULO, base, base + COUNTER_MODULO)
    return min((c for c in candidates if c >= 0), key=lambda c: abs(c - reference), default=counter)

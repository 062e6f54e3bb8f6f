"""The companion daemon's lifecycle and its one loop: links in, the pure parts in between, links out.

Concurrency model: **one thread, one loop** (:meth:`Companion.step`). Each iteration drains the two
MAVLink endpoints (non-blocking UDP/serial reads), waits up to ``timing.poll_s`` for a camera frame,
processes it, and runs the periodic tasks (modes, command retries, heartbeats, TIMESYNC, fallback
setpoints). Every wait is bounded; :meth:`Companion.close` releases everything. The only other threads
are the operator image publisher's (:mod:`companion.image_publisher`: the loop hands frames over
without ever waiting on a viewer).

This module owns the links, the clock and the order of things; the parts it wires are pure (time passed in or
injected, no sockets) except the edges named as such, and each is tested on its own:

* the two endpoints: :mod:`companion.router` (which message goes where), :mod:`companion.autopilot_input` and
  :mod:`companion.gcs_input` (each message, by type, to its service), :mod:`companion.outbound` (what the
  services return to be sent, and the edge that packs and writes it), :mod:`companion.security` (signing, the
  sender allowlist), :mod:`companion.guard` (one bad message never ends the loop; nothing non-finite goes to
  the autopilot);
* the services: :mod:`companion.params` (PARAM_*), :mod:`companion.gcs_commands` (COMMAND_LONG for compid 191,
  setpoints, mode changes answered for the autopilot), :mod:`companion.command_clock` (the age of commands),
  :mod:`companion.modes` and :mod:`companion.commands` (the mode machine, the acked autopilot commands);
* motion: :mod:`companion.arbiter` (every source of motion becomes one command; scripted setpoints never reach
  the autopilot raw) as :mod:`companion.motion` takes it, :mod:`companion.perception_stage` (never fatal),
  :mod:`companion.frame_step` (perception output + operator input + mode -> setpoint and feedback),
  :mod:`companion.frame_state` (what a frame leaves for the rest of the loop);
* time: :mod:`companion.imu_clock` (feedback on the IMU's stamps, the bounded wait for the IMU),
  :mod:`companion.scheduler` (periodic tasks); :mod:`companion.recording` (an edge), :mod:`companion.stats`.

The ground-station endpoint is hostile (issue 16): see :mod:`companion.security`; the autopilot link is
internal (the bridge on the same board, or PX4 over its serial port): no signing there.

Clocks: the camera stamps (SITL: simulated time, = the autopilot's board time;
:class:`companion.timesync.AutopilotTime`) stamp everything that describes the vehicle (setpoints, odometry,
feedback); the injected ``clock`` (monotonic wall time) times the links (ground-station loss, camera silence,
command acks), which are wall-time phenomena.

**Deterministic lock-step** (``--lockstep tcp://HOST:PORT``, :mod:`quadlink.lockstep`,
:mod:`companion.lockstep_links`): the daemon is the participant ``"companion"`` of the SITL's coordinator, and
the loop becomes a step loop (:meth:`Companion.run` -> :meth:`Companion.lockstep_step`): per STEP, the
autopilot's datagrams, then the ground station's, exactly up to the counts the step announces (waiting for
those in flight, holding back later ones for their step; every one handled, not ``MAX_ROUTED_PER_STEP``), then the
camera frames the *previous* step announced (by then the IMU has reached them: no wait for it), then the
periodic tasks once, and DONE with the datagrams sent. The clock is the step's simulated time, so every
timer (heartbeat, TIMESYNC, link and camera timeouts, command acks, the mode machine) runs on simulated time
and the daemon is a function of what it received and when it was simulated, not of the machine's load. Wall
time is left only in bounded waits (a missing unit ends the flight with
:class:`~quadlink.lockstep.LockstepError`), in statistics and logs (latency, the tlog's stamps), in the
signing timestamps' epoch and in pymavlink's pruning of silent ground-station clients: none of them changes
what is sent to the autopilot.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import itertools
import logging
import math
import threading
import time
from collections.abc import Callable, Iterable
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from companion import messages as msgs
from companion.arbiter import Arbiter, Pose, Source
from companion.autopilot_input import AutopilotInput, is_autopilot_heartbeat
from companion.cameras import CameraInput
from companion.command_clock import GcsCommandClock
from companion.commands import CommandQueue
from companion.config import CompanionConfig
from companion.frame_state import FrameState
from companion.frame_step import frame_step, height_m, map_points_h_m, setpoint_velocity
from companion.gcs_commands import GcsCommands
from companion.gcs_input import GcsInput
from companion.guard import ErrorCounter, non_finite_fields
from companion.height import HeightParams
from companion.imu_clock import ImuClock, imu_sample
from companion.interfaces import ImageSink, MavLink, Pipeline, PipelineFactory, default_pipeline_factory
from companion.journal import JournalWriter, Kind
from companion.landing_spot import (
    CLEARING_LOOKAHEAD_M,
    SURVEY_YAW_RATE_RAD_S,
    BelowMemory,
    ClearingSurvey,
    clearing_azimuth_rad,
    clearing_command,
    narrow_reach_m,
    object_below,
    room_to_clear,
    tops_xy_m,
)
from companion.latency import LatencyGuard
from companion.link_reader import CodecReader
from companion.lockstep_links import AUTOPILOT_IN, CAMERA_IN, GCS_IN, LockstepLinks
from companion.modes import AutopilotRequest, Mode, ModeMachine, SpotRefusal, StatusText
from companion.motion import Motion
from companion.obstacle_points import select_points, with_open_tops
from companion.operator_input import camera_yaw_rad
from companion.outbound import AutopilotAck, GcsReply, Outbox, Output, ToAutopilot
from companion.pan_scan import PanScanParams
from companion.params import PARAM_NAMES, CompanionParams, ParamService
from companion.perception_stage import PerceptionStage
from companion.position_hold import PositionHold
from companion.recording import FrameRecording
from companion.reference import ReferenceOutput
from companion.reference_params import ReferenceParams
from companion.router import route_from_autopilot
from companion.scheduler import HeartbeatBehindAutopilot, PeriodicTasks, Task
from companion.security import GcsSecurity
from companion.seen_ground import SeenGround
from companion.stats import PROGRESS_EVERY_S, AirborneCounts, ProgressLine, Stats
from companion.timesync import AutopilotTime, TimeSync
from companion.trajectory_follow import feed_forward_after_safety
from companion.vehicle_state import VehicleState
from perception.pipeline import PerceptionOutput
from quadlink.camera import RgbdFrame
from quadlink.lockstep import CountedMavlink, LockstepEnded, LockstepError, Step, wait_for_units
from quadlink.mavlink import mavlink
from quadlink.mavlink.timesync import NS

log = logging.getLogger(__name__)

__all__ = ["PARAM_NAMES", "Companion", "ImageSink", "MavLink", "Pipeline", "Stats", "default_pipeline_factory"]

MAX_ROUTED_PER_STEP = 2000


class _Stopped(Exception):
    """The stop flag was set while a lock-step step waited for a unit: the loop ends without its DONE."""


class Companion:
    """The daemon's state and its single loop. Links are injected (tests use ephemeral UDP ports).

    ``lockstep``: the daemon is a deterministic lock-step participant (:mod:`companion.lockstep_links`, joined
    on ``autopilot`` and ``gcs``); its ``clock`` must then be the coordinator's step clock
    (``lockstep.client.clock``)."""

    def __init__(self, cfg: CompanionConfig, autopilot: MavLink, gcs: MavLink, camera: CameraInput,
                 pipeline_factory: PipelineFactory, image_server: ImageSink | None = None, tlog: Any | None = None,
                 clock: Callable[[], float] = time.monotonic, wall: Callable[[], float] = time.time,
                 frame_recorder: Any | None = None, lockstep: LockstepLinks | None = None,
                 journal: JournalWriter | None = None, stopwatch: Callable[[], float] | None = None) -> None:
        if lockstep is not None and (clock != lockstep.client.clock or lockstep.autopilot.conn is not autopilot
                                     or lockstep.gcs.conn is not gcs):
            raise ValueError("a lock-step daemon runs on the step clock (clock=lockstep.client.clock) and on the "
                             "links the lock-step counts")
        self.lockstep = lockstep
        self._stop: threading.Event | None = None
        # times the frame-to-setpoint latency (a statistic): the step clock stands still during a step
        stopwatch = stopwatch or (clock if lockstep is None else time.monotonic)
        # the input journal (companion.journal): every event handled, the clocks read and the bytes written in it
        self.journal = journal
        if journal is not None:
            # (the wall clock only stamps the tlog and signs: neither is behaviour, and a signed link is not replayed)
            clock, stopwatch = journal.clock(clock, Kind.CLOCK), journal.clock(stopwatch, Kind.STOPWATCH)
        with self._event(Kind.INIT):
            self._build(cfg, autopilot, gcs, camera, pipeline_factory, image_server, tlog, clock, wall, stopwatch,
                        frame_recorder)

    def _build(self, cfg: CompanionConfig, autopilot: MavLink, gcs: MavLink, camera: CameraInput,
               pipeline_factory: PipelineFactory, image_server: ImageSink | None, tlog: Any | None,
               clock: Callable[[], float], wall: Callable[[], float], stopwatch: Callable[[], float],
               frame_recorder: Any | None) -> None:
        self._stopwatch = stopwatch
        self.cfg = cfg
        # the autopilot link (500 Hz HIGHRES_IMU) is decoded by the dialect's codec, not mavutil's recv_msg
        self.autopilot: MavLink = CodecReader(autopilot) if hasattr(autopilot, "recv") else autopilot
        self.gcs, self.camera = gcs, camera
        if self.journal is not None:
            self.autopilot = self.journal.link(self.autopilot, Kind.OUT_AUTOPILOT)
            self.gcs = self.journal.link(gcs, Kind.OUT_GCS)
        self.image_server, self.tlog = image_server, tlog
        self.recording = FrameRecording(frame_recorder)   # quadlink.camera.FrameRecordWriter: every frame received
        self.clock, self.wall = clock, wall
        ident = cfg.identity
        self.sysid, self.compid, self.ap_compid = ident.system_id, ident.component_id, ident.autopilot_component_id
        self.errors = ErrorCounter(clock)
        self.stats = Stats()
        self.air_counts = AirborneCounts()   # the odometry's counts from the take-off to the landing
        self.perception = PerceptionStage(pipeline_factory, self.stats, self.errors)
        self.out = Outbox(self.autopilot, self.gcs, self.sysid, self.compid, self.ap_compid, self.errors, self.stats,
                          tlog, wall)
        self.security = GcsSecurity(cfg.security, self.sysid, self.compid, clock)
        self.security.enable_signing(self.out.gcs_codec, getattr(gcs, "mav", None), wall)
        self.params = CompanionParams(cfg.pan_scan, cfg.reference)
        self.param_service = ParamService(self.params)
        self.modes = ModeMachine(cfg.modes)
        self.commands = CommandQueue()
        self.timesync = TimeSync()
        # the ground stations' command clock (issue 18): TIMESYNC with each sender, the commands' age
        self.command_clock = GcsCommandClock(cfg.links.max_command_age_s, cfg.links.gcs_timesync_max_rtt_s)
        self.gcs_sync, self.command_age = self.command_clock.sync, self.command_clock.age
        self.vehicle = VehicleState()
        self.arbiter = Arbiter(cfg.arbiter)
        self.landing_spot = cfg.landing_spot
        self.below = BelowMemory(cfg.landing_spot)   # objects seen under the vehicle, for its landings
        self.ground = SeenGround(cfg.seen_ground)      # where the camera has looked: a landing needs to have seen it
        self._takeoff_spot_pending = True               # the take-off spot is marked seen at the first pose in the air
        self._clearing_world_az: float | None = None  # the way off an object below, kept in the odometry's world
        self._survey: ClearingSurvey | None = None      # the look round before it is chosen
        self._clearing_narrow = False                   # the way off was taken by the narrow rule
        self.gcs_commands = GcsCommands(self.modes, self.arbiter, self.param_service, clock, self.vehicle.status,
                                        self._camera_fresh, self._land_refusal)
        self.autopilot_input = AutopilotInput(self.vehicle, self.commands, self.modes, self.timesync, clock)
        self.gcs_input = GcsInput(self.security, self.command_clock, self.gcs_commands, self.param_service,
                                  self.arbiter, self.modes, self.stats, self.compid, clock)
        self.motion = Motion(self.arbiter, self.command_age, clock, self.out.status_text)
        self.state = FrameState(HeightParams(cfg.reference.takeoff_height_m, cfg.reference.floor_height_time_constant_s,
                                             cfg.reference.height_fix_max_age_s))
        t = cfg.timing
        self.imu_clock = ImuClock(t.feedback_rate_hz, t.imu_wait_s, t.imu_slack_s)
        self.tasks = PeriodicTasks({Task.HEARTBEAT: 1.0 / t.heartbeat_rate_hz, Task.TIMESYNC: t.timesync_period_s,
                                    Task.GCS_TIMESYNC: cfg.links.gcs_timesync_period_s, Task.COMMAND_AGE: 1.0,
                                    Task.FALLBACK: 1.0 / t.fallback_setpoint_rate_hz,
                                    Task.FEEDBACK: 1.0 / t.feedback_rate_hz, Task.PROGRESS: PROGRESS_EVERY_S}, clock())
        self.own_heartbeat = HeartbeatBehindAutopilot()   # never ahead of the autopilot's traffic (mavsdk_server)
        self.progress = ProgressLine(PROGRESS_EVERY_S)
        self.time = AutopilotTime(self.timesync, t.camera_stamps, clock())   # stamps what we send
        self.latency = LatencyGuard(cfg.latency)   # the age of each frame's data, paid for by the safety law
        self.position_hold = PositionHold(cfg.position_hold)   # stay where the reference stops the vehicle
        self._last_seq: int | None = None

    # ------------------------------------------------------------------ parameters (companion.params)
    @property
    def scan_params(self) -> PanScanParams:
        return self.params.scan

    @property
    def ref_params(self) -> ReferenceParams:
        return self.params.reference

    # ------------------------------------------------------------------ what leaves (companion.outbound)
    def _forward(self, link: MavLink, msg: Any) -> bool:
        if link is self.autopilot and non_finite_fields(msg, any_command=True):
            # a ground station's NaN/inf never reaches the autopilot either: dropped, counted, answered
            self.stats.forward_refused += 1
            self._emit(self.security.refuse_forward(msg, self.ap_compid))
            return False
        return self.out.forward(link, msg)

    def _emit(self, outputs: Iterable[Output]) -> None:
        """What the mode machine and the services returned, sent in order (companion.outbound); then the mode's
        consequence for the pan-scan's time (companion.frame_state)."""
        for a in outputs:
            if isinstance(a, StatusText):
                self.out.status_text(a)
            elif isinstance(a, AutopilotRequest):
                self.commands.push(a)
            elif isinstance(a, GcsReply):
                self.out.to_gcs(a.msg, a.src_component)
            elif isinstance(a, AutopilotAck):
                self.out.to_gcs_as(a.msg, self.sysid, self.ap_compid)
            elif isinstance(a, ToAutopilot):
                self.out.to_autopilot(a.msg)
        self.state.on_mode(self.modes.mode, self.time.frame_stamp_s)

    # ------------------------------------------------------------------ the loop
    def run(self, stop: threading.Event, duration_s: float | None = None) -> None:
        """The one loop, whatever the event source: one turn (:meth:`step` on the wall clock and the sockets, or
        :meth:`lockstep_step` per STEP of the coordinator) after another, until ``stop`` is set or ``duration_s``
        of the clock have passed (in lock-step: simulated seconds, or the simulation's end;
        :class:`~quadlink.lockstep.LockstepError` when the coordinator is lost or a unit does not come). The stop
        flag is looked at between turns and while a step waits for a unit (every wait is sliced at 0.1 s at
        most). A journal's replay hands the same handlers their events (:mod:`companion.replay`)."""
        self._stop = stop
        end = None if duration_s is None else self.clock() + duration_s
        ls = self.lockstep
        try:
            while not stop.is_set() and (end is None or self.clock() < end):
                if ls is None:
                    self.step()
                    continue
                step = ls.client.next_step()
                if step is not None:
                    self.lockstep_step(step)
        except _Stopped:
            pass
        except LockstepEnded as exc:   # the simulation's normal end: ours too
            log.info("lock-step: %s", exc)
        except LockstepError as exc:
            log.error("lock-step ended: %s", exc)
            raise
        finally:
            if ls is not None:
                ls.close()

    def step(self) -> None:
        self._drain_autopilot()
        self._drain_gcs()
        frame = self.camera.read(self.cfg.timing.poll_s)
        if frame is not None:
            self._wait_for_imu(frame.stamp_s)
            self.handle_frame(frame)
        self.handle_periodic()

    # ------------------------------------------------------------------ the handlers every event source calls
    def _event(self, kind: Kind, payload: Callable[[], bytes] | None = None) -> contextlib.AbstractContextManager[None]:
        """The journal's record of one event (a no-op without a journal)."""
        if self.journal is None:
            return contextlib.nullcontext()
        return self.journal.event(kind, payload() if payload is not None else b"")

    def handle_autopilot(self, msg: Any) -> None:
        """One message from the autopilot (the wall-clock loop, the lock-step and a journal's replay call this)."""
        with self._event(Kind.AUTOPILOT, msg.get_msgbuf):
            self._guarded(f"autopilot {msg.get_type()}", self._on_autopilot, msg)

    def handle_gcs(self, msg: Any) -> None:
        """One message from a ground station."""
        with self._event(Kind.GCS, msg.get_msgbuf):
            self._guarded(f"ground station {msg.get_type()}", self._on_gcs, msg)

    def handle_gcs_bad_data(self) -> None:
        """Ground-station bytes that did not decode, or that signing refused (unsigned, wrong key, replayed)."""
        with self._event(Kind.GCS_BAD):
            self.stats.gcs_bad_data += 1

    def handle_frame(self, frame: RgbdFrame) -> None:
        """One camera frame."""
        journal = self.journal
        with self._event(Kind.FRAME, (lambda: journal.frame_payload(frame)) if journal is not None else None):
            self._guarded("frame", self._process_frame, frame)

    def handle_periodic(self) -> None:
        """One turn of the periodic tasks (heartbeat, timesync, feedback, the fallback setpoint, the status line)."""
        with self._event(Kind.PERIODIC):
            self._guarded("periodic tasks", self._periodic)

    def _guarded(self, where: str, handler: Callable[[Any], None] | Callable[[], None], *args: Any) -> None:
        """Run one message's (or one task's) handling; an unexpected exception is counted and logged, and the
        loop goes on (issue 16). The one place the daemon catches everything: a flight loop must not end on
        a bug reached by one message."""
        try:
            handler(*args)
        except Exception as exc:  # noqa: BLE001 - see the docstring: counted and logged (ErrorCounter)
            self.stats.handler_errors += 1
            self.errors.record(where, exc)

    # ------------------------------------------------------------------ the lock-step's turn (quadlink.lockstep)
    def lockstep_step(self, step: Step) -> None:
        """One STEP: the inputs in their fixed order, each exactly up to its count, the periodic tasks, DONE.

        The camera's frames are those the previous step announced (:attr:`LockstepLinks.frames_due`); this step's
        wait in the socket for the next one."""
        ls = self.lockstep
        assert ls is not None, "lockstep_step without a lock-step"
        self._read_counted(ls.autopilot, step.count(AUTOPILOT_IN), self._drain_autopilot, AUTOPILOT_IN)
        self._read_counted(ls.gcs, step.count(GCS_IN), self._drain_gcs, GCS_IN)
        self._read_frames(ls, ls.frames_due)
        ls.frames_due = step.count(CAMERA_IN)
        self.handle_periodic()
        ls.client.done(ls.sent())

    def _check_stop(self) -> None:
        if self._stop is not None and self._stop.is_set():
            raise _Stopped

    def _read_counted(self, link: CountedMavlink, expected: int | None, drain: Callable[[int | None], None],
                      name: str) -> None:
        """Handle every message of the first ``expected`` datagrams of ``link``, waiting (bounded) for those still
        in flight; later ones wait for their step. ``expected`` None (a link without a lock-step sender): what
        is there, as the wall-clock loop does, not deterministically."""
        link.allow = expected
        limit = None if expected is not None else MAX_ROUTED_PER_STEP

        def pump(block_s: float) -> None:
            self._check_stop()
            link.wait_readable(block_s)
            drain(limit)

        drain(limit)
        wait_for_units(lambda: link.received, expected, pump, name)
        drain(limit)   # what pymavlink still holds of the last datagram (the cap keeps later ones out)
        while expected is not None and link.handed < min(expected, link.received):
            drain(limit)   # a datagram that parsed to nothing (a frame split over datagrams) ends a drain early

    def _read_frames(self, ls: LockstepLinks, due: int | None) -> None:
        """Process the camera's frames until ``due`` have been handed over (waiting, bounded, for those in flight);
        no more are read in this step. No wait for the IMU: it has reached these frames by construction."""
        def pump(block_s: float) -> None:
            self._check_stop()
            frame = ls.camera.take(block_s)
            if frame is not None:
                self.handle_frame(frame)

        wait_for_units(lambda: ls.camera.received, due, pump, CAMERA_IN)

    # ------------------------------------------------------------------ the links' messages
    def _drain_autopilot(self, limit: int | None = MAX_ROUTED_PER_STEP) -> None:
        """Handle what the autopilot link has now: at most ``limit`` messages (None: until it has nothing)."""
        for _ in itertools.repeat(None) if limit is None else range(limit):
            msg = self.autopilot.recv_msg()
            if msg is None:
                return
            if msg.get_type() != "BAD_DATA":
                self.handle_autopilot(msg)

    def _drain_gcs(self, limit: int | None = MAX_ROUTED_PER_STEP) -> None:
        """Handle what the ground-station link has now: at most ``limit`` messages (None: until it has nothing)."""
        for _ in itertools.repeat(None) if limit is None else range(limit):
            msg = self.gcs.recv_msg()
            if msg is None:
                return
            if msg.get_type() == "BAD_DATA":
                self.handle_gcs_bad_data()
            else:
                self.handle_gcs(msg)

    def _wait_for_imu(self, stamp_s: float) -> None:
        """Let the IMU stream catch up with the frame (bounded), if it is flowing at all (the policy:
        :class:`companion.imu_clock.ImuClock`); the autopilot link is drained meanwhile. Never in lock-step:
        there the frame is handled a step after its own, when the IMU has reached it, and the step clock stands
        still (a deadline on it would never pass) and the link must not be read past its count."""
        imu = self.imu_clock
        if self.lockstep is not None or not imu.should_wait(stamp_s, self.time.imu_stamp_s):
            return
        deadline = self.clock() + imu.imu_wait_s
        while not imu.caught_up(stamp_s, self.time.imu_stamp_s):
            if self.clock() >= deadline:
                imu.on_wait_timeout()
                return
            self._drain_autopilot()
            time.sleep(0.0005)
        imu.on_caught_up()

    # ------------------------------------------------------------------ the two endpoints
    def _on_autopilot(self, msg: Any) -> None:
        self.out.log_packet(msg.get_msgbuf())
        kind = msg.get_type()
        route = route_from_autopilot(kind, getattr(msg, "target_component", None), self.compid)
        if route.consume and kind == "HIGHRES_IMU":
            self._on_imu(msg)
        elif route.consume:
            if kind == "HEARTBEAT" and is_autopilot_heartbeat(msg):
                self._on_autopilot_identity(msg.get_srcSystem(), msg.get_srcComponent())
            self._emit(self.autopilot_input.on_message(msg))
        if route.forward and kind == "HEARTBEAT" and self.modes.in_control and \
                msg.autopilot != mavlink.MAV_AUTOPILOT_INVALID and msg.get_srcComponent() == self.ap_compid:
            # the autopilot's heartbeat with the mode of the motion authority (companion.gcs_commands)
            if self.out.to_gcs_as(self.gcs_commands.mode_heartbeat(msg), msg.get_srcSystem(), msg.get_srcComponent()):
                self._routed_to_gcs()
        elif route.forward and self._forward(self.gcs, msg):
            self._routed_to_gcs()

    def _routed_to_gcs(self) -> None:
        """An autopilot message went to the ground stations: the companion's held heartbeat goes right behind it."""
        self.stats.routed_to_gcs += 1
        if self.own_heartbeat.forwarded():
            self.out.to_gcs(msgs.heartbeat_message(self.modes.mode))

    def _on_autopilot_identity(self, sysid: int, ap_compid: int) -> None:
        """The autopilot's heartbeat names the vehicle's system id (the companion speaks as it) and its component."""
        if sysid != self.sysid:
            log.info("autopilot is system %d: using it as our system id", sysid)
            self.sysid = sysid
            self.out.set_system_id(sysid)
            self.security.on_system_id(sysid)
        self.ap_compid = ap_compid

    def _on_imu(self, msg: Any) -> None:
        sample = imu_sample(msg)
        if sample is None:
            return
        self.time.on_imu(sample.stamp_s, self.clock())
        self.state.gyro_q_rad_s = sample.gyro_q_rad_s
        self.perception.on_imu(sample.stamp_s, sample.gyro_q_rad_s, sample.accel_q_m_s2)
        if self.imu_clock.feedback_due(sample.stamp_s):
            self._send_feedback(sample.stamp_s)

    def _on_gcs(self, msg: Any) -> None:
        self.out.log_packet(msg.get_msgbuf())
        handled = self.gcs_input.on_message(msg, self.sysid, self.ap_compid, self._pose)
        self._emit(handled.outputs)
        if handled.forward and self._forward(self.autopilot, msg):
            self.stats.routed_to_autopilot += 1

    # ------------------------------------------------------------------ state read between frames
    def _pose(self) -> Pose:
        return self.state.pose(self.modes.mode, self.time.frame_stamp_s, self.scan_params)

    def _camera_fresh(self, now: float | None = None) -> bool:
        """A camera frame arrived within ``camera_timeout_s`` (wall time) of ``now`` (default: the clock now)."""
        last = self.time.frame_wall_s
        return last is not None and (self.clock() if now is None else now) - last <= self.cfg.timing.camera_timeout_s

    def _height_above_floor_m(self) -> float | None:
        h = self.state.height.height_m   # above the take-off pose, where the body centre is takeoff_height_m up
        return None if h is None else h + self.ref_params.takeoff_height_m

    def _points_below(self) -> NDArray[np.float64] | None:
        """The map's points (moved in by the odometry's drift since each was seen, as the avoidance takes them) and
        the remembered tops of the objects under the vehicle (companion.landing_spot), in H."""
        out = self.state.last_output
        if out is None:
            return None
        points = map_points_h_m(out, self.ref_params, self._height_above_floor_m())
        if not out.odometry_ok:   # no pose to place the memory with: the map alone
            return points
        remembered = self.below.points_h(out.position_m, out.yaw_rad, self._height_above_floor_m())
        return np.vstack([np.asarray(points, dtype=float).reshape(-1, 3), remembered])

    def _failsafe_refusal(self) -> str | None:
        """What keeps a failsafe landing from coming down here and moves it clear first (companion.modes): an
        object below, while the vehicle can move clear. It first turns on the spot to look every way
        (:class:`companion.landing_spot.ClearingSurvey`), then takes a way off with room
        (:func:`companion.landing_spot.room_to_clear`: nothing of the avoidance's band in the path it sweeps over
        the influence distance, with a lateral margin), or else a narrow one (nothing in the path as far as the spot
        where the footprint clears, no lateral margin: the reference's safe distance still holds the move off what
        it sees), chosen again if it loses its room on the way. With neither, it looks round again (while it looks
        one way the others age out of the map) until the mode machine's ``land_clear_timeout_s``; with anything
        inside the safe distance, or without a pose, it lands where it is, on the object: a clearing move is motion
        nobody commanded.

        A vehicle over the edge of a box in a cluttered room (columns and walls 0.8-1.1 m away all round) found
        no way with the full margin, landed "where it was" and came down the box's side to 0.11 m of it (campaign
        seed 4242, flight 34); the narrow rule had a way off in every look round of that flight."""
        out = self.state.last_output
        if out is None or not out.odometry_ok or not math.isfinite(out.yaw_rad):
            return None
        # once moving clear, the spot must be clear by a margin (hysteresis): the map's tops read a few cm
        # optimistic, and a landing that stopped just past the footprint came down beside the box inside the safe
        # distance (campaign 9, flight 2); before, a wall the vehicle rests beside must not count as "below"
        map_below = self._points_below()
        spot = self._land_refusal(self.landing_spot.clear_margin_m if self.modes.clearing_spot else 0.0,
                                  points_below=map_below)
        if spot is None:
            return None
        refusal = spot.text
        ref = self.ref_params
        height = self._height_above_floor_m()
        band = select_points(map_points_h_m(out, ref, height), ref, height, ref.influence_distance_m)
        room_m = ref.safe_distance_m - 0.05

        # built only when a way off is judged by the narrow rule or chosen again (a kept wide way needs neither)
        @functools.cache
        def points_below() -> NDArray[np.float64] | None:
            return None if map_below is None else np.vstack([map_below, self._unseen_ground_points()])

        @functools.cache
        def tops() -> NDArray[np.float64]:
            return tops_xy_m(points_below(), height, self.landing_spot, ref.floor_margin_m)

        def room(az_h: float) -> bool:
            return room_to_clear(band, az_h, ref.influence_distance_m, room_m)

        def narrow_room(az_h: float) -> bool:
            reach = min(ref.influence_distance_m, narrow_reach_m(tops(), az_h, self.landing_spot))
            return room_to_clear(band, az_h, reach, room_m, lateral_margin_m=0.0)

        if not room_to_clear(band, 0.0, 0.0, room_m):    # inside the safe distance of something: no room anywhere
            return None
        yaw = float(out.yaw_rad)
        kept_rule = narrow_room if self._clearing_narrow else room
        if self._clearing_world_az is not None and kept_rule(self._clearing_world_az - yaw):
            return refusal
        if self._clearing_world_az is None and (self._survey is None or not self._survey.done):
            return refusal    # look round first (_clearing_command turns the vehicle)
        # the way off, chosen after the look round, or again when the one taken has no room any more
        sectors, _, offset_deg = msgs.sector_arrays(out.sectors)
        for narrow, rule in ((False, room), (True, narrow_room)):
            az_h = clearing_azimuth_rad(points_below(), height, self.landing_spot, ref.floor_margin_m,
                                        camera_yaw_rad(self.state.R_qc), sectors, ref.unknown_sector_guard_rad,
                                        math.radians(offset_deg), room=rule)
            if az_h is not None:
                self._clearing_world_az, self._clearing_narrow = yaw + az_h, narrow
                return refusal
        self._clearing_world_az, self._survey, self._clearing_narrow = None, None, False   # look round again
        return refusal

    def _land_refusal(self, extra_radius_m: float = 0.0, *,
                      points_below: NDArray[np.float64] | None | Literal["build"] = "build") -> SpotRefusal | None:
        """Why the spot under the vehicle is no place to land (an object seen below it, or ground the camera has
        not seen, within the footprint widened by ``extra_radius_m``), or None. ``points_below`` is
        :meth:`_points_below` when the caller has built it already."""
        if isinstance(points_below, str):
            points_below = self._points_below()
        below = object_below(points_below, self._height_above_floor_m(), self.landing_spot,
                             self.ref_params.floor_margin_m, extra_radius_m)
        if below is not None:
            return SpotRefusal(below.refusal())
        out = self.state.last_output
        if not self.ground.params.enabled or out is None or not out.odometry_ok:
            return None
        unseen = self.ground.unseen_fraction(out.position_m, self.landing_spot.footprint_radius_m + extra_radius_m)
        if unseen is not None and unseen > self.ground.params.max_unseen_fraction:
            return SpotRefusal(f"ground below not seen ({100 * unseen:.0f} %)", unseen=True)
        return None

    def _unseen_ground_points(self) -> NDArray[np.float64]:
        """The ground the camera has not seen around the vehicle, as the tops of objects just above the landing's
        threshold (H): a way off an unseen spot leads to seen ground as a way off an object leads off its top."""
        out = self.state.last_output
        height = self._height_above_floor_m()
        if not self.ground.params.enabled or out is None or not out.odometry_ok or height is None:
            return np.zeros((0, 3))
        return self.ground.unseen_points_h(out.position_m, out.yaw_rad,
                                           CLEARING_LOOKAHEAD_M + self.landing_spot.footprint_radius_m,
                                           height - (max(self.landing_spot.min_top_m, self.ref_params.floor_margin_m)
                                                     + 0.05))

    def _clearing_command(self, out: PerceptionOutput | None) -> tuple[NDArray[np.float64], float] | None:
        """While a failsafe landing moves clear of an object below (companion.modes), the command that does it
        (velocity in H, yaw rate): the way off is chosen once and kept in the odometry's world; the vehicle turns
        its camera to it first and moves only while it looks that way (in HOLD nothing pan-scans, and a way the
        camera does not look at becomes unseen, where the reference flies nothing: a re-flown campaign flight
        held 15 s over a box)."""
        if not self.modes.clearing_spot:
            self._clearing_world_az, self._survey, self._clearing_narrow = None, None, False
            return None
        yaw = float(out.yaw_rad) if out is not None and out.odometry_ok and math.isfinite(out.yaw_rad) else None
        if yaw is None:   # no pose: hold (the failsafe lands after its timeout)
            return np.zeros(3), 0.0
        if self._clearing_world_az is None:   # looking round before the way off is chosen
            if self._survey is None:
                self._survey = ClearingSurvey()
            self._survey.observe(yaw)
            return np.zeros(3), (0.0 if self._survey.done else SURVEY_YAW_RATE_RAD_S)
        return clearing_command(self._clearing_world_az - yaw, camera_yaw_rad(self.state.R_qc), self.landing_spot)

    # ------------------------------------------------------------------ the pipeline at camera rate
    def _process_frame(self, frame: RgbdFrame) -> None:
        t_in = self._stopwatch()
        self.stats.frames += 1
        seq_gap = 1 if self._last_seq is None else frame.seq - self._last_seq
        if seq_gap > 1:
            self.stats.frames_skipped += seq_gap - 1   # dropped at the source, or skipped
        self._last_seq = frame.seq
        st = self.state
        st.R_qc = np.asarray(frame.R_qc, dtype=float)
        out = self.perception.on_frame(frame)
        st.on_odometry(out, first_frame=self.stats.frames == 1)
        stamp = self.time.on_frame(frame.stamp_s, self.clock())
        st.on_mode(self.modes.mode, stamp)
        if out is not None:
            st.last_output = out
            self.stats.perception_s.append(float(out.processing_time_s))
            self.air_counts.on_output(out.odometry_counts, self.modes.mode != Mode.IDLE)
        height = st.height.update(stamp, height_m(out), None if out is None else out.floor_height_m)
        if self.modes.mode == Mode.IDLE:
            self.below.clear()   # a new flight, a new odometry world
            self.ground.clear()
            self.position_hold.reset()
            self._takeoff_spot_pending = True
        if out is not None and out.odometry_ok and (self.modes.mode in (Mode.IDLE, Mode.TAKEOFF)
                                                    or self._takeoff_spot_pending):
            # the ground the vehicle stands on, and climbs straight up from (a take-off's, or an offboard script's
            # climb from the ground: the first pose after it), counts as seen
            self.ground.mark_disc(out.position_m, self.ground.params.takeoff_radius_m)
            self._takeoff_spot_pending = self.modes.mode == Mode.IDLE
        if self.modes.mode != Mode.IDLE and out is not None and out.odometry_ok:
            self.ground.observe(frame.depth_m, frame.intrinsics, st.R_qc, frame.p_qc_m, out.roll_rad, out.pitch_rad,
                                out.yaw_rad, out.position_m)
            # with the walls seen from below extended up to the vehicle: beside it, not below it
            self.below.observe(with_open_tops(out.obstacle_points_h_m, out.obstacle_open_top,
                                              self._height_above_floor_m(), self.ref_params.floor_margin_m),
                               self._height_above_floor_m(), self.ref_params.floor_margin_m,
                               out.position_m, out.yaw_rad)
        now = self.clock()
        self._emit(self.modes.update(now, self.vehicle.status(), st.odometry_ok, self._failsafe_refusal))
        cmd = self.motion.command(self._pose())
        op = self.motion.operator_of(cmd)
        scripted = cmd.source == Source.SCRIPT
        clearing = self._clearing_command(out)
        v_command = clearing[0] if clearing is not None else cmd.v_h_m_s if scripted else None
        ob = self.cfg.obstacles
        ref_params, operator_enabled = self._latency_law(stamp, seq_gap)
        if self.latency.holding and clearing is None:
            v_command, operator_enabled = None, False   # late data: no commanded motion, the repulsion still acts
        step = frame_step(out, op, st.R_qc, st.scan(self.modes.mode, stamp, self.scan_params), ref_params,
                          operator_enabled or clearing is not None, ob.allow_unknown_when_fresh,
                          v_command_h_m_s=v_command,
                          command_yaw_rate_rad_s=clearing[1] if clearing is not None else cmd.yaw_rate_rad_s,
                          height_above_takeoff_m=height,
                          height_verified=st.height.verified(stamp), command_into_unknown=ob.scripts_into_unknown,
                          height_uncertainty_m=st.height.uncertainty_m(stamp),
                          baro_height_m=self.vehicle.baro_height(now))
        held = self.position_hold.step(stamp, step.ref, None if out is None else out.position_m,
                                      math.nan if out is None else out.yaw_rad, out is not None and out.odometry_ok,
                                      self.modes.in_control)
        if held is not step.ref:
            step = dataclasses.replace(step, ref=held)
        st.on_step(step)
        a_ff = cmd.a_ff_h_m_s2 if scripted and clearing is None else None
        self._send_setpoint(stamp, step.ref,
                            feed_forward_after_safety(a_ff, step.ref.constrained, step.ref.v_repulsion_h_m_s))
        self.stats.latencies_s.append(self._stopwatch() - t_in)
        if out is not None:
            odometry = st.odometry_message(stamp, out)
            self.out.to_autopilot(odometry)
            self.out.to_gcs(odometry)
        self.camera.ack(frame.seq)
        if out is not None:
            for m in st.telemetry(stamp, out, ob.min_distance_cm, ob.max_distance_cm, self.ref_params):
                self.out.to_gcs(m)
            self._publish_image(frame, out, step.ref)
        self.recording.write(frame)

    def _latency_law(self, stamp_s: float, seq_gap: int = 1) -> tuple[ReferenceParams, bool]:
        """This frame's age on the autopilot's clock (companion.latency), the reference law's parameters that pay
        for it (stopping time, speed limit, and the map's drift margin for the frames skipped, ``seq_gap`` since the
        last one processed) and whether the operator may move the vehicle; the hold is told."""
        ref = self.ref_params
        age_s = self.time.estimate_s(self.clock()) - stamp_s
        v = self.latency.on_frame(self.clock(), age_s, ref.stopping_time_s, ref.max_speed_m_s, seq_gap)
        if v.drift_scale > 1.0:
            ref = dataclasses.replace(ref, map_drift_m_s=ref.map_drift_m_s * v.drift_scale)
        self.stats.data_ages_s.append(v.age_s)
        if v.changed:
            text = (f"companion: data {v.age_s * 1e3:.0f} ms old: holding" if v.holding
                    else f"companion: data {v.age_s * 1e3:.0f} ms old: resuming")
            self._emit([StatusText(mavlink.MAV_SEVERITY_WARNING if v.holding else mavlink.MAV_SEVERITY_INFO, text)])
            log.warning("%s", text)
        if v.stopping_time_s != ref.stopping_time_s or v.max_speed_m_s != ref.max_speed_m_s:
            ref = dataclasses.replace(ref, stopping_time_s=v.stopping_time_s, max_speed_m_s=v.max_speed_m_s)
        return ref, self.modes.operator_enabled and not v.holding

    def _send_setpoint(self, stamp_s: float, ref: ReferenceOutput, a_ff_h_m_s2: NDArray[np.float64] | None = None
                       ) -> None:
        """The safety layer's velocity (and a trajectory's acceleration feed-forward, when the layer left the
        velocity as commanded: :func:`companion.trajectory_follow.feed_forward_after_safety`)."""
        v, yaw_rate = setpoint_velocity(ref, self.modes.in_control)
        if not self.modes.in_control:
            a_ff_h_m_s2 = None
        self.out.to_autopilot(msgs.setpoint_message(stamp_s, self.sysid, self.ap_compid, v, yaw_rate, a_ff_h_m_s2))
        self.stats.setpoints += 1

    def _send_feedback(self, stamp_s: float) -> None:
        st, mode = self.state, self.modes.mode
        self.out.to_gcs(st.feedback(stamp_s, st.scan(mode, stamp_s, self.scan_params), self.motion.reported_mode(mode),
                                    self.modes.gcs_ok, self._camera_fresh()))
        self.stats.feedback += 1

    def _publish_image(self, frame: RgbdFrame, out: PerceptionOutput, ref: ReferenceOutput) -> None:
        if self.image_server is None or self.image_server.client_count == 0:
            return
        meta = self.state.image_meta(frame, out, ref, self.modes.mode, self.scan_params)
        self.image_server.publish(frame, meta)   # never blocks (ImageSink)

    # ------------------------------------------------------------------ periodic tasks (companion.scheduler)
    def _periodic(self) -> None:
        now = self.clock()
        camera_silent = not self._camera_fresh(now)
        if camera_silent:
            self.state.odometry_ok = False
        if self.arbiter.link_alive(now):
            # the ground station is there while it sends heartbeats, setpoints or MANUAL_CONTROL; a silent
            # motion source is the arbiter's business (it holds), not a lost link
            self.modes.on_manual_control(now)
        self.modes.on_motion_command(self.arbiter.last_command_s)   # a live link alone keeps no vehicle flying
        self._emit(self.modes.update(now, self.vehicle.status(), self.state.odometry_ok, self._failsafe_refusal))
        self._emit(self.autopilot_input.poll_commands(now, self.sysid, self.ap_compid))
        if self.own_heartbeat.expired(now):   # held, and the autopilot fell silent: it goes alone
            self.out.to_gcs(msgs.heartbeat_message(self.modes.mode))
        for task in self.tasks.due(now, camera_silent, ImuClock.silent(now, self.time.imu_wall_s)):
            self._run_task(task, now)

    def _run_task(self, task: Task, now: float) -> None:
        if task == Task.HEARTBEAT:
            hb = msgs.heartbeat_message(self.modes.mode)
            self.out.to_autopilot(hb)
            if self.own_heartbeat.due(now):   # else held for the autopilot's next message (scheduler's docstring)
                self.out.to_gcs(hb)
        elif task == Task.TIMESYNC:
            self.out.to_autopilot(mavlink.MAVLink_timesync_message(0, int(now * 1e9)))
        elif task == Task.GCS_TIMESYNC:
            self.out.to_gcs(mavlink.MAVLink_timesync_message(0, int(now * NS)))
        elif task == Task.COMMAND_AGE:   # the figures for the ground station (and the tlog)
            ms = int(self.time.estimate_s(self.clock()) * 1e3) & 0xFFFFFFFF
            self._emit(GcsReply(m) for m in self.command_clock.report(ms))
            if self.stats.data_ages_s:   # the newest frame's data age, for the ground station and the tlog
                self._emit([GcsReply(mavlink.MAVLink_named_value_float_message(
                    ms, b"DATA_AGE", float(self.stats.data_ages_s[-1]))),
                    GcsReply(mavlink.MAVLink_named_value_int_message(ms, b"LATE_HOLD", int(self.latency.holding)))])
            out = self.state.last_output
            if out is not None:   # the odometry's frames that were not plainly aligned: since the start, in the air
                c, a = out.odometry_counts, self.air_counts.counts
                self._emit(GcsReply(mavlink.MAVLink_named_value_int_message(ms, name, value)) for name, value in (
                    (b"ODO_BRIDGE", c.fallbacks), (b"ODO_HELD", c.lost), (b"ODO_JUMP", c.rejected_jumps),
                    (b"ODO_RESTRT", c.restarts), (b"AIR_BRIDGE", a.fallbacks), (b"AIR_HELD", a.lost),
                    (b"AIR_JUMP", a.rejected_jumps), (b"AIR_RESTRT", a.restarts)))
        elif task == Task.FALLBACK:   # keeps the autopilot's stream alive without a camera (frame_step.fallback_step)
            stamp = self.time.estimate_s(now)
            op = self.motion.operator_of(self.motion.command(self._pose()))
            self._send_setpoint(stamp, self.state.fallback(op, self.ref_params, self.modes.operator_enabled, stamp,
                                                           self.vehicle.baro_height(now)))
        elif task == Task.FEEDBACK:
            self._send_feedback(self.time.estimate_s(now))
        elif task == Task.PROGRESS:
            st = self.state
            counts = "" if st.last_output is None else \
                f"{st.last_output.odometry_counts.summary()}; in the air {self.air_counts.counts.summary()}"
            log.info("%s", self.progress.line(self.stats, self.modes.mode.name, st.odometry_ok, self.modes.gcs_ok,
                                              st.height.summary(), self.command_clock.summary(), counts))
            self.stats.trim()

    def close(self) -> None:
        for name, closer in (("lock-step", self.lockstep.close if self.lockstep else None),
                             ("camera", self.camera.close), ("autopilot", self.autopilot.close),
                             ("gcs", self.gcs.close),
                             ("image stream", self.image_server.close if self.image_server else None),
                             ("tlog", self.tlog.close if self.tlog else None),
                             ("frame recording", self.recording.close),
                             ("journal", self.journal.close if self.journal else None)):
            if closer is None:
                continue
            try:
                closer()
            except OSError as exc:
                log.warning("closing %s: %s", name, exc)

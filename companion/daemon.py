"""The companion daemon's lifecycle and its one loop: links in, the pure parts in between, links out.

Concurrency model: **one thread, one loop** (:meth:`Companion.step`). Each iteration drains the two
MAVLink endpoints (non-blocking UDP/serial reads), waits up to ``timing.poll_s`` for a camera frame,
processes it, and runs the periodic tasks (modes, command retries, heartbeats, TIMESYNC, fallback
setpoints). Every wait is bounded; :meth:`Companion.close` releases everything. The only other threads
are the operator image publisher's (:mod:`companion.image_publisher`: the loop hands frames over
without ever waiting on a viewer).

The parts it wires (each pure, each tested on its own):

* :mod:`companion.router` — which message goes where;
* :mod:`companion.arbiter` — every source of motion (MANUAL_CONTROL, scripted setpoints, mode changes)
  becomes one command for the reference pipeline; scripted setpoints never reach the autopilot raw;
* :mod:`companion.frame_step` — perception output + operator input + mode -> setpoint and feedback;
* :mod:`companion.scheduler` — the periodic deadlines;
* :mod:`companion.params` — the PARAM_* service for compid 191;
* :mod:`companion.gcs_commands` — the ground stations' COMMAND_LONG for compid 191, their setpoints, and the
  mode changes the companion answers for the autopilot;
* :mod:`companion.command_clock` — TIMESYNC with each ground station and the age of its commands;
* :mod:`companion.security` — signing, the sender allowlist and the refusals on the ground-station endpoint;
* :mod:`companion.perception_stage` — the perception pipeline, built on the first frame, never fatal;
* :mod:`companion.outbound` — what the services return to be sent, and the edge that packs and writes it;
* :mod:`companion.modes`, :mod:`companion.commands` — the mode machine and the acked autopilot commands;
* :mod:`companion.guard` — one bad message never ends the loop: unexpected exceptions in its handling are
  caught, counted and logged once in a while; nothing non-finite goes to the autopilot.

The ground-station endpoint is hostile (issue 16): see :mod:`companion.security`; the autopilot link is
internal (the bridge on the same board, or PX4 over its serial port): no signing there.

Clocks: the camera stamps (SITL: simulated time, = the autopilot's board time;
:class:`companion.timesync.AutopilotTime`) stamp everything that describes the vehicle (setpoints, odometry,
feedback); the injected ``clock`` (monotonic wall time) times the links (ground-station loss, camera silence,
command acks), which are wall-time phenomena.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Iterable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion import messages as msgs
from companion.arbiter import Arbiter, MotionCommand, Pose, Source
from companion.cameras import CameraInput
from companion.command_clock import GcsCommandClock
from companion.commands import CommandQueue
from companion.config import CompanionConfig
from companion.frame_step import (
    NO_SCAN,
    FrameStep,
    fallback_step,
    feedback_message,
    frame_step,
    height_m,
    operator_image_meta,
    setpoint_velocity,
)
from companion.gcs_commands import GcsCommands
from companion.guard import ErrorCounter, non_finite_fields
from companion.height import HeightEstimator, HeightParams
from companion.interfaces import ImageSink, MavLink, Pipeline, PipelineFactory, default_pipeline_factory
from companion.link_reader import CodecReader
from companion.modes import AutopilotRequest, Mode, ModeMachine, StatusText
from companion.operator_input import OperatorInput, operator_from_manual_control
from companion.outbound import AutopilotAck, GcsReply, Outbox, Output
from companion.pan_scan import PanScanParams, PanScanState, pan_scan
from companion.params import PARAM_NAMES, CompanionParams, ParamService
from companion.perception_stage import PerceptionStage
from companion.reference import ReferenceOutput
from companion.reference_params import ReferenceParams
from companion.router import route_from_autopilot, route_from_gcs
from companion.scheduler import Deadlines, StampTicker
from companion.security import GcsSecurity
from companion.stats import Stats
from companion.timesync import AutopilotTime, TimeSync
from companion.trajectory_follow import feed_forward_after_safety
from companion.vehicle_state import VehicleState
from quadlink.camera import RgbdFrame
from quadlink.mavlink import mavlink
from quadlink.mavlink.timesync import NS
from quadlink.operator_image import OperatorImageMeta
from quadlink.px4_modes import decode_custom_mode

log = logging.getLogger(__name__)

__all__ = ["PARAM_NAMES", "Companion", "ImageSink", "MavLink", "Pipeline", "Stats", "default_pipeline_factory"]

MAX_ROUTED_PER_STEP = 2000
PROGRESS_EVERY_S = 5.0
IMU_SILENT_S = 0.1          # no HIGHRES_IMU for this long: feedback paced on wall time instead
IMU_LAG_LIMIT = 30          # consecutive IMU-wait timeouts after which the daemon stops waiting
MAX_STAMP_US = 2**53        # an autopilot boot time beyond this (285 years, and float64's exact integers) is garbage


class Companion:
    """The daemon's state and its single loop. Links are injected (tests use ephemeral UDP ports)."""

    def __init__(self, cfg: CompanionConfig, autopilot: MavLink, gcs: MavLink, camera: CameraInput,
                 pipeline_factory: PipelineFactory, image_server: ImageSink | None = None, tlog: Any | None = None,
                 clock: Callable[[], float] = time.monotonic, wall: Callable[[], float] = time.time,
                 frame_recorder: Any | None = None) -> None:
        self.cfg = cfg
        # the autopilot link (500 Hz HIGHRES_IMU) is decoded by the dialect's codec, not mavutil's recv_msg
        self.autopilot: MavLink = CodecReader(autopilot) if hasattr(autopilot, "recv") else autopilot
        self.gcs, self.camera = gcs, camera
        self.image_server = image_server
        self.tlog = tlog
        self.frame_recorder = frame_recorder   # quadlink.camera.FrameRecordWriter: every frame received
        self.clock, self.wall = clock, wall
        ident = cfg.identity
        self.sysid = ident.system_id
        self.compid = ident.component_id
        self.ap_compid = ident.autopilot_component_id
        self.errors = ErrorCounter(clock)
        self.stats = Stats()
        self.perception = PerceptionStage(pipeline_factory, self.stats, self.errors)
        self.out = Outbox(self.autopilot, gcs, self.sysid, self.compid, self.ap_compid, self.errors, self.stats,
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
        self.op = OperatorInput()
        self.arbiter = Arbiter(cfg.arbiter)
        self.gcs_commands = GcsCommands(self.modes, self.arbiter, self.param_service, clock, self.vehicle.status,
                                        self._camera_fresh)
        self.last_command: MotionCommand | None = None
        # perception / reference state (held between frames for the 50 Hz feedback)
        self.last_output: Any | None = None
        self.last_ref: ReferenceOutput | None = None
        self.odometry_ok = False
        self.height = HeightEstimator(HeightParams(cfg.reference.takeoff_height_m,
                                                   cfg.reference.floor_height_time_constant_s,
                                                   cfg.reference.height_fix_max_age_s))
        self._reset_counter = 0
        self._scan_t0_s: float | None = None
        self._gyro_q = np.zeros(3)
        self._nearest: tuple[NDArray[np.float64], float] | None = None   # nearest obstacle (vector in H, m)
        self._avoid_points_h_m: NDArray[np.float64] | None = None   # the avoidance's points at the last frame
        self._imu_wait_misses = 0
        self._feedback_ticker = StampTicker(1.0 / cfg.timing.feedback_rate_hz)
        self.deadlines = Deadlines()
        self.deadlines.arm("progress", clock() + PROGRESS_EVERY_S)
        self._progress_frames = 0
        self.time = AutopilotTime(self.timesync, cfg.timing.camera_stamps, clock())   # stamps what we send
        self._R_qc = np.eye(3)

    # ------------------------------------------------------------------ parameters (companion.params)
    @property
    def scan_params(self) -> PanScanParams:
        return self.params.scan

    @property
    def ref_params(self) -> ReferenceParams:
        return self.params.reference

    def param_values(self) -> dict[str, float]:
        return self.params.values()

    def set_param(self, name: str, value: float) -> bool:
        changed, out = self.param_service.set(name, value)
        self._emit(out)
        return changed

    # ------------------------------------------------------------------ sending (companion.outbound)
    def send_autopilot(self, msg: Any) -> None:
        self.out.to_autopilot(msg)

    def send_gcs(self, msg: Any, src_component: int | None = None) -> None:
        self.out.to_gcs(msg, src_component)

    def _forward(self, link: MavLink, msg: Any) -> bool:
        if link is self.autopilot and non_finite_fields(msg, any_command=True):
            # a ground station's NaN/inf never reaches the autopilot either: dropped, counted, answered
            self.stats.forward_refused += 1
            self._emit(self.security.refuse_forward(msg, self.ap_compid))
            return False
        return self.out.forward(link, msg)

    def _status_text(self, st: StatusText) -> None:
        level = logging.WARNING if st.severity <= mavlink.MAV_SEVERITY_WARNING else logging.INFO
        log.log(level, "%s", st.text)
        self.send_gcs(mavlink.MAVLink_statustext_message(st.severity, st.text.encode()[:50]))

    def _emit(self, outputs: Iterable[Output]) -> None:
        """What the mode machine and the ground-station services returned, sent in order (companion.outbound)."""
        for a in outputs:
            if isinstance(a, StatusText):
                self._status_text(a)
            elif isinstance(a, AutopilotRequest):
                self.commands.push(a)
            elif isinstance(a, GcsReply):
                self.send_gcs(a.msg, a.src_component)
            elif isinstance(a, AutopilotAck):
                self.out.to_gcs_as(a.msg, self.sysid, self.ap_compid)
        if self.modes.mode == Mode.TELEOP and self._scan_t0_s is None:
            self._scan_t0_s = self.time.frame_stamp_s if self.time.frame_stamp_s is not None else 0.0
        elif self.modes.mode != Mode.TELEOP:
            self._scan_t0_s = None

    # ------------------------------------------------------------------ the loop
    def run(self, stop: threading.Event, duration_s: float | None = None) -> None:
        end = None if duration_s is None else self.clock() + duration_s
        while not stop.is_set() and (end is None or self.clock() < end):
            self.step()

    def step(self) -> None:
        self._drain_autopilot()
        self._drain_gcs()
        frame = self.camera.read(self.cfg.timing.poll_s)
        if frame is not None:
            self._wait_for_imu(frame.stamp_s)
            self._guarded("frame", self._process_frame, frame)
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

    def _drain_autopilot(self) -> None:
        for _ in range(MAX_ROUTED_PER_STEP):
            msg = self.autopilot.recv_msg()
            if msg is None:
                return
            if msg.get_type() != "BAD_DATA":
                self._guarded(f"autopilot {msg.get_type()}", self._on_autopilot, msg)

    def _drain_gcs(self) -> None:
        for _ in range(MAX_ROUTED_PER_STEP):
            msg = self.gcs.recv_msg()
            if msg is None:
                return
            if msg.get_type() == "BAD_DATA":
                self.stats.gcs_bad_data += 1   # includes what signing refused (unsigned, wrong key, replayed)
            else:
                self._guarded(f"ground station {msg.get_type()}", self._on_gcs, msg)

    def _wait_for_imu(self, stamp_s: float) -> None:
        """Let the IMU stream catch up with the frame (bounded), if it is flowing at all.

        If the wait keeps timing out the IMU structurally lags the frames on this setup (a producer that
        emits them later): stop waiting rather than add latency to every frame (the attitude filter
        extrapolates the last few ms).
        """
        t = self.cfg.timing
        imu = self.time
        if imu.imu_stamp_s is None or stamp_s - imu.imu_stamp_s > 0.2 or self._imu_wait_misses >= IMU_LAG_LIMIT:
            return
        deadline = self.clock() + t.imu_wait_s
        while imu.imu_stamp_s < stamp_s - t.imu_slack_s:
            if self.clock() >= deadline:
                self._imu_wait_misses += 1
                if self._imu_wait_misses == IMU_LAG_LIMIT:
                    log.info("IMU lags the camera frames by more than %.0f ms: not waiting for it any more",
                             t.imu_slack_s * 1e3)
                return
            self._drain_autopilot()
            time.sleep(0.0005)
        self._imu_wait_misses = 0

    # ------------------------------------------------------------------ autopilot side
    def _on_autopilot(self, msg: Any) -> None:
        self.out.log_packet(msg.get_msgbuf())
        kind = msg.get_type()
        route = route_from_autopilot(kind, getattr(msg, "target_component", None), self.compid)
        if route.consume:
            if kind == "HIGHRES_IMU":
                self._on_imu(msg)
            elif kind == "HEARTBEAT":
                if msg.autopilot != mavlink.MAV_AUTOPILOT_INVALID and msg.type != mavlink.MAV_TYPE_GCS:
                    self._on_autopilot_heartbeat(msg)
            elif kind == "EXTENDED_SYS_STATE":
                self.vehicle.landed_state = msg.landed_state
            elif kind == "COMMAND_ACK":
                done, failed = self.commands.on_ack(msg.command, msg.result, self.clock())
                if done is not None:
                    log.info("autopilot accepted %s", done.name)
                for req, why in failed:
                    self._emit(self.modes.on_request_failed(req, self.clock(), why))
            elif kind == "TIMESYNC":
                reply = self.timesync.on_message(msg, self.clock())   # TIMESYNC with the autopilot
                if reply is not None:
                    self.send_autopilot(reply)
        if route.forward and kind == "HEARTBEAT" and self.modes.in_control and \
                msg.autopilot != mavlink.MAV_AUTOPILOT_INVALID and msg.get_srcComponent() == self.ap_compid:
            self._forward_mode_heartbeat(msg)
        elif route.forward and self._forward(self.gcs, msg):
            self.stats.routed_to_gcs += 1

    def _forward_mode_heartbeat(self, msg: Any) -> None:
        """The autopilot's heartbeat with the mode of the motion authority (companion.gcs_commands)."""
        if self.out.to_gcs_as(self.gcs_commands.mode_heartbeat(msg), msg.get_srcSystem(), msg.get_srcComponent()):
            self.stats.routed_to_gcs += 1

    def _on_autopilot_heartbeat(self, msg: Any) -> None:
        src = msg.get_srcSystem()
        if src != self.sysid:
            log.info("autopilot is system %d: using it as our system id", src)
            self.sysid = src
            self.out.set_system_id(src)
            self.security.on_system_id(src)
        self.ap_compid = msg.get_srcComponent()
        self.vehicle.on_heartbeat(msg.base_mode, msg.custom_mode, self.clock())

    def _on_imu(self, msg: Any) -> None:
        stamp = msg.time_usec * 1e-6
        values = (msg.xgyro, msg.ygyro, msg.zgyro, msg.xacc, msg.yacc, msg.zacc)
        if not all(map(math.isfinite, values)) or msg.time_usec > MAX_STAMP_US:   # scalar checks: cheaper at 500 Hz
            return   # (fuzzing found: a uint64 stamp near 2**64 made the feedback's time_usec overflow when packed)
        gyro = np.array(values[:3])
        accel = np.array(values[3:])
        self.time.on_imu(stamp, self.clock())
        self._gyro_q = gyro
        self.perception.on_imu(stamp, gyro, accel)
        if self._feedback_ticker.due(stamp):
            self._send_feedback(stamp)

    # ------------------------------------------------------------------ ground-station side
    def _on_gcs(self, msg: Any) -> None:
        self.out.log_packet(msg.get_msgbuf())
        kind = msg.get_type()
        if not self.security.permits(msg):
            self.stats.refused_senders += 1
            self._emit(self.security.refuse_sender(msg))
            return
        target_system = msg.target if kind == "MANUAL_CONTROL" else getattr(msg, "target_system", None)
        if kind == "HEARTBEAT":
            self.arbiter.on_heartbeat(self.clock())
        elif kind == "COMMAND_LONG" and msg.command == mavlink.MAV_CMD_DO_SET_MODE and \
                target_system in (0, self.sysid) and msg.target_component in (0, self.ap_compid) and \
                self._on_gcs_set_mode(msg, msg.param1, msg.param2, msg.param3):
            return
        route = route_from_gcs(kind, target_system, getattr(msg, "target_component", None), self.sysid,
                               self.compid)
        if route.consume:
            if kind == "MANUAL_CONTROL":
                self._on_manual_control(msg)
            elif kind == "SET_POSITION_TARGET_LOCAL_NED":
                self._emit(self.gcs_commands.on_setpoint(msg, self._pose()))
            elif kind in ("SET_POSITION_TARGET_GLOBAL_INT", "SET_ATTITUDE_TARGET"):
                self._emit(self.gcs_commands.refuse_motion(f"{kind} not supported: use SET_POSITION_TARGET_LOCAL_NED "
                                                           "velocity"))
            elif kind == "SET_MODE":
                mode = decode_custom_mode(msg.custom_mode)
                if not self._on_gcs_set_mode(msg, msg.base_mode, mode.main, mode.sub, ack=False) and \
                        self._forward(self.autopilot, msg):
                    self.stats.routed_to_autopilot += 1   # not ours to answer: the autopilot's mode
            elif kind == "TIMESYNC":
                reply = self.command_clock.on_timesync(msg, self.clock())
                if reply is not None:
                    self.send_gcs(reply)
            elif kind == "COMMAND_STAMP":
                self.command_clock.on_stamp(msg, self.clock())
            elif kind == "COMMAND_LONG":
                self._emit(self.gcs_commands.on_command_long(msg))
            elif kind == "COMMAND_INT":
                self._emit(self.gcs_commands.on_command_int(msg))
            else:
                self._emit(self.param_service.on_message(msg))
        if route.forward and self._forward(self.autopilot, msg):
            self.stats.routed_to_autopilot += 1

    def _on_manual_control(self, msg: Any) -> None:
        """Only a fresh command moves the vehicle (companion.command_age) or keeps the link alive.

        The link's liveness counts from the *arrival* of the newest accepted command (counting from its send
        time would leave ``gcs_timeout_s`` minus the one-way delay of slack: at 300 ms one way the vehicle
        flapped between TELEOP and HOLD on every loss burst); the operator input itself is zeroed once that
        command is older than the age (:meth:`_operator`)."""
        now = self.clock()
        age = self.command_clock.on_command(msg, now)
        self.stats.manual_controls += 1
        if not age.accepted:
            return
        self.op = operator_from_manual_control(msg.x, msg.y, msg.z, self.ref_params.deadband)
        self.arbiter.on_manual_control(now, msg.x, msg.y, msg.z)
        self.modes.on_manual_control(now)

    def _operator_of(self, cmd: MotionCommand) -> OperatorInput:
        """The operator's input when the arbiter gives the operator control and its command is fresh."""
        if cmd.source != Source.OPERATOR or cmd.operator is None or not self.command_age.fresh(self.clock()):
            return OperatorInput()
        return cmd.operator

    def _pose(self) -> Pose:
        """What the arbiter needs of the state: the odometry's position and yaw, the pan-scan's offset; the height
        is the one held to the floor (companion.height), so a trajectory's altitude is the floor's, not the drift's."""
        out = self.last_output
        frame_s = self.time.frame_stamp_s
        scan = self._scan_state(frame_s) if frame_s is not None else NO_SCAN
        if out is None or not out.odometry_ok or out.position_m is None:
            return Pose(None, None, scan.yaw_offset_rad)
        p = self._position_m(out)
        return Pose((float(p[0]), float(p[1]), float(p[2])), float(out.yaw_rad), scan.yaw_offset_rad)

    def _position_m(self, out: Any) -> NDArray[np.float64]:
        """The odometry's position (local NED from the take-off pose) with the height held to the floor
        (:mod:`companion.height`): what the arbiter, the autopilot's ODOMETRY and the ground station get."""
        p = np.array(out.position_m, dtype=float)
        if self.height.height_m is not None and out.odometry_ok:
            p[2] = -self.height.height_m
        return p

    def _on_gcs_set_mode(self, msg: Any, base_mode: float, main: float, sub: float, ack: bool = True) -> bool:
        """A mode change for the autopilot (companion.gcs_commands): answered here, or not (it goes on)?"""
        handled, out = self.gcs_commands.on_set_mode(msg, base_mode, main, sub, ack)
        self._emit(out)
        return handled

    def _command(self) -> MotionCommand:
        """The arbiter's command now, its transitions as STATUSTEXT."""
        cmd = self.arbiter.command(self.clock(), self._pose())
        for text in self.arbiter.take_events():
            self._status_text(StatusText(mavlink.MAV_SEVERITY_WARNING if "lost" in text else mavlink.MAV_SEVERITY_INFO,
                                         f"companion: {text}"))
        if self.last_command is None or cmd.source != self.last_command.source:
            log.info("motion source: %s (%s)", cmd.source.name, cmd.reason)
        self.last_command = cmd
        return cmd

    def _camera_fresh(self) -> bool:
        return self.time.frame_wall_s is not None and \
            self.clock() - self.time.frame_wall_s <= self.cfg.timing.camera_timeout_s

    # ------------------------------------------------------------------ the pipeline at camera rate
    def _scan_state(self, stamp_s: float) -> PanScanState:
        if self.modes.mode != Mode.TELEOP or self._scan_t0_s is None:
            return NO_SCAN
        return pan_scan(self.scan_params, stamp_s - self._scan_t0_s)

    def _process_frame(self, frame: RgbdFrame) -> None:
        t_in = self.clock()
        self.stats.frames += 1
        self._R_qc = np.asarray(frame.R_qc, dtype=float)
        out = self.perception.on_frame(frame)
        ok = out is not None and bool(out.odometry_ok)
        if ok and not self.odometry_ok and self.stats.frames > 1:
            self._reset_counter += 1  # estimate restarted after a failure: tell the autopilot
        self.odometry_ok = ok
        stamp = self.time.on_frame(frame.stamp_s, self.clock())
        if self.modes.mode == Mode.TELEOP and self._scan_t0_s is None:
            self._scan_t0_s = stamp
        self._emit(self.modes.update(self.clock(), self.vehicle.status(), self.odometry_ok))
        if out is not None:
            self.last_output = out
            self.stats.perception_s.append(float(out.processing_time_s))
        height = self.height.update(stamp, height_m(out), None if out is None else out.floor_height_m)
        cmd = self._command()
        op = self._operator_of(cmd)
        step: FrameStep = frame_step(out, op, self._R_qc, self._scan_state(stamp), self.ref_params,
                                     self.modes.operator_enabled, self.cfg.obstacles.allow_unknown_when_fresh,
                                     v_command_h_m_s=cmd.v_h_m_s if cmd.source == Source.SCRIPT else None,
                                     command_yaw_rate_rad_s=cmd.yaw_rate_rad_s, height_above_takeoff_m=height,
                                     height_verified=self.height.verified(stamp),
                                     command_into_unknown=self.cfg.obstacles.scripts_into_unknown)
        self._nearest = step.nearest   # for TELEOP_FEEDBACK at 50 Hz
        self._avoid_points_h_m = step.obstacle_points_h_m   # the operator image's obstacle dots
        self.last_ref = step.ref
        a_ff = cmd.a_ff_h_m_s2 if cmd.source == Source.SCRIPT else None
        self._send_setpoint(stamp, step.ref,
                            feed_forward_after_safety(a_ff, step.ref.constrained, step.ref.v_repulsion_h_m_s))
        self.stats.latencies_s.append(self.clock() - t_in)
        if out is not None:
            self._send_odometry(stamp, out)
        self.camera.ack(frame.seq)
        if out is not None:
            self._send_gcs_telemetry(stamp, out)
            self._publish_image(frame, out, step.ref)
        if self.frame_recorder is not None:
            self._record_frame(frame)

    def _record_frame(self, frame: RgbdFrame) -> None:
        try:
            self.frame_recorder.write(frame)  # type: ignore[union-attr]
        except OSError as exc:  # a full disk stops the recording, never the flight loop
            log.error("frame recording stopped: %s", exc)
            self.frame_recorder = None

    def _send_setpoint(self, stamp_s: float, ref: ReferenceOutput, a_ff_h_m_s2: NDArray[np.float64] | None = None
                       ) -> None:
        """The safety layer's velocity (and a trajectory's acceleration feed-forward, when the layer left the
        velocity as commanded: :func:`companion.trajectory_follow.feed_forward_after_safety`)."""
        v, yaw_rate = setpoint_velocity(ref, self.modes.in_control)
        if not self.modes.in_control:
            a_ff_h_m_s2 = None
        self.send_autopilot(msgs.setpoint_message(stamp_s, self.sysid, self.ap_compid, v, yaw_rate, a_ff_h_m_s2))
        self.stats.setpoints += 1

    def _send_odometry(self, stamp_s: float, out: Any) -> None:
        m = msgs.odometry_message(stamp_s, self._position_m(out), out.roll_rad, out.pitch_rad, out.yaw_rad, out.v_h_m_s,
                                  out.omega_q_rad_s, out.v_h_cov, bool(out.odometry_ok),
                                  float(out.odometry_fitness), self._reset_counter)
        self.send_autopilot(m)
        self.send_gcs(m)

    def _send_gcs_telemetry(self, stamp_s: float, out: Any) -> None:
        self.send_gcs(msgs.attitude_message(stamp_s, out.roll_rad, out.pitch_rad, out.yaw_rad, out.omega_q_rad_s))
        self.send_gcs(msgs.local_position_message(stamp_s, self._position_m(out), out.yaw_rad, out.v_h_m_s))
        ob = self.cfg.obstacles
        self.send_gcs(msgs.obstacle_distance_message(stamp_s, out.sectors, ob.min_distance_cm, ob.max_distance_cm))

    def reported_companion_mode(self) -> Mode:
        """The mode machine's mode, HOLD while it is TELEOP but no source commands motion (the arbiter holds)."""
        if self.modes.mode == Mode.TELEOP and self.last_command is not None and self.last_command.hold:
            return Mode.HOLD
        return self.modes.mode

    def _send_feedback(self, stamp_s: float) -> None:
        self.send_gcs(feedback_message(stamp_s, self.last_output, self.last_ref, self._scan_state(stamp_s),
                                       self._R_qc, self._nearest, self._gyro_q, self.reported_companion_mode(),
                                       self.odometry_ok, self.modes.gcs_ok, self._camera_fresh()))
        self.stats.feedback += 1

    def image_meta(self, frame: RgbdFrame, out: Any, ref: ReferenceOutput) -> OperatorImageMeta:
        """The operator image's metadata for ``frame`` from the daemon's state now."""
        return operator_image_meta(frame.stamp_s, out, ref, self._scan_state(frame.stamp_s), self.scan_params,
                                   self._gyro_q, self.modes.mode, self._avoid_points_h_m, frame.R_qc, frame.p_qc_m)

    def _publish_image(self, frame: RgbdFrame, out: Any, ref: ReferenceOutput) -> None:
        if self.image_server is None or self.image_server.client_count == 0:
            return
        self.image_server.publish(frame, self.image_meta(frame, out, ref))   # never blocks (ImageSink)

    # ------------------------------------------------------------------ periodic tasks
    def _periodic(self) -> None:
        now = self.clock()
        t = self.cfg.timing
        camera_silent = self.time.frame_wall_s is None or now - self.time.frame_wall_s > t.camera_timeout_s
        if camera_silent:
            self.odometry_ok = False
        if self.arbiter.link_alive(now):
            # the ground station is there while it sends heartbeats, setpoints or MANUAL_CONTROL; a silent
            # motion source is the arbiter's business (it holds), not a lost link
            self.modes.on_manual_control(now)
        self.modes.on_motion_command(self.arbiter.last_command_s)   # a live link alone keeps no vehicle flying
        self._emit(self.modes.update(now, self.vehicle.status(), self.odometry_ok))
        send, failed = self.commands.poll(now)
        for req, why in failed:
            self._emit(self.modes.on_request_failed(req, now, why))
        for command, confirmation in send:
            self.send_autopilot(mavlink.MAVLink_command_long_message(
                self.sysid, self.ap_compid, command.command, confirmation, *command.params))
        if self.deadlines.due("heartbeat", now, 1.0 / t.heartbeat_rate_hz):
            hb = mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID,
                                                   0, int(self.modes.mode), mavlink.MAV_STATE_ACTIVE, 3)
            self.send_autopilot(hb)
            self.send_gcs(hb)
        if self.deadlines.due("timesync", now, t.timesync_period_s):
            self.send_autopilot(mavlink.MAVLink_timesync_message(0, int(now * 1e9)))
        if self.deadlines.due("gcs_timesync", now, self.cfg.links.gcs_timesync_period_s):
            self.send_gcs(mavlink.MAVLink_timesync_message(0, int(now * NS)))
        if self.deadlines.due("command_age", now, 1.0):   # the figures for the ground station (and the tlog)
            ms = int(self.time.estimate_s(self.clock()) * 1e3) & 0xFFFFFFFF
            self._emit(GcsReply(m) for m in self.command_clock.report(ms))
        if camera_silent and self.deadlines.due("fallback", now, 1.0 / t.fallback_setpoint_rate_hz):
            # keeps the autopilot's stream alive without a camera (frame_step.fallback_step)
            cmd = self._command()
            op = self._operator_of(cmd)
            ref = fallback_step(self.last_output, op, self._R_qc, self.ref_params, self.modes.operator_enabled,
                                height_above_takeoff_m=self.height.height_m,
                                height_verified=self.height.verified(self.time.estimate_s(now)))
            self.last_ref = ref
            self._send_setpoint(self.time.estimate_s(now), ref)
        imu_silent = self.time.imu_wall_s is None or now - self.time.imu_wall_s > IMU_SILENT_S
        if imu_silent and self.deadlines.due("feedback", now, 1.0 / t.feedback_rate_hz):
            self._send_feedback(self.time.estimate_s(now))
        if self.deadlines.due("progress", now, PROGRESS_EVERY_S):
            self._log_progress()

    def _log_progress(self) -> None:
        fps = (self.stats.frames - self._progress_frames) / PROGRESS_EVERY_S
        self._progress_frames = self.stats.frames
        h, off = self.height.height_m, self.height.offset_m
        height = "height ?" if h is None else f"height {h:.2f} m (floor {'?' if off is None else f'{off:+.2f}'})"
        log.info("mode %s  camera %.1f fps  %s  %s  %s", self.modes.mode.name, fps,
                 self.stats.summary(self.odometry_ok, self.modes.gcs_ok), height, self.command_clock.summary())
        self.stats.trim()

    def close(self) -> None:
        for name, closer in (("camera", self.camera.close), ("autopilot", self.autopilot.close),
                             ("gcs", self.gcs.close),
                             ("image stream", self.image_server.close if self.image_server else None),
                             ("tlog", self.tlog.close if self.tlog else None),
                             ("frame recording", self.frame_recorder.close if self.frame_recorder else None)):
            if closer is None:
                continue
            try:
                closer()
            except OSError as exc:
                log.warning("closing %s: %s", name, exc)

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
* :mod:`companion.modes`, :mod:`companion.commands` — the mode machine and the acked autopilot commands;
* :mod:`companion.guard` — one bad message never ends the loop: unexpected exceptions in its handling are
  caught, counted and logged once in a while; nothing non-finite goes to the autopilot.

The ground-station endpoint is hostile (issue 16): MAVLink 2 signing when configured (``security`` in the
config; pymavlink checks signatures and refuses replays on the endpoint's codec), state-changing messages
only from the allowlisted system ids (refused with COMMAND_ACK DENIED / a STATUSTEXT), command params read
through :mod:`quadlink.mavlink.command_params` (NaN = unused). The autopilot link is internal (the bridge
on the same board, or PX4 over its serial port): no signing there.

Clocks: the camera stamps (SITL: simulated time, = the autopilot's board time) stamp everything that
describes the vehicle (setpoints, odometry, feedback); the injected ``clock`` (monotonic wall time)
times the links (ground-station loss, camera silence, command acks), which are wall-time phenomena.
"""

from __future__ import annotations

import logging
import math
import struct
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion import messages as msgs
from companion.arbiter import Arbiter, MotionCommand, Pose, Setpoint, Source
from companion.cameras import CameraInput
from companion.command_age import CommandAgeFilter, CommandAgeParams, Sender
from companion.commands import CommandQueue
from companion.config import CompanionConfig
from companion.frame_step import (
    NO_SCAN,
    FrameStep,
    fallback_step,
    feedback_message,
    frame_step,
    operator_image_meta,
    setpoint_velocity,
)
from companion.guard import ErrorCounter, RateLimit, non_finite_fields
from companion.interfaces import ImageSink, MavLink, Pipeline, PipelineFactory, default_pipeline_factory
from companion.link_reader import CodecReader
from companion.modes import AutopilotRequest, Mode, ModeMachine, StatusText
from companion.pan_scan import PanScanParams, PanScanState, pan_scan
from companion.params import PARAM_NAMES, CompanionParams, handle_param_message, param_value_message, set_by_index
from companion.reference import OperatorInput, ReferenceOutput, ReferenceParams, operator_from_manual_control
from companion.router import route_from_autopilot, route_from_gcs
from companion.scheduler import Deadlines, StampTicker
from companion.stats import Stats
from companion.timesync import TimeSync
from companion.vehicle_state import VehicleState
from quadlink.camera import RgbdFrame
from quadlink.errors import QuadlinkError
from quadlink.mavlink import mavlink
from quadlink.mavlink.command_params import COMMAND_PARAMS, CommandParamError, read_params
from quadlink.mavlink.security import enable_signing
from quadlink.mavlink.timesync import NS, TimesyncConfig, TimesyncEstimator, answer_fields, is_request
from quadlink.operator_image import OperatorImageMeta
from quadlink.px4_modes import AUTO_LOITER, OFFBOARD, POSCTL, Px4MainMode, decode_custom_mode

log = logging.getLogger(__name__)

__all__ = ["PARAM_NAMES", "Companion", "ImageSink", "MavLink", "Pipeline", "Stats", "default_pipeline_factory"]

MAX_ROUTED_PER_STEP = 2000
MAX_GCS_SENDERS = 16        # TIMESYNC estimators kept for ground-station senders (every port is hostile)
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
        self._pipeline_factory = pipeline_factory
        self._pipeline: Pipeline | None = None
        self._pipeline_intrinsics: Any = None
        self.image_server = image_server
        self.tlog = tlog
        self.frame_recorder = frame_recorder   # quadlink.camera.FrameRecordWriter: every frame received
        self.clock, self.wall = clock, wall
        ident = cfg.identity
        self.sysid = ident.system_id
        self.compid = ident.component_id
        self.ap_compid = ident.autopilot_component_id
        self._codec = mavlink.MAVLink(None, self.sysid, self.compid)
        self._codec.robust_parsing = True
        self._gcs_codec = mavlink.MAVLink(None, self.sysid, self.compid)   # packs (and signs) for ground stations
        self._setup_gcs_security()
        self.errors = ErrorCounter(clock)
        self._refusal_limit = RateLimit(clock)
        self.params = CompanionParams(cfg.pan_scan, cfg.reference)
        self.modes = ModeMachine(cfg.modes)
        self.commands = CommandQueue()
        self.timesync = TimeSync()
        # the ground stations' command clock (issue 18): TIMESYNC with each sender, the commands' age
        self.gcs_sync: dict[Sender, TimesyncEstimator] = {}
        self._gcs_sync_cfg = TimesyncConfig(max_rtt_s=cfg.links.gcs_timesync_max_rtt_s)
        self.command_age = CommandAgeFilter(CommandAgeParams(max_command_age_s=cfg.links.max_command_age_s))
        self.vehicle = VehicleState()
        self.stats = Stats()
        self.op = OperatorInput()
        self.arbiter = Arbiter(cfg.arbiter)
        self.last_command: MotionCommand | None = None
        self._ap_codec = mavlink.MAVLink(None, self.sysid, self.ap_compid)   # replies made for the autopilot
        self._last_refusal = ""
        # perception / reference state (held between frames for the 50 Hz feedback)
        self.last_output: Any | None = None
        self.last_ref: ReferenceOutput | None = None
        self.last_frame_wall_s: float | None = None
        self.last_frame_stamp_s: float | None = None
        self.odometry_ok = False
        self._reset_counter = 0
        self._scan_t0_s: float | None = None
        self._imu_stamp_s: float | None = None
        self._imu_wall_s: float | None = None
        self._gyro_q = np.zeros(3)
        self._nearest: tuple[NDArray[np.float64], float] | None = None   # nearest obstacle (vector in H, m)
        self._avoid_points_h_m: NDArray[np.float64] | None = None   # the avoidance's points at the last frame
        self._imu_wait_misses = 0
        self._feedback_ticker = StampTicker(1.0 / cfg.timing.feedback_rate_hz)
        self.deadlines = Deadlines()
        self.deadlines.arm("progress", clock() + PROGRESS_EVERY_S)
        self._progress_frames = 0
        self._start_wall_s = clock()
        self._R_qc = np.eye(3)

    def _setup_gcs_security(self) -> None:
        """Signing on the ground-station endpoint (what we send, and pymavlink's check of what it receives on
        the link's own codec) and the allowlist of senders."""
        sec = self.cfg.security
        self.allowlist = sec.allowlist(self.sysid)
        key = sec.key()
        self.signing = key is not None
        if key is None:
            return
        rx = getattr(self.gcs, "mav", None)
        if rx is None or not hasattr(rx, "signing"):
            raise QuadlinkError("signing configured but the ground-station link has no MAVLink codec to check it")
        enable_signing(self._gcs_codec, key, sec.require_signing, link_id=0, unix_time_s=self.wall())
        enable_signing(rx, key, sec.require_signing, link_id=0, unix_time_s=self.wall())
        log.info("ground-station endpoint: MAVLink 2 signing %s", "required" if sec.require_signing else "optional")

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
        old = self.params.values().get(name)
        if not self.params.set(name, value):
            return False
        self._param_changed(name, old)
        return True

    def _param_changed(self, name: str, old: float | None) -> None:
        self._status_text(StatusText(6, f"companion: {name} {old:g} -> {self.params.values()[name]:g}"))

    # ------------------------------------------------------------------ sending
    def _log_packet(self, buf: bytes) -> None:
        if self.tlog is not None:
            self.tlog.write(buf, self.wall())

    def _send(self, link: MavLink, msg: Any, codec: Any | None = None) -> None:
        try:
            buf = bytes(msg.pack(self._codec if codec is None else codec))
        except (struct.error, OverflowError, ValueError, TypeError) as exc:  # one bad value drops one message
            self.errors.record(f"packing {msg.get_type()}", exc)
            return
        try:
            link.write(buf)
        except OSError as exc:  # a link hiccup must never stop the loop
            log.debug("send %s failed: %s", msg.get_type(), exc)
        self._log_packet(buf)

    def send_autopilot(self, msg: Any) -> None:
        bad = non_finite_fields(msg)
        if bad:   # never reaches the autopilot (the setpoint path holds before this: frame_step.setpoint_velocity)
            self.stats.non_finite_dropped += 1
            self.errors.record(f"non-finite {msg.get_type()}", ValueError(", ".join(bad)))
            return
        self._send(self.autopilot, msg)

    def send_gcs(self, msg: Any, src_component: int | None = None) -> None:
        """Pack (signed when configured) and send to the ground stations; ``src_component`` answers for another
        component of this system (the autopilot's acks)."""
        if src_component is None:
            self._send(self.gcs, msg, self._gcs_codec)
            return
        own, self._gcs_codec.srcComponent = self._gcs_codec.srcComponent, src_component
        try:
            self._send(self.gcs, msg, self._gcs_codec)
        finally:
            self._gcs_codec.srcComponent = own

    def _forward(self, link: MavLink, msg: Any) -> bool:
        if link is self.autopilot and non_finite_fields(msg, any_command=True):
            self._refuse_forward(msg)   # a ground station's NaN/inf never reaches the autopilot either
            return False
        try:
            link.write(msg.get_msgbuf())
            return True
        except OSError as exc:
            log.debug("routing %s failed: %s", msg.get_type(), exc)
            return False

    def _status_text(self, st: StatusText) -> None:
        level = logging.WARNING if st.severity <= mavlink.MAV_SEVERITY_WARNING else logging.INFO
        log.log(level, "%s", st.text)
        self.send_gcs(mavlink.MAVLink_statustext_message(st.severity, st.text.encode()[:50]))

    def _actions(self, actions: list[Any]) -> None:
        for a in actions:
            if isinstance(a, StatusText):
                self._status_text(a)
            elif isinstance(a, AutopilotRequest):
                self.commands.push(a)
        if self.modes.mode == Mode.TELEOP and self._scan_t0_s is None:
            self._scan_t0_s = self.last_frame_stamp_s if self.last_frame_stamp_s is not None else 0.0
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
        if self._imu_stamp_s is None or stamp_s - self._imu_stamp_s > 0.2 or self._imu_wait_misses >= IMU_LAG_LIMIT:
            return
        deadline = self.clock() + t.imu_wait_s
        while self._imu_stamp_s < stamp_s - t.imu_slack_s:
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
        self._log_packet(msg.get_msgbuf())
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
                    self._actions(self.modes.on_request_failed(req, self.clock(), why))
            elif kind == "TIMESYNC":
                self._on_timesync(msg)
        if route.forward and kind == "HEARTBEAT" and self.modes.in_control and \
                msg.autopilot != mavlink.MAV_AUTOPILOT_INVALID and msg.get_srcComponent() == self.ap_compid:
            self._forward_mode_heartbeat(msg)
        elif route.forward and self._forward(self.gcs, msg):
            self.stats.routed_to_gcs += 1

    def reported_mode(self) -> int:
        """The PX4 custom mode the ground station sees while the companion flies the vehicle: OFFBOARD while a
        script is engaged (MAVSDK's offboard plugin checks it), POSCTL while the operator flies, else hold."""
        now = self.clock()
        if self.arbiter.offboard_engaged:
            return OFFBOARD.custom_mode
        return (POSCTL if self.arbiter.operator_alive(now) else AUTO_LOITER).custom_mode

    def _forward_mode_heartbeat(self, msg: Any) -> None:
        """The autopilot's heartbeat with the mode of the motion authority (the companion's arbiter)."""
        base_mode = msg.base_mode | mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        hb = mavlink.MAVLink_heartbeat_message(msg.type, msg.autopilot, base_mode, self.reported_mode(),
                                               msg.system_status, msg.mavlink_version)
        self._ap_codec.srcSystem, self._ap_codec.srcComponent = msg.get_srcSystem(), msg.get_srcComponent()
        try:
            self.gcs.write(bytes(hb.pack(self._ap_codec)))
            self.stats.routed_to_gcs += 1
        except OSError as exc:
            log.debug("routing HEARTBEAT failed: %s", exc)

    def _on_autopilot_heartbeat(self, msg: Any) -> None:
        src = msg.get_srcSystem()
        if src != self.sysid:
            log.info("autopilot is system %d: using it as our system id", src)
            self.sysid = src
            self._codec.srcSystem = self._gcs_codec.srcSystem = src
            self.allowlist = self.cfg.security.allowlist(src)
        self.ap_compid = msg.get_srcComponent()
        armed = bool(msg.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
        if armed != self.vehicle.armed:
            log.info("autopilot %s", "armed" if armed else "disarmed")
        self.vehicle.armed = armed
        self.vehicle.custom_mode = msg.custom_mode
        self.vehicle.heartbeat_wall_s = self.clock()

    def _on_imu(self, msg: Any) -> None:
        stamp = msg.time_usec * 1e-6
        values = (msg.xgyro, msg.ygyro, msg.zgyro, msg.xacc, msg.yacc, msg.zacc)
        if not all(map(math.isfinite, values)) or msg.time_usec > MAX_STAMP_US:   # scalar checks: cheaper at 500 Hz
            return   # (fuzzing found: a uint64 stamp near 2**64 made the feedback's time_usec overflow when packed)
        gyro = np.array(values[:3])
        accel = np.array(values[3:])
        self._imu_stamp_s, self._imu_wall_s, self._gyro_q = stamp, self.clock(), gyro
        if self._pipeline is not None:
            try:
                self._pipeline.on_imu(stamp, gyro, accel)
            except (ValueError, ArithmeticError, QuadlinkError) as exc:
                self.stats.pipeline_errors += 1
                log.warning("perception rejected an IMU sample: %s", exc)
        if self._feedback_ticker.due(stamp):
            self._send_feedback(stamp)

    def _on_timesync(self, msg: Any) -> None:
        now_ns = int(self.clock() * 1e9)
        if msg.tc1 == 0:  # a request from the autopilot: answer with our clock
            self.send_autopilot(mavlink.MAVLink_timesync_message(now_ns, msg.ts1))
        elif self.timesync.on_response(msg.tc1, msg.ts1, now_ns):
            log.debug("timesync offset %.3f ms rtt %.3f ms", self.timesync.offset_ns * 1e-6,  # type: ignore[operator]
                      self.timesync.rtt_ns * 1e-6)  # type: ignore[operator]

    # ------------------------------------------------------------------ ground-station side
    def _on_gcs(self, msg: Any) -> None:
        self._log_packet(msg.get_msgbuf())
        kind = msg.get_type()
        if not self.allowlist.permits(msg):
            self._refuse_sender(msg)
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
                self._on_gcs_setpoint(msg)
            elif kind in ("SET_POSITION_TARGET_GLOBAL_INT", "SET_ATTITUDE_TARGET"):
                self._refuse(f"{kind} not supported: use SET_POSITION_TARGET_LOCAL_NED velocity")
            elif kind == "SET_MODE":
                mode = decode_custom_mode(msg.custom_mode)
                if not self._on_gcs_set_mode(msg, msg.base_mode, mode.main, mode.sub, ack=False) and \
                        self._forward(self.autopilot, msg):
                    self.stats.routed_to_autopilot += 1   # not ours to answer: the autopilot's mode
            elif kind == "TIMESYNC":
                self._on_gcs_timesync(msg)
            elif kind == "COMMAND_STAMP":
                self.command_age.on_stamp((msg.get_srcSystem(), msg.get_srcComponent()), msg.get_seq(),
                                          msg.time_usec, msg.command_msgid, self.clock())
            elif kind == "COMMAND_LONG":
                self._on_gcs_command(msg)
            else:
                before = self.params.values()
                replies, changed = handle_param_message(self.params, msg)
                if changed is not None:
                    self._param_changed(changed, before[changed])
                for reply in replies:
                    self.send_gcs(reply)
        if route.forward and self._forward(self.autopilot, msg):
            self.stats.routed_to_autopilot += 1

    def _on_manual_control(self, msg: Any) -> None:
        """Only a fresh command moves the vehicle (companion.command_age) or keeps the link alive.

        The link's liveness counts from the *arrival* of the newest accepted command (counting from its send
        time would leave ``gcs_timeout_s`` minus the one-way delay of slack: at 300 ms one way the vehicle
        flapped between TELEOP and HOLD on every loss burst); the operator input itself is zeroed once that
        command is older than the age (:meth:`_operator`)."""
        now = self.clock()
        sender = (msg.get_srcSystem(), msg.get_srcComponent())
        sync = self.gcs_sync.get(sender)
        offset_s = None if sync is None or sync.offset_ns is None else sync.offset_ns / NS
        age = self.command_age.on_command(sender, msg.get_seq(), msg.get_msgId(), now, offset_s)
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

    def _on_gcs_timesync(self, msg: Any) -> None:
        now_ns = int(self.clock() * NS)
        if is_request(msg.tc1):   # a ground station measuring its round trip to us: our clock
            self.send_gcs(mavlink.MAVLink_timesync_message(*answer_fields(msg.ts1, now_ns)))
            return
        sender = (msg.get_srcSystem(), msg.get_srcComponent())
        sync = self.gcs_sync.get(sender)
        if sync is None:
            if len(self.gcs_sync) >= MAX_GCS_SENDERS:
                return
            sync = self.gcs_sync[sender] = TimesyncEstimator(self._gcs_sync_cfg)
        sync.on_response(msg.tc1, msg.ts1, now_ns)

    def _pose(self) -> Pose:
        """What the arbiter needs of the state: the odometry's position and yaw, the pan-scan's offset."""
        out = self.last_output
        scan = self._scan_state(self.last_frame_stamp_s) if self.last_frame_stamp_s is not None else NO_SCAN
        if out is None or not out.odometry_ok or out.position_m is None:
            return Pose(None, None, scan.yaw_offset_rad)
        p = np.asarray(out.position_m, dtype=float)
        return Pose((float(p[0]), float(p[1]), float(p[2])), float(out.yaw_rad), scan.yaw_offset_rad)

    def _refuse(self, text: str) -> None:
        """A refused motion command: STATUSTEXT once per distinct reason (a script streams at 20 Hz)."""
        if text != self._last_refusal:
            self._last_refusal = text
            self._status_text(StatusText(mavlink.MAV_SEVERITY_WARNING, f"companion: {text}"))

    def _on_gcs_setpoint(self, msg: Any) -> None:
        sp = Setpoint(msg.coordinate_frame, msg.type_mask, (msg.x, msg.y, msg.z), (msg.vx, msg.vy, msg.vz), msg.yaw,
                      msg.yaw_rate)
        refusal = self.arbiter.on_setpoint(self.clock(), sp, self._pose())
        if refusal is not None:
            self._refuse(refusal.text)
        else:
            self._last_refusal = ""

    def _on_gcs_set_mode(self, msg: Any, base_mode: float, main: float, sub: float, ack: bool = True) -> bool:
        """A mode change for the autopilot. OFFBOARD engages a script, a hold-like mode (POSCTL, ALTCTL,
        AUTO_LOITER) disengages it — answered here, as the autopilot would, while the companion flies the
        vehicle (its heartbeat reports the arbiter's mode). Other modes (LAND, RTL, ...) and every mode
        change while the companion is not in control go on to the autopilot. Handled here?"""
        if not (int(base_mode) & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED) or not all(map(math.isfinite, (main, sub))):
            return False
        main_i, sub_i = int(main), int(sub)
        offboard = main_i == Px4MainMode.OFFBOARD
        hold = main_i in (Px4MainMode.POSCTL, Px4MainMode.ALTCTL) or \
            (main_i == AUTO_LOITER.main and sub_i == AUTO_LOITER.sub)
        if not (offboard or hold):
            return False
        accepted = self.arbiter.on_set_mode(self.clock(), offboard)
        for text in self.arbiter.take_events():
            self._status_text(StatusText(mavlink.MAV_SEVERITY_INFO, f"companion: {text}"))
        if not self.modes.in_control:
            return False   # the autopilot flies its own mode: it answers
        if ack:
            result = mavlink.MAV_RESULT_ACCEPTED if accepted else mavlink.MAV_RESULT_DENIED
            reply = mavlink.MAVLink_command_ack_message(mavlink.MAV_CMD_DO_SET_MODE, result, 0, 0, msg.get_srcSystem(),
                                                        msg.get_srcComponent())
            self._ap_codec.srcSystem, self._ap_codec.srcComponent = self.sysid, self.ap_compid
            try:
                self.gcs.write(bytes(reply.pack(self._ap_codec)))
            except OSError as exc:
                log.debug("mode ack failed: %s", exc)
        return True

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
        return self.last_frame_wall_s is not None and \
            self.clock() - self.last_frame_wall_s <= self.cfg.timing.camera_timeout_s

    def _refuse_sender(self, msg: Any) -> None:
        """A state-changing message from a system id not on the allowlist: COMMAND_ACK DENIED for a command,
        a STATUSTEXT (at most one per sender and kind every 2 s), nothing executed or forwarded."""
        self.stats.refused_senders += 1
        kind, src = msg.get_type(), msg.get_srcSystem()
        if kind in ("COMMAND_LONG", "COMMAND_INT"):
            target = msg.target_component
            self.send_gcs(mavlink.MAVLink_command_ack_message(msg.command, mavlink.MAV_RESULT_DENIED, 0, 0, src,
                                                              msg.get_srcComponent()),
                          src_component=None if target in (0, self.compid) else target)
        if self._refusal_limit.allow((src, kind)):
            self._status_text(StatusText(mavlink.MAV_SEVERITY_WARNING,
                                         f"companion: {kind} from sysid {src} refused (not allowed)"))

    def _refuse_forward(self, msg: Any) -> None:
        """A ground-station message for the autopilot with a non-finite value: dropped, counted; a command is
        answered DENIED (as the component it targeted) and the sender told once in a while."""
        self.stats.forward_refused += 1
        kind, src = msg.get_type(), msg.get_srcSystem()
        if kind in ("COMMAND_LONG", "COMMAND_INT"):
            self.send_gcs(mavlink.MAVLink_command_ack_message(msg.command, mavlink.MAV_RESULT_DENIED, 0, 0, src,
                                                              msg.get_srcComponent()),
                          src_component=msg.target_component or self.ap_compid)
        if self._refusal_limit.allow((src, kind, "non-finite")):
            self._status_text(StatusText(mavlink.MAV_SEVERITY_WARNING,
                                         f"companion: {kind} not forwarded: non-finite value"))

    def _on_gcs_command(self, msg: Any) -> None:
        cmd = msg.command
        result = mavlink.MAV_RESULT_UNSUPPORTED
        try:   # MAVLink's NaN = "unused" per command; a required param NaN/inf/out of range: DENIED
            p = read_params(cmd, (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6,
                                  msg.param7)) if cmd in COMMAND_PARAMS else (math.nan,) * 7
        except CommandParamError as exc:
            self._status_text(StatusText(mavlink.MAV_SEVERITY_WARNING, f"companion: {exc}"))
            self.send_gcs(mavlink.MAVLink_command_ack_message(cmd, mavlink.MAV_RESULT_DENIED, 0, 0,
                                                              msg.get_srcSystem(), msg.get_srcComponent()))
            return
        name = {mavlink.MAV_CMD_NAV_TAKEOFF: "takeoff", mavlink.MAV_CMD_NAV_LAND: "land"}.get(cmd)
        if cmd == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
            name = "arm" if p[0] == 1.0 else "disarm"
        if name == "takeoff" and not self._camera_fresh():
            self._status_text(StatusText(mavlink.MAV_SEVERITY_WARNING,
                                         "companion: takeoff refused: no camera frames (perception not running)"))
            result = mavlink.MAV_RESULT_TEMPORARILY_REJECTED
        elif name is not None:
            ok, actions = self.modes.request(name, self.clock(), self.vehicle.status())
            self._actions(actions)
            result = mavlink.MAV_RESULT_ACCEPTED if ok else mavlink.MAV_RESULT_TEMPORARILY_REJECTED
        elif cmd == mavlink.MAV_CMD_DO_SET_PARAMETER:
            index = int(p[0])   # read_params: a finite whole number
            old = self.params.values().get(PARAM_NAMES[index]) if 0 <= index < len(PARAM_NAMES) else None
            changed = set_by_index(self.params, index, p[1])
            result = mavlink.MAV_RESULT_ACCEPTED if changed else mavlink.MAV_RESULT_DENIED
            if changed:
                self._param_changed(changed, old)
            if old is not None:   # the value now, changed or not (as a refused PARAM_SET is answered)
                self.send_gcs(param_value_message(self.params, index))
        self.send_gcs(mavlink.MAVLink_command_ack_message(cmd, result, 0, 0, msg.get_srcSystem(),
                                                          msg.get_srcComponent()))

    # ------------------------------------------------------------------ the pipeline at camera rate
    def _scan_state(self, stamp_s: float) -> PanScanState:
        if self.modes.mode != Mode.TELEOP or self._scan_t0_s is None:
            return NO_SCAN
        return pan_scan(self.scan_params, stamp_s - self._scan_t0_s)

    def _perceive(self, frame: RgbdFrame) -> Any | None:
        if self._pipeline is None:
            self._pipeline = self._pipeline_factory(frame)
            self._pipeline_intrinsics = frame.intrinsics
            log.info("perception started on %dx%d frames", frame.intrinsics.width, frame.intrinsics.height)
        elif frame.intrinsics != self._pipeline_intrinsics:   # the camera does not change mid-flight: hostile
            self.stats.pipeline_errors += 1
            self.errors.record("camera frame", ValueError(
                f"frame {frame.seq} is {frame.intrinsics.width}x{frame.intrinsics.height} with other intrinsics "
                "than the stream's first: not processed"))
            return None
        try:
            return self._pipeline.on_frame(frame)
        except (ValueError, ArithmeticError, np.linalg.LinAlgError, QuadlinkError) as exc:
            self.stats.pipeline_errors += 1
            log.warning("perception failed on frame %d: %s", frame.seq, exc)
            return None

    def _process_frame(self, frame: RgbdFrame) -> None:
        t_in = self.clock()
        self.stats.frames += 1
        self._R_qc = np.asarray(frame.R_qc, dtype=float)
        out = self._perceive(frame)
        ok = out is not None and bool(out.odometry_ok)
        if ok and not self.odometry_ok and self.stats.frames > 1:
            self._reset_counter += 1  # estimate restarted after a failure: tell the autopilot
        self.odometry_ok = ok
        stamp = self._stamp_to_autopilot(frame.stamp_s)
        self.last_frame_wall_s, self.last_frame_stamp_s = self.clock(), stamp
        if self.modes.mode == Mode.TELEOP and self._scan_t0_s is None:
            self._scan_t0_s = stamp
        self._actions(self.modes.update(self.clock(), self.vehicle.status(), self.odometry_ok))
        if out is not None:
            self.last_output = out
            self.stats.perception_s.append(float(out.processing_time_s))
        cmd = self._command()
        op = self._operator_of(cmd)
        step: FrameStep = frame_step(out, op, self._R_qc, self._scan_state(stamp), self.ref_params,
                                     self.modes.operator_enabled, self.cfg.obstacles.allow_unknown_when_fresh,
                                     v_command_h_m_s=cmd.v_h_m_s if cmd.source == Source.SCRIPT else None,
                                     command_yaw_rate_rad_s=cmd.yaw_rate_rad_s)
        self._nearest = step.nearest   # for TELEOP_FEEDBACK at 50 Hz
        self._avoid_points_h_m = step.obstacle_points_h_m   # the operator image's obstacle dots
        self.last_ref = step.ref
        self._send_setpoint(stamp, step.ref)
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

    def _stamp_to_autopilot(self, stamp_s: float) -> float:
        if self.cfg.timing.camera_stamps == "local":
            remote = self.timesync.to_remote_s(stamp_s)
            return stamp_s if remote is None else remote
        return stamp_s

    def _send_setpoint(self, stamp_s: float, ref: ReferenceOutput) -> None:
        v, yaw_rate = setpoint_velocity(ref, self.modes.in_control)
        self.send_autopilot(msgs.setpoint_message(stamp_s, self.sysid, self.ap_compid, v, yaw_rate))
        self.stats.setpoints += 1

    def _send_odometry(self, stamp_s: float, out: Any) -> None:
        m = msgs.odometry_message(stamp_s, out.position_m, out.roll_rad, out.pitch_rad, out.yaw_rad, out.v_h_m_s,
                                  out.omega_q_rad_s, out.v_h_cov, bool(out.odometry_ok),
                                  float(out.odometry_fitness), self._reset_counter)
        self.send_autopilot(m)
        self.send_gcs(m)

    def _send_gcs_telemetry(self, stamp_s: float, out: Any) -> None:
        self.send_gcs(msgs.attitude_message(stamp_s, out.roll_rad, out.pitch_rad, out.yaw_rad, out.omega_q_rad_s))
        self.send_gcs(msgs.local_position_message(stamp_s, out.position_m, out.yaw_rad, out.v_h_m_s))
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
        camera_silent = self.last_frame_wall_s is None or now - self.last_frame_wall_s > t.camera_timeout_s
        if camera_silent:
            self.odometry_ok = False
        if self.arbiter.link_alive(now):
            # the ground station is there while it sends heartbeats, setpoints or MANUAL_CONTROL; a silent
            # motion source is the arbiter's business (it holds), not a lost link
            self.modes.on_manual_control(now)
        self._actions(self.modes.update(now, self.vehicle.status(), self.odometry_ok))
        send, failed = self.commands.poll(now)
        for req, why in failed:
            self._actions(self.modes.on_request_failed(req, now, why))
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
        if self.deadlines.due("command_age", now, 1.0):
            self._send_command_age()
        if camera_silent and self.deadlines.due("fallback", now, 1.0 / t.fallback_setpoint_rate_hz):
            # keeps the autopilot's stream alive without a camera (frame_step.fallback_step)
            cmd = self._command()
            op = self._operator_of(cmd)
            ref = fallback_step(self.last_output, op, self._R_qc, self.ref_params, self.modes.operator_enabled)
            self.last_ref = ref
            self._send_setpoint(self._fallback_stamp(now), ref)
        imu_silent = self._imu_wall_s is None or now - self._imu_wall_s > IMU_SILENT_S
        if imu_silent and self.deadlines.due("feedback", now, 1.0 / t.feedback_rate_hz):
            self._send_feedback(self._fallback_stamp(now))
        if self.deadlines.due("progress", now, PROGRESS_EVERY_S):
            self._log_progress()

    def _send_command_age(self) -> None:
        """The commands' age figures as NAMED_VALUE_* to the ground station (and the tlog: the demo report)."""
        c = self.command_age.counts
        ms = int(self._fallback_stamp(self.clock()) * 1e3) & 0xFFFFFFFF
        for name, value in (("CMD_OK", c.accepted), ("CMD_DROP", c.dropped), ("CMD_STALE", c.stale),
                            ("CMD_UNPAIR", c.unpaired)):
            self.send_gcs(mavlink.MAVLink_named_value_int_message(ms, name.encode(), value))
        for name, q in (("CMD_AGE50", 50.0), ("CMD_AGE99", 99.0)):
            age = self.command_age.age_percentile_s(q)
            if math.isfinite(age):
                self.send_gcs(mavlink.MAVLink_named_value_float_message(ms, name.encode(), age))

    def _log_progress(self) -> None:
        fps = (self.stats.frames - self._progress_frames) / PROGRESS_EVERY_S
        self._progress_frames = self.stats.frames
        c = self.command_age.counts
        log.info("mode %s  camera %.1f fps  %s  commands %d ok / %d dropped (stale %d, unpaired %d), age p50 %.0f "
                 "p99 %.0f ms", self.modes.mode.name, fps, self.stats.summary(self.odometry_ok, self.modes.gcs_ok),
                 c.accepted, c.dropped, c.stale, c.unpaired, self.command_age.age_percentile_s(50) * 1e3,
                 self.command_age.age_percentile_s(99) * 1e3)
        self.stats.trim()

    def _fallback_stamp(self, now: float) -> float:
        """Autopilot time estimate without a fresh frame: last IMU or frame stamp plus the wall time since."""
        if self._imu_stamp_s is not None and self._imu_wall_s is not None:
            return self._imu_stamp_s + (now - self._imu_wall_s)
        if self.last_frame_stamp_s is not None and self.last_frame_wall_s is not None:
            return self.last_frame_stamp_s + (now - self.last_frame_wall_s)
        return now - self._start_wall_s

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

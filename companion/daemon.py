"""The companion daemon: camera + autopilot + ground station -> perception -> reference -> setpoints.

Concurrency model: **one thread, one loop** (:meth:`Companion.step`). Each iteration drains the two
MAVLink endpoints (non-blocking UDP/serial reads), waits up to ``timing.poll_s`` for a camera frame,
processes it, and runs the periodic tasks (modes, command retries, heartbeats, TIMESYNC, fallback
setpoints). Every wait is bounded; :meth:`Companion.close` releases everything. The only other threads
are those inside :class:`quadlink.camera.CameraStreamServer` (accepting operator-view clients).

Clocks: the camera stamps (SITL: simulated time, = the autopilot's board time) stamp everything that
describes the vehicle (setpoints, odometry, feedback); the injected ``clock`` (monotonic wall time)
times the links (ground-station loss, camera silence, command acks), which are wall-time phenomena.

Routing (like mavlink-router on a companion computer): everything from the autopilot goes to the
ground-station endpoint except what is addressed to this component; everything from a ground station
addressed to the autopilot's system (or broadcast) goes to the autopilot, except MANUAL_CONTROL (the
companion consumes it: it is the operator's command to the companion) and what is addressed to this
component (COMMAND_LONG, PARAM_* for compid 191). Broadcast parameter requests are answered by both.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from companion import messages as msgs
from companion.cameras import CameraInput
from companion.commands import (
    PX4_CUSTOM_MAIN_MODE_AUTO,
    PX4_CUSTOM_SUB_MODE_AUTO_LAND,
    PX4_CUSTOM_SUB_MODE_AUTO_TAKEOFF,
    CommandQueue,
)
from companion.config import CompanionConfig, pan_scan_params
from companion.link_reader import CodecReader
from companion.modes import AutopilotRequest, Mode, ModeMachine, StatusText, VehicleStatus
from companion.pan_scan import PanScanParams, PanScanState, pan_scan
from companion.reference import (
    OperatorInput,
    ReferenceOutput,
    ReferenceParams,
    camera_yaw_rad,
    nearest_obstacle,
    operator_from_manual_control,
    reference_velocity,
)
from companion.timesync import TimeSync
from quadlink.camera import RgbdFrame
from quadlink.errors import QuadlinkError
from quadlink.mavlink import mavlink

log = logging.getLogger(__name__)


class MavLink(Protocol):
    """What the daemon needs of a pymavlink ``mavfile``."""

    def recv_msg(self) -> Any: ...

    def write(self, buf: bytes) -> Any: ...

    def close(self) -> Any: ...


class Pipeline(Protocol):
    """The perception façade (``perception.pipeline.PerceptionPipeline``)."""

    def on_imu(self, stamp_s: float, gyro_q_rad_s: NDArray[np.float64], accel_q_m_s2: NDArray[np.float64]) -> None: ...

    def on_frame(self, frame: RgbdFrame) -> Any: ...


PipelineFactory = Callable[[RgbdFrame], Pipeline]

# Companion parameters (PARAM_* to compid 191; also MAV_CMD_DO_SET_PARAMETER param1 = index).
PARAM_NAMES = ("PANSCAN_EN", "PANSCAN_AMP", "PANSCAN_OMEGA", "CMP_K_V", "CMP_K_PSI", "CMP_SAFE_DIST")
MAX_ROUTED_PER_STEP = 2000
MAX_IMAGE_POINTS = 400
PROGRESS_EVERY_S = 5.0


@dataclass
class Stats:
    frames: int = 0
    setpoints: int = 0
    feedback: int = 0
    routed_to_gcs: int = 0
    routed_to_autopilot: int = 0
    manual_controls: int = 0
    pipeline_errors: int = 0
    latencies_s: list[float] = field(default_factory=list)
    perception_s: list[float] = field(default_factory=list)


def _recent_median_ms(values_s: list[float], n: int = 300) -> str:
    """Median of the last ``n`` durations, for the status line."""
    recent = sorted(values_s[-n:])
    return f"{recent[len(recent) // 2] * 1e3:.1f} ms" if recent else "-"


@dataclass
class _Vehicle:
    armed: bool = False
    landed_state: int | None = None
    custom_mode: int = 0
    heartbeat_wall_s: float | None = None

    def status(self) -> VehicleStatus:
        main = (self.custom_mode >> 16) & 0xFF
        sub = (self.custom_mode >> 24) & 0xFF
        if self.landed_state is not None and self.landed_state != mavlink.MAV_LANDED_STATE_UNDEFINED:
            in_air = self.landed_state in (mavlink.MAV_LANDED_STATE_IN_AIR, mavlink.MAV_LANDED_STATE_TAKEOFF,
                                           mavlink.MAV_LANDED_STATE_LANDING)
        else:
            in_air = self.armed
        taking_off = (self.landed_state == mavlink.MAV_LANDED_STATE_TAKEOFF
                      or (main == PX4_CUSTOM_MAIN_MODE_AUTO and sub == PX4_CUSTOM_SUB_MODE_AUTO_TAKEOFF))
        landing = (self.landed_state == mavlink.MAV_LANDED_STATE_LANDING
                   or (main == PX4_CUSTOM_MAIN_MODE_AUTO and sub == PX4_CUSTOM_SUB_MODE_AUTO_LAND))
        return VehicleStatus(self.armed, in_air, taking_off, landing, self.landed_state is not None)


def default_pipeline_factory(cfg: CompanionConfig, seed: int = 0) -> PipelineFactory:
    """Builds ``perception.pipeline.PerceptionPipeline`` on the first frame (its intrinsics and mount)."""
    try:
        from perception.pipeline import PerceptionConfig, PerceptionPipeline
    except ImportError as exc:
        raise QuadlinkError(f"perception pipeline not available ({exc}); the companion needs perception/pipeline.py"
                            ) from exc
    from quadlink.config import load_config

    pcfg = load_config(cfg.perception_config, PerceptionConfig) if cfg.perception_config else PerceptionConfig()

    def make(frame: RgbdFrame) -> Pipeline:
        return PerceptionPipeline(pcfg, frame.intrinsics, frame.R_qc, frame.p_qc_m, np.random.default_rng(seed))

    return make


class Companion:
    """The daemon's state and its single loop. Links are injected (tests use ephemeral UDP ports)."""

    def __init__(self, cfg: CompanionConfig, autopilot: MavLink, gcs: MavLink, camera: CameraInput,
                 pipeline_factory: PipelineFactory, image_server: Any | None = None, tlog: Any | None = None,
                 clock: Callable[[], float] = time.monotonic, wall: Callable[[], float] = time.time,
                 frame_recorder: Any | None = None) -> None:
        self.cfg = cfg
        # the autopilot link (500 Hz HIGHRES_IMU) is decoded by the dialect's codec, not mavutil's recv_msg
        self.autopilot: MavLink = CodecReader(autopilot) if hasattr(autopilot, "recv") else autopilot
        self.gcs, self.camera = gcs, camera
        self._pipeline_factory = pipeline_factory
        self._pipeline: Pipeline | None = None
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
        self.ref_params: ReferenceParams = cfg.reference
        self.scan_params: PanScanParams = pan_scan_params(cfg.pan_scan)
        self.modes = ModeMachine(cfg.modes)
        self.commands = CommandQueue()
        self.timesync = TimeSync()
        self.vehicle = _Vehicle()
        self.stats = Stats()
        self.op = OperatorInput()
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
        self._imu_wait_misses = 0
        self._next_feedback_s = 0.0
        self._next_feedback_wall_s = 0.0
        self._next_heartbeat_wall_s = 0.0
        self._next_timesync_wall_s = 0.0
        self._next_fallback_wall_s = 0.0
        self._next_progress_wall_s = clock() + PROGRESS_EVERY_S
        self._progress_frames = 0
        self._start_wall_s = clock()
        self._R_qc = np.eye(3)

    # ------------------------------------------------------------------ sending
    def _pack(self, msg: Any) -> bytes:
        return bytes(msg.pack(self._codec))

    def _log_packet(self, buf: bytes) -> None:
        if self.tlog is not None:
            self.tlog.write(buf, self.wall())

    def _send(self, link: MavLink, msg: Any) -> None:
        buf = self._pack(msg)
        try:
            link.write(buf)
        except OSError as exc:  # a link hiccup must never stop the loop
            log.debug("send %s failed: %s", msg.get_type(), exc)
        self._log_packet(buf)

    def send_autopilot(self, msg: Any) -> None:
        self._send(self.autopilot, msg)

    def send_gcs(self, msg: Any) -> None:
        self._send(self.gcs, msg)

    def _status_text(self, st: StatusText) -> None:
        level = logging.WARNING if st.severity <= 4 else logging.INFO
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
            self._process_frame(frame)
        self._periodic()

    def _drain_autopilot(self) -> None:
        for _ in range(MAX_ROUTED_PER_STEP):
            msg = self.autopilot.recv_msg()
            if msg is None:
                return
            if msg.get_type() != "BAD_DATA":
                self._on_autopilot(msg)

    def _drain_gcs(self) -> None:
        for _ in range(MAX_ROUTED_PER_STEP):
            msg = self.gcs.recv_msg()
            if msg is None:
                return
            if msg.get_type() != "BAD_DATA":
                self._on_gcs(msg)

    def _wait_for_imu(self, stamp_s: float) -> None:
        """Let the IMU stream catch up with the frame (bounded), if it is flowing at all.

        If the wait keeps timing out the IMU structurally lags the frames on this setup (a producer that
        emits them later): stop waiting rather than add latency to every frame (the attitude filter
        extrapolates the last few ms).
        """
        t = self.cfg.timing
        if self._imu_stamp_s is None or stamp_s - self._imu_stamp_s > 0.2 or self._imu_wait_misses >= 30:
            return
        deadline = self.clock() + t.imu_wait_s
        while self._imu_stamp_s < stamp_s - t.imu_slack_s:
            if self.clock() >= deadline:
                self._imu_wait_misses += 1
                if self._imu_wait_misses == 30:
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
        to_me = getattr(msg, "target_component", None) == self.compid
        if kind == "HIGHRES_IMU":
            self._on_imu(msg)
        elif kind == "HEARTBEAT":
            if msg.autopilot != mavlink.MAV_AUTOPILOT_INVALID and msg.type != mavlink.MAV_TYPE_GCS:
                self._on_autopilot_heartbeat(msg)
        elif kind == "EXTENDED_SYS_STATE":
            self.vehicle.landed_state = msg.landed_state
        elif kind == "COMMAND_ACK" and (to_me or getattr(msg, "target_component", 0) == 0):
            done, failed = self.commands.on_ack(msg.command, msg.result, self.clock())
            if done is not None:
                log.info("autopilot accepted %s", done.name)
            for req, why in failed:
                self._actions(self.modes.on_request_failed(req, self.clock(), why))
        elif kind == "TIMESYNC":
            self._on_timesync(msg)
        if not to_me:
            try:
                self.gcs.write(msg.get_msgbuf())
                self.stats.routed_to_gcs += 1
            except OSError as exc:
                log.debug("routing to GCS failed: %s", exc)

    def _on_autopilot_heartbeat(self, msg: Any) -> None:
        src = msg.get_srcSystem()
        if src != self.sysid:
            log.info("autopilot is system %d: using it as our system id", src)
            self.sysid = src
            self._codec.srcSystem = src
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
        if not all(map(math.isfinite, values)):   # scalar checks: numpy reductions cost more at 500 Hz
            return
        gyro = np.array(values[:3])
        accel = np.array(values[3:])
        self._imu_stamp_s, self._imu_wall_s, self._gyro_q = stamp, self.clock(), gyro
        if self._pipeline is not None:
            try:
                self._pipeline.on_imu(stamp, gyro, accel)
            except (ValueError, ArithmeticError, QuadlinkError) as exc:
                self.stats.pipeline_errors += 1
                log.warning("perception rejected an IMU sample: %s", exc)
        period = 1.0 / self.cfg.timing.feedback_rate_hz
        if stamp >= self._next_feedback_s or stamp < self._next_feedback_s - 1.0:  # (a restart rewinds time)
            self._send_feedback(stamp)
            self._next_feedback_s = (math.floor(stamp / period) + 1) * period

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
        if kind == "MANUAL_CONTROL":
            if msg.target in (0, self.sysid):
                self._on_manual_control(msg)
            return
        tsys = getattr(msg, "target_system", None)
        tcomp = getattr(msg, "target_component", None)
        if tsys not in (None, 0, self.sysid):
            return  # another system: nothing behind this companion has it
        if tcomp == self.compid:
            self._handle_local(msg)
            return
        if tcomp in (None, 0) and kind in ("PARAM_REQUEST_LIST", "PARAM_REQUEST_READ", "PARAM_SET"):
            self._handle_local(msg)  # broadcast: answer for this component too
        try:
            self.autopilot.write(msg.get_msgbuf())
            self.stats.routed_to_autopilot += 1
        except OSError as exc:
            log.debug("routing to autopilot failed: %s", exc)

    def _on_manual_control(self, msg: Any) -> None:
        self.op = operator_from_manual_control(msg.x, msg.y, msg.z, self.ref_params.deadband)
        self.modes.on_manual_control(self.clock())
        self.stats.manual_controls += 1

    def _handle_local(self, msg: Any) -> None:
        kind = msg.get_type()
        if kind == "COMMAND_LONG":
            self._on_gcs_command(msg)
        elif kind == "PARAM_REQUEST_LIST":
            for i in range(len(PARAM_NAMES)):
                self._send_param(i)
        elif kind == "PARAM_REQUEST_READ":
            name = msg.param_id.rstrip("\x00") if isinstance(msg.param_id, str) else ""
            index = PARAM_NAMES.index(name) if name in PARAM_NAMES else msg.param_index
            if 0 <= index < len(PARAM_NAMES):
                self._send_param(index)
        elif kind == "PARAM_SET":
            name = msg.param_id.rstrip("\x00") if isinstance(msg.param_id, str) else ""
            if name in PARAM_NAMES and self.set_param(name, msg.param_value):
                self._send_param(PARAM_NAMES.index(name))

    def _on_gcs_command(self, msg: Any) -> None:
        cmd = msg.command
        result = mavlink.MAV_RESULT_UNSUPPORTED
        name = {mavlink.MAV_CMD_NAV_TAKEOFF: "takeoff", mavlink.MAV_CMD_NAV_LAND: "land"}.get(cmd)
        if cmd == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
            name = "arm" if msg.param1 >= 0.5 else "disarm"
        camera_fresh = self.last_frame_wall_s is not None and \
            self.clock() - self.last_frame_wall_s <= self.cfg.timing.camera_timeout_s
        if name == "takeoff" and not camera_fresh:
            self._status_text(StatusText(4, "companion: takeoff refused: no camera frames (perception not running)"))
            result = mavlink.MAV_RESULT_TEMPORARILY_REJECTED
        elif name is not None:
            ok, actions = self.modes.request(name, self.clock(), self.vehicle.status())
            self._actions(actions)
            result = mavlink.MAV_RESULT_ACCEPTED if ok else mavlink.MAV_RESULT_TEMPORARILY_REJECTED
        elif cmd == mavlink.MAV_CMD_DO_SET_PARAMETER:
            index = int(round(msg.param1))
            ok = 0 <= index < len(PARAM_NAMES) and self.set_param(PARAM_NAMES[index], msg.param2)
            result = mavlink.MAV_RESULT_ACCEPTED if ok else mavlink.MAV_RESULT_DENIED
            if ok:
                self._send_param(index)
        self.send_gcs(mavlink.MAVLink_command_ack_message(cmd, result, 0, 0, msg.get_srcSystem(),
                                                          msg.get_srcComponent()))

    def param_values(self) -> dict[str, float]:
        s, r = self.scan_params, self.ref_params
        return {"PANSCAN_EN": 1.0 if s.enabled else 0.0, "PANSCAN_AMP": s.amplitude_rad_s,
                "PANSCAN_OMEGA": s.omega_rad_s,
                "CMP_K_V": r.k_v_m_s, "CMP_K_PSI": r.k_psi_rad_s, "CMP_SAFE_DIST": r.safe_distance_m}

    def set_param(self, name: str, value: float) -> bool:
        if not math.isfinite(value):
            return False
        old = self.param_values()[name]
        if name == "PANSCAN_EN":
            self.scan_params = dataclasses.replace(self.scan_params, enabled=value >= 0.5)
        elif name in ("PANSCAN_AMP", "PANSCAN_OMEGA"):
            if value < 0 or (name == "PANSCAN_OMEGA" and value == 0):
                return False
            amp = value if name == "PANSCAN_AMP" else self.scan_params.amplitude_rad_s
            omega = value if name == "PANSCAN_OMEGA" else self.scan_params.omega_rad_s
            cfg = dataclasses.replace(self.cfg.pan_scan, enabled=self.scan_params.enabled, amplitude_rad_s=amp,
                                      omega_rad_s=omega)
            self.scan_params = pan_scan_params(cfg)  # the response depends on omega
        elif name in ("CMP_K_V", "CMP_K_PSI", "CMP_SAFE_DIST"):
            if value < 0:
                return False
            r = self.ref_params
            if name == "CMP_K_V":
                self.ref_params = dataclasses.replace(r, k_v_m_s=float(value))
            elif name == "CMP_K_PSI":
                self.ref_params = dataclasses.replace(r, k_psi_rad_s=float(value))
            else:
                self.ref_params = dataclasses.replace(r, safe_distance_m=float(value))
        self._status_text(StatusText(6, f"companion: {name} {old:g} -> {self.param_values()[name]:g}"))
        return True

    def _send_param(self, index: int) -> None:
        name = PARAM_NAMES[index]
        self.send_gcs(mavlink.MAVLink_param_value_message(name.encode(), float(self.param_values()[name]),
                                                          mavlink.MAV_PARAM_TYPE_REAL32, len(PARAM_NAMES), index))

    # ------------------------------------------------------------------ the pipeline at camera rate
    def _scan_state(self, stamp_s: float) -> PanScanState:
        if self.modes.mode != Mode.TELEOP or self._scan_t0_s is None:
            return PanScanState(0.0, 0.0, False)
        return pan_scan(self.scan_params, stamp_s - self._scan_t0_s)

    def _process_frame(self, frame: RgbdFrame) -> None:
        t_in = self.clock()
        self.stats.frames += 1
        self._R_qc = np.asarray(frame.R_qc, dtype=float)
        if self._pipeline is None:
            self._pipeline = self._pipeline_factory(frame)
            log.info("perception started on %dx%d frames", frame.intrinsics.width, frame.intrinsics.height)
        try:
            out = self._pipeline.on_frame(frame)
        except (ValueError, ArithmeticError, np.linalg.LinAlgError, QuadlinkError) as exc:
            self.stats.pipeline_errors += 1
            log.warning("perception failed on frame %d: %s", frame.seq, exc)
            out = None
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
        points = None if out is None else out.obstacle_points_h_m
        self._nearest = nearest_obstacle(points, self.ref_params)   # for TELEOP_FEEDBACK at 50 Hz
        sectors, _, offset_deg = msgs.sector_arrays(None if out is None else out.sectors)
        block = out is None or not self.cfg.obstacles.allow_unknown_when_fresh
        ref = reference_velocity(self.op, self._R_qc, self._scan_state(stamp), points, self.ref_params,
                                 sectors_m=sectors, block_unknown=block,
                                 operator_enabled=self.modes.operator_enabled,
                                 sector_offset_rad=math.radians(offset_deg), height_m=self._height_m(out))
        self.last_ref = ref
        self._send_setpoint(stamp, ref)
        self.stats.latencies_s.append(self.clock() - t_in)
        if out is not None:
            self._send_odometry(stamp, out)
        self.camera.ack(frame.seq)
        if out is not None:
            self._send_gcs_telemetry(stamp, out)
            self._publish_image(frame, out, ref)
        if self.frame_recorder is not None:
            self._record_frame(frame)

    def _record_frame(self, frame: RgbdFrame) -> None:
        try:
            self.frame_recorder.write(frame)  # type: ignore[union-attr]
        except OSError as exc:  # a full disk stops the recording, never the flight loop
            log.error("frame recording stopped: %s", exc)
            self.frame_recorder = None

    @staticmethod
    def _height_m(out: Any) -> float | None:
        """Height above the take-off floor from the odometry (its world starts on the ground, NED)."""
        if out is None or not out.odometry_ok or out.position_m is None:
            return None
        z = float(np.asarray(out.position_m, dtype=float)[2])
        return -z if math.isfinite(z) else None

    def _stamp_to_autopilot(self, stamp_s: float) -> float:
        if self.cfg.timing.camera_stamps == "local":
            remote = self.timesync.to_remote_s(stamp_s)
            return stamp_s if remote is None else remote
        return stamp_s

    def _send_setpoint(self, stamp_s: float, ref: ReferenceOutput) -> None:
        # Outside TELEOP/HOLD the autopilot flies its own mode; the stream (zero) only keeps offboard ready.
        v, yaw_rate = (ref.v_ref_h_m_s, ref.yaw_rate_ref_rad_s) if self.modes.in_control else (np.zeros(3), 0.0)
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

    def _send_feedback(self, stamp_s: float) -> None:
        out, ref = self.last_output, self.last_ref
        zero = np.zeros(3)
        v_est = zero if out is None else np.asarray(out.v_h_m_s, dtype=float)
        roll = 0.0 if out is None else out.roll_rad
        pitch = 0.0 if out is None else out.pitch_rad
        scan = self._scan_state(stamp_s)
        yaw_cmd = (0.0 if ref is None else ref.operator_yaw_rate_rad_s) + scan.yaw_rate_rad_s  # eq. (8) held
        alpha = camera_yaw_rad(self._R_qc) + scan.yaw_offset_rad  # eq. (6) at this instant
        nearest = self._nearest
        obst, dist = nearest if nearest is not None else (zero, -1.0)
        fresh = self.last_frame_wall_s is not None and \
            self.clock() - self.last_frame_wall_s <= self.cfg.timing.camera_timeout_s
        flags = msgs.feedback_flags(scan.enabled, self.odometry_ok, self.modes.gcs_ok, fresh)
        v_cmd = zero if ref is None else ref.v_ref_h_m_s
        v_rep = zero if ref is None else ref.v_repulsion_h_m_s
        self.send_gcs(msgs.teleop_feedback_message(
            stamp_s, v_est, v_cmd, v_rep, alpha, scan.yaw_rate_rad_s, yaw_cmd,
            msgs.euler_yaw_rate_rad_s(self._gyro_q, roll, pitch), obst, dist, int(self.modes.mode), flags))
        self.stats.feedback += 1

    def _publish_image(self, frame: RgbdFrame, out: Any, ref: ReferenceOutput) -> None:
        if self.image_server is None or self.image_server.client_count == 0:
            return
        pts = np.asarray(out.obstacle_points_c_m if out.obstacle_points_c_m is not None else np.zeros((0, 3)),
                         dtype=float).reshape(-1, 3)[:MAX_IMAGE_POINTS]
        scan = self._scan_state(frame.stamp_s)
        meta = {
            "stamp_s": float(frame.stamp_s), "roll_rad": float(out.roll_rad), "pitch_rad": float(out.pitch_rad),
            "yaw_rad": float(out.yaw_rad),
            "gyro_yaw_rate_rad_s": msgs.euler_yaw_rate_rad_s(self._gyro_q, out.roll_rad, out.pitch_rad),
            "obstacle_points_c_m": np.round(pts, 3).tolist(),
            "v_cmd_h_m_s": [float(x) for x in ref.v_ref_h_m_s],
            "v_est_h_m_s": [float(x) for x in np.asarray(out.v_h_m_s, dtype=float)],
            "pan_scan": {"enabled": scan.enabled, "yaw_rate_rad_s": scan.yaw_rate_rad_s,
                         "yaw_offset_rad": scan.yaw_offset_rad, "alpha_rad": ref.alpha_rad,
                         "amplitude_rad_s": self.scan_params.amplitude_rad_s,
                         "omega_rad_s": self.scan_params.omega_rad_s},
            "mode": self.modes.mode.name.lower(),
        }
        image = RgbdFrame(frame.seq, frame.stamp_s, frame.rgb, None, frame.intrinsics, frame.R_qc, frame.p_qc_m, meta)
        try:
            self.image_server.publish(image, rgb_jpeg=True)
        except (OSError, QuadlinkError) as exc:
            log.warning("operator image stream: %s", exc)

    # ------------------------------------------------------------------ periodic tasks
    def _periodic(self) -> None:
        now = self.clock()
        t = self.cfg.timing
        camera_silent = self.last_frame_wall_s is None or now - self.last_frame_wall_s > t.camera_timeout_s
        if camera_silent:
            self.odometry_ok = False
        self._actions(self.modes.update(now, self.vehicle.status(), self.odometry_ok))
        send, failed = self.commands.poll(now)
        for req, why in failed:
            self._actions(self.modes.on_request_failed(req, now, why))
        for command, confirmation in send:
            self.send_autopilot(mavlink.MAVLink_command_long_message(
                self.sysid, self.ap_compid, command.command, confirmation, *command.params))
        if now >= self._next_heartbeat_wall_s:
            self._next_heartbeat_wall_s = now + 1.0 / t.heartbeat_rate_hz
            hb = mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID,
                                                   0, int(self.modes.mode), mavlink.MAV_STATE_ACTIVE, 3)
            self.send_autopilot(hb)
            self.send_gcs(hb)
        if now >= self._next_timesync_wall_s:
            self._next_timesync_wall_s = now + t.timesync_period_s
            self.send_autopilot(mavlink.MAVLink_timesync_message(0, int(now * 1e9)))
        if camera_silent and now >= self._next_fallback_wall_s:
            # No camera: obstacle data stale -> no motion toward unknown (= all) sectors, repulsion from the
            # last map kept (conservative), operator zeroed by HOLD; keeps the autopilot's stream alive.
            self._next_fallback_wall_s = now + 1.0 / t.fallback_setpoint_rate_hz
            points = None if self.last_output is None else self.last_output.obstacle_points_h_m
            stamp = self._fallback_stamp(now)
            ref = reference_velocity(self.op, self._R_qc, PanScanState(0.0, 0.0, False), points, self.ref_params,
                                     sectors_m=None, block_unknown=True, operator_enabled=self.modes.operator_enabled,
                                     height_m=self._height_m(self.last_output))
            self.last_ref = ref
            self._send_setpoint(stamp, ref)
        imu_silent = self._imu_wall_s is None or now - self._imu_wall_s > 0.1
        if imu_silent and now >= self._next_feedback_wall_s:
            self._next_feedback_wall_s = now + 1.0 / t.feedback_rate_hz
            self._send_feedback(self._fallback_stamp(now))

        if now >= self._next_progress_wall_s:
            self._next_progress_wall_s = now + PROGRESS_EVERY_S
            self._log_progress()

    def _log_progress(self) -> None:
        s = self.stats
        fps = (s.frames - self._progress_frames) / PROGRESS_EVERY_S
        self._progress_frames = s.frames
        p50, per50 = _recent_median_ms(s.latencies_s), _recent_median_ms(s.perception_s)
        log.info("mode %s  camera %.1f fps  frame->setpoint p50 %s (perception %s)  odometry %s  gcs link %s  "
                 "manual %d  routed %d to GCS / %d to autopilot", self.modes.mode.name, fps, p50, per50,
                 "ok" if self.odometry_ok else "FAIL", "ok" if self.modes.gcs_ok else "lost", s.manual_controls,
                 s.routed_to_gcs, s.routed_to_autopilot)
        if len(s.latencies_s) > 20000:
            del s.latencies_s[:-2000]
            del s.perception_s[:-2000]

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


"""The ground station process: wires the device, the force law, the command mapping, the vehicle
link and the operator view to clocks and sockets.

Concurrency model: a few threads sharing immutable snapshots (replaced atomically under one lock),
a queue for button presses, one stop event; every wait has a timeout.

* force loop, 1 kHz (``device.force_rate_hz``): poll device -> eq. (15) -> set force. Precise sleep
  (``time.sleep`` to ``spin_s`` before the deadline, then a short spin); the interpreter's thread
  switch interval is lowered to 0.5 ms while it runs so the other threads cannot hold it off.
* network loop, 50 Hz (``mapping.rate_hz``): MAVLink in (telemetry, TELEOP_FEEDBACK, acks), MANUAL_CONTROL
  and HEARTBEAT out, buttons -> commands, status, CSV log.
* view loop, camera rate: image stream -> pan-scan compensation -> rendered view -> web page / video.
* HTTP server thread (view/server.py).
"""

from __future__ import annotations

import csv
import logging
import math
import queue
import re
import sys
import threading
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any, TextIO

import cv2
import numpy as np
from numpy.typing import NDArray

from quadlink.camera import CameraStreamClient
from quadlink.errors import LinkError, QuadlinkError
from quadlink.mavlink import mavlink
from quadlink.mavlink.connection import open_mavlink
from teleop.commands import CommandResult, CommandTracker, OutgoingCommand
from teleop.config import TeleopConfig
from teleop.devices.base import HapticDevice
from teleop.force import VehicleMotion, link_ok
from teleop.force_loop import DeviceSpec, ForceProcess, ForceSnapshot, MotionInput, PeriodRecorder, run_force_loop
from teleop.mapping import ManualControl, map_device_to_command
from teleop.telemetry import (
    FLAG_GCS_LINK_OK,
    FLAG_ODOMETRY_OK,
    MODE_NAMES,
    Telemetry,
    apply_message,
    min_obstacle_m,
)
from teleop.view.panscan import PanScanEstimator
from teleop.view.render import OperatorViewRenderer, Overlay
from teleop.view.server import ViewHub, ViewServer

log = logging.getLogger(__name__)

CSV_FIELDS = ["t_s", "qx_m", "qy_m", "qz_m", "qdx_m_s", "qdy_m_s", "qdz_m_s", "fop_x_n", "fop_y_n", "fop_z_n",
              "tau_x_n", "tau_y_n", "tau_z_n", "qtx_m", "qty_m", "qtz_m", "link_gain", "cmd_x", "cmd_z", "cmd_r",
              "vx_h", "vy_h", "vz_h", "vx_cmd", "vy_cmd", "vz_cmd", "vx_rep", "vy_rep", "vz_rep", "alpha_rad",
              "yaw_rate", "pan_scan_rate_used", "obstacle_m", "mode", "flags", "armed"]


def warnings_for(tel: Telemetry, link_is_ok: bool, t_s: float, cfg: TeleopConfig) -> list[str]:
    """Warnings shown on the page and in the terminal (pure)."""
    out = []
    if not link_is_ok:
        out.append("VEHICLE LINK LOST" if tel.feedback is not None else "no vehicle link yet")
    fb = tel.feedback
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
                 clock: Callable[[], float] = time.perf_counter, exit_at_script_end: bool = True) -> None:
        self.cfg = cfg
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
        self.force_periods = PeriodRecorder()
        self.commands = CommandTracker(cfg.commands)
        self.hub = ViewHub()
        self.server: ViewServer | None = None
        self._conn: Any = None
        self._threads: list[threading.Thread] = []
        self._switch_interval = sys.getswitchinterval()
        self.manual_control_sent = 0
        self.view_frames = 0
        self.error: BaseException | None = None

    # ---- lifecycle -------------------------------------------------------------------------
    def start(self) -> None:
        if isinstance(self.device, DeviceSpec):   # before any thread: the force loop in its own process
            self._force_proc = ForceProcess(self.device, self.cfg)
        self._conn = open_mavlink(self.vehicle_url, self.cfg.network.source_system, self.cfg.network.source_component)
        log.info("vehicle link %s (MANUAL_CONTROL at %.0f Hz to sysid %d)", self.vehicle_url, self.cfg.mapping.rate_hz,
                 self.cfg.mapping.target_system)
        if self.http_port is not None:
            period_ms = max(int(1000 / 30), 20)
            self.server = ViewServer(self.hub, self.cfg.network.http_host, self.http_port, period_ms)
        if self._force_proc is None:
            sys.setswitchinterval(0.0005)   # the force thread waits at most this long for the GIL
            self._spawn("force-loop", self._force_thread)
        self._spawn("network-loop", self._network_loop)
        if self.image_stream_url is not None or self.server is not None or self.record_path:
            self._spawn("view-loop", self._view_loop)

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
        """Block until stopped (Ctrl-C, quit button, script end, duration), printing status lines."""
        t0 = self.clock()
        next_status = t0 + status_period_s
        shown_warnings: set[str] = set()
        while not self.stop_event.wait(0.1):
            t = self.clock()
            if duration_s is not None and t - t0 >= duration_s:
                break
            if self._force_proc is not None and not self._force_proc.alive:
                raise QuadlinkError("the force process died (see its log above)")
            if self.exit_at_script_end and self.device_finished:
                log.info("script finished")
                break
            with self._lock:   # STATUSTEXTs are logged when they arrive; the others when they appear
                warnings = {_warning_kind(w): w for w in self._warnings if not w.startswith("vehicle: ")}
            for kind in set(warnings) - shown_warnings:
                log.warning("%s", warnings[kind])
            shown_warnings = set(warnings)
            if t >= next_status:
                next_status = t + status_period_s
                log.info("%s", self.status_line())
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
        if self._conn is not None:
            self._conn.close()

    # ---- snapshots -------------------------------------------------------------------------
    def vehicle_time_s(self) -> float | None:
        """The vehicle's clock (TELEOP_FEEDBACK time_usec, simulated time in the SITL), None before any."""
        fb = self.telemetry.feedback
        return None if fb is None else fb.time_usec * 1e-6

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
        }

    def status_line(self) -> str:
        s = self.status()
        bat = f"{s['battery_v']:.1f} V" if s["battery_v"] is not None else "- V"
        obst = f"{s['min_obstacle_m']:.2f} m" if s["min_obstacle_m"] is not None else "none"
        f = s["force_n"]
        return (f"link {s['link']} | mode {s['mode']} | {'armed' if s['armed'] else 'disarmed'} | bat {bat} | "
                f"obstacle {obst} | {s['command']} | q [{s['q_m'][0]:+.3f} {s['q_m'][1]:+.3f} {s['q_m'][2]:+.3f}] m"
                f" | force [{f[0]:+.2f} {f[1]:+.2f} {f[2]:+.2f}] N")

    # ---- force loop (1 kHz): in-process variant ------------------------------------------
    def _force_thread(self) -> None:
        assert isinstance(self.device, HapticDevice)
        run_force_loop(self.device, self.cfg, _ThreadIO(self), self.clock)

    # ---- network loop (50 Hz) --------------------------------------------------------------
    def _network_loop(self) -> None:
        period = 1.0 / self.cfg.mapping.rate_hz
        conn = self._conn
        vcfg = self.cfg.view
        estimator = PanScanEstimator(vcfg.initial_frequency_hz, vcfg.min_frequency_hz, vcfg.max_frequency_hz,
                                     vcfg.bandpass_q, vcfg.bias_periods,
                                     operator_yaw_time_constant_s=vcfg.operator_yaw_time_constant_s)
        ap = (self.cfg.commands.autopilot_system, self.cfg.commands.autopilot_component)
        csv_file: TextIO | None = None
        writer = None
        if self.log_csv:
            csv_file = open(self.log_csv, "w", newline="", encoding="utf-8")  # noqa: SIM115 - closed below
            writer = csv.writer(csv_file)
            writer.writerow(CSV_FIELDS)
            log.info("logging force/q/command to %s", self.log_csv)
        t0 = self.clock()
        next_t = t0
        next_heartbeat = t0
        try:
            while not self.stop_event.is_set():
                t = self.clock()
                tel = self.telemetry
                for _ in range(1000):
                    try:
                        msg = conn.recv_match(blocking=False)
                    except (OSError, ValueError) as exc:   # a bad datagram or a transient socket error
                        log.debug("MAVLink receive: %s", exc)
                        break
                    if msg is None:
                        break
                    mtype = msg.get_type()
                    if mtype == "BAD_DATA":
                        continue
                    tel = apply_message(tel, msg, t, ap, self.cfg.commands.companion_component)
                    if mtype == "TELEOP_FEEDBACK" and tel.feedback is not None:
                        new_fb = tel.feedback
                        est = estimator.update(new_fb.gyro_yaw_rate_rad_s, new_fb.time_usec * 1e-6, new_fb.pan_scan_on,
                                               new_fb.yaw_rate_cmd_rad_s - new_fb.pan_scan_yaw_rate_rad_s)
                        self._pan_scan_hz = est.frequency_hz
                        ps = (est.yaw_rate_rad_s if self.cfg.force.pan_scan_source == "estimated"
                              else new_fb.pan_scan_yaw_rate_rad_s if new_fb.pan_scan_on else 0.0)
                        self._motion = MotionInput(t, VehicleMotion(new_fb.v_h_m_s, new_fb.alpha_rad,
                                                                    new_fb.gyro_yaw_rate_rad_s, ps),
                                                   new_fb.mode in self.cfg.force.cue_modes)
                        if self._force_proc is not None:
                            self._force_proc.set_motion(self._motion, new_fb.time_usec * 1e-6)
                    elif mtype == "COMMAND_ACK":
                        self._ack(self.commands.on_command_ack(msg.command, msg.result, t))
                    elif mtype == "PARAM_VALUE":
                        pid = msg.param_id if isinstance(msg.param_id, str) else msg.param_id.decode(errors="ignore")
                        self._ack(self.commands.on_param_value(pid.rstrip("\x00"), msg.param_value, t))
                    elif mtype == "STATUSTEXT" and msg.severity <= mavlink.MAV_SEVERITY_WARNING:
                        log.warning("vehicle says: %s", tel.last_statustext)
                # buttons -> commands
                presses = self._force_proc.buttons() if self._force_proc is not None else []
                while True:
                    try:
                        presses.append(self._buttons.get_nowait())
                    except queue.Empty:
                        break
                for button in presses:
                    if button == "quit":
                        log.info("quit pressed")
                        self.stop_event.set()
                        continue
                    out = self.commands.build(button, tel.feedback.pan_scan_on if tel.feedback else False)
                    if out is not None:
                        log.info("button %s -> %s", button, out.name)
                        self._send_command(conn, self.commands.submit(out, t))
                resend, failed = self.commands.poll(t)
                for out in resend:
                    self._send_command(conn, out)
                for result in failed:
                    self._ack(result)
                # operator command, eqs. (2)-(3)
                force = self.force
                q = force.device.q_m if force else np.zeros(3)
                cmd = map_device_to_command(q, self.cfg.mapping, self.cfg.device)
                conn.mav.manual_control_send(self.cfg.mapping.target_system, cmd.x, cmd.y, cmd.z, cmd.r, cmd.buttons)
                self.manual_control_sent += 1
                if t >= next_heartbeat:
                    next_heartbeat = t + 1.0
                    conn.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0,
                                            mavlink.MAV_STATE_ACTIVE)
                ok = link_ok(tel.feedback.t_recv_s if tel.feedback else None, t, self.cfg.force.link_timeout_s)
                warnings = warnings_for(tel, ok, t, self.cfg)
                with self._lock:
                    self._telemetry, self._command, self._warnings = tel, cmd, warnings
                self.hub.set_status(self.status())
                if writer is not None:
                    writer.writerow(self._csv_row(t - t0, force, cmd, tel))
                next_t += period
                if self.clock() - next_t > 10 * period:
                    next_t = self.clock()
                self.stop_event.wait(max(next_t - self.clock(), 0.0))
        finally:
            if csv_file is not None:
                csv_file.close()

    def _send_command(self, conn: Any, out: OutgoingCommand) -> None:
        if out.kind == "command_long":
            conn.mav.command_long_send(out.target_system, out.target_component, out.command, out.confirmation,
                                       *out.params)
        else:
            conn.mav.param_set_send(out.target_system, out.target_component, out.param_id.encode(),
                                    out.param_value, mavlink.MAV_PARAM_TYPE_REAL32)

    def _ack(self, result: CommandResult | None) -> None:
        if result is None:
            return
        (log.info if result.accepted else log.warning)("command %s", result.text)
        with self._lock:
            self._acks.append(result.text)

    def _csv_row(self, t_s: float, force: ForceSnapshot | None, cmd: ManualControl, tel: Telemetry) -> list[Any]:
        z3 = (0.0, 0.0, 0.0)
        dev = force.device if force else None
        q = dev.q_m if dev is not None else z3
        qd = dev.qdot_m_s if dev is not None else z3
        fop = dev.operator_force_n if dev is not None and dev.operator_force_n is not None else z3
        tau = force.tau_d_n if force else z3
        qt = force.q_tilde_m if force and force.q_tilde_m is not None else (math.nan,) * 3
        fb = tel.feedback
        motion = self._motion
        row: list[Any] = [f"{t_s:.4f}", *(f"{v:.5f}" for v in q), *(f"{v:.5f}" for v in qd),
                          *(f"{v:.4f}" for v in fop), *(f"{v:.4f}" for v in tau), *(f"{v:.5f}" for v in qt),
                          f"{force.link_gain if force else 0.0:.3f}", cmd.x, cmd.z, cmd.r]
        if fb is not None:
            row += [*(f"{v:.4f}" for v in fb.v_h_m_s), *(f"{v:.4f}" for v in fb.v_cmd_h_m_s),
                    *(f"{v:.4f}" for v in fb.v_rep_h_m_s), f"{fb.alpha_rad:.4f}", f"{fb.gyro_yaw_rate_rad_s:.4f}",
                    f"{motion.motion.pan_scan_yaw_rate_rad_s if motion else 0.0:.4f}",
                    "" if fb.obstacle_distance_m is None else f"{fb.obstacle_distance_m:.3f}", fb.mode, fb.flags]
        else:
            row += [""] * 15
        row.append(int(tel.armed))
        return row

    # ---- view loop (camera rate) -----------------------------------------------------------
    def _view_loop(self) -> None:
        vcfg = self.cfg.view
        renderer = OperatorViewRenderer(vcfg.canvas_width_px, vcfg.canvas_height_px, vcfg.background_decay_s)
        estimator = PanScanEstimator(vcfg.initial_frequency_hz, vcfg.min_frequency_hz, vcfg.max_frequency_hz,
                                     vcfg.bandpass_q, vcfg.bias_periods,
                                     operator_yaw_time_constant_s=vcfg.operator_yaw_time_constant_s)
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
                        img = renderer.render(None, None, np.eye(3), 0.0, 0.0, 0.0, t,
                                              self._overlay({}, ("waiting for the image stream",)))
                        self._publish(img)
                        last_render = t
                    continue
                meta = frame.meta or {}
                gyro = _meta_float(meta, "gyro_yaw_rate_rad_s")
                est = estimator.update(gyro, frame.stamp_s, bool(meta.get("pan_scan_on", True)),
                                       self._operator_yaw_rate_cmd())
                img = renderer.render(frame.rgb, frame.intrinsics, frame.R_qc, _meta_float(meta, "roll_rad"),
                                      _meta_float(meta, "pitch_rad"), est.yaw_rad, frame.stamp_s,
                                      self._overlay(meta, ()))
                self._publish(img)
                last_render = t
                self.view_frames += 1
                if self.record_path:
                    if video is None:
                        video = _open_video(self.record_path, img.shape[1], img.shape[0])
                    video.write(img)
                client.ack(frame.seq)  # type: ignore[union-attr]
        finally:
            if client is not None:
                client.close()
            if video is not None:
                video.release()
                log.info("recorded operator view to %s", self.record_path)

    def _overlay(self, meta: dict[str, Any], extra_warnings: tuple[str, ...]) -> Overlay:
        s = self.status()
        tel = self.telemetry
        fb = tel.feedback
        v_cmd = _meta_vec(meta, "v_cmd_h") or (fb.v_cmd_h_m_s if fb else (0.0, 0.0, 0.0))
        v_est = _meta_vec(meta, "v_est_h") or (fb.v_h_m_s if fb else (0.0, 0.0, 0.0))
        points = meta.get("obstacle_points_c_m") or []
        pts = tuple(tuple(float(c) for c in p[:3]) for p in points
                    if isinstance(p, (list, tuple)) and len(p) >= 3 and all(isinstance(c, (int, float)) for c in p[:3]))
        bat = f"{s['battery_v']:.1f} V" if s["battery_v"] is not None else "- V"
        obst = f"{s['min_obstacle_m']:.2f} m" if s["min_obstacle_m"] is not None else "none"
        lines = (f"link {s['link']}  mode {s['mode']}  {'ARMED' if s['armed'] else 'disarmed'}",
                 f"battery {bat}  obstacle {obst}  pan-scan {'on' if s['pan_scan_on'] else 'off'}")
        return Overlay(v_cmd_h_m_s=v_cmd, v_est_h_m_s=v_est, force_d_n=tuple(s["force_n"]),  # type: ignore[arg-type]
                       force_limit_n=self.cfg.device.force_limit_n, obstacle_points_c_m=pts,  # type: ignore[arg-type]
                       obstacle_warning_m=self.cfg.view.obstacle_warning_m,
                       status_lines=lines, warnings=tuple(s["warnings"]) + extra_warnings)

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


def _meta_float(meta: dict[str, Any], key: str) -> float:
    value = meta.get(key, 0.0)
    return float(value) if isinstance(value, (int, float)) and math.isfinite(value) else 0.0


def _meta_vec(meta: dict[str, Any], key: str) -> tuple[float, float, float] | None:
    value = meta.get(key)
    if isinstance(value, (list, tuple)) and len(value) == 3 and all(isinstance(v, (int, float)) for v in value):
        return (float(value[0]), float(value[1]), float(value[2]))
    return None


def _open_video(path: str, width: int, height: int, fps: float = 30.0) -> cv2.VideoWriter:
    fourcc = cv2.VideoWriter.fourcc(*("MJPG" if Path(path).suffix.lower() == ".avi" else "mp4v"))
    writer = cv2.VideoWriter(path, fourcc, fps, (width, height))
    if not writer.isOpened():
        raise LinkError(f"--record {path}: OpenCV cannot open a video writer (use .avi or .mp4)")
    log.info("recording the operator view to %s", path)
    return writer

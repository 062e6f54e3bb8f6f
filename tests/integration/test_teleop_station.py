"""The ground station against a fake companion (pymavlink on an ephemeral UDP port + the companion's image
publisher fed by its real metadata producer):
MANUAL_CONTROL flows, commands are acknowledged, the force opposes a push when the feedback says the vehicle
is blocked, and a headless-Chromium screenshot of the operator page shows the view with obstacle points."""

from __future__ import annotations

import shutil
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from companion.frame_step import operator_image_meta
from companion.image_publisher import OperatorImagePublisher
from companion.modes import Mode
from companion.operator_input import OperatorInput
from companion.pan_scan import PanScanParams, pan_scan
from companion.reference import reference_velocity
from companion.reference_params import ReferenceParams
from quadlink.camera import CameraIntrinsics, RgbdFrame
from quadlink.mavlink import mavlink
from quadlink.mavlink.connection import open_mavlink
from quadlink.vehicle import load_vehicle
from teleop.config import TeleopConfig
from teleop.devices.script import ScriptConfig, ScriptStepConfig, build_script
from teleop.devices.virtual import ScriptedOperator, VirtualDevice
from teleop.mapping import ManualControl, command_to_velocity, mapping_gains
from teleop.station import Station

CHROMIUM = shutil.which("chromium") or ("/usr/bin/chromium" if Path("/usr/bin/chromium").exists() else None)
PUSH_N = 2.0


class FakeCompanion:
    """The companion's ground-station endpoint: consumes MANUAL_CONTROL, acks commands, sends feedback."""

    def __init__(self, cfg: TeleopConfig) -> None:
        self.cfg = cfg
        self.conn = open_mavlink("udpin:127.0.0.1:0", 1, 191)
        self.port = self.conn.port.getsockname()[1]
        self.autopilot = mavlink.MAVLink(self.conn, 1, 1)      # the autopilot's identity, same socket
        self.manual: list[tuple[int, int, int, int]] = []
        self.commands: list[int] = []
        self.params: dict[str, float] = {}
        self.follow = False          # False: the vehicle is blocked (v = 0); True: it flies the command
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        t0 = time.monotonic()
        next_hb = 0.0
        while not self.stop.is_set():
            while (msg := self.conn.recv_match(blocking=False)) is not None:
                mtype = msg.get_type()
                if mtype == "MANUAL_CONTROL":
                    self.manual.append((msg.x, msg.y, msg.z, msg.r))
                elif mtype == "COMMAND_LONG":
                    self.commands.append(msg.command)
                    self.autopilot.command_ack_send(msg.command, mavlink.MAV_RESULT_ACCEPTED)
                elif mtype == "PARAM_SET":
                    pid = msg.param_id if isinstance(msg.param_id, str) else msg.param_id.decode()
                    self.params[pid] = msg.param_value
                    self.conn.mav.param_value_send(pid.encode(), msg.param_value, msg.param_type, 1, 0)
            t = time.monotonic() - t0
            if self.manual:
                x, y, z, r = self.manual[-1]
                forward, v_down, yaw_rate = command_to_velocity(ManualControl(x, y, z, r), self.cfg.mapping)
                v = (forward, 0.0, v_down) if self.follow else (0.0, 0.0, 0.0)
                self.conn.mav.send(mavlink.MAVLink_teleop_feedback_message(
                    time_usec=int(t * 1e6), vx_h=v[0], vy_h=v[1], vz_h=v[2], vx_cmd=forward, vy_cmd=0.0,
                    vz_cmd=v_down, vx_rep=-0.3, vy_rep=0.0, vz_rep=0.0, alpha=0.0, pan_scan_yaw_rate=0.0,
                    yaw_rate_cmd=yaw_rate, gyro_yaw_rate=yaw_rate, obstacle_x=0.9, obstacle_y=0.0,
                    obstacle_z=0.0, obstacle_distance=0.9, mode=2,
                    flags=0b0110 | int(self.params.get("PANSCAN_EN", 0.0) == 1.0)))
                if t >= next_hb:
                    next_hb = t + 1.0
                    self.autopilot.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_GENERIC,
                                                  mavlink.MAV_MODE_FLAG_SAFETY_ARMED, 0, mavlink.MAV_STATE_ACTIVE)
                    self.autopilot.sys_status_send(0, 0, 0, 0, 11700, -1, 80, 0, 0, 0, 0, 0, 0)
            self.stop.wait(0.02)

    def close(self) -> None:
        self.stop.set()
        self.thread.join(timeout=2.0)
        self.conn.close()


class ImageStreamFromCompanion:
    """The companion's operator image stream: its real publisher, metadata from its real producer
    (``companion.frame_step.operator_image_meta``) for a perception output with obstacle points ahead."""

    def __init__(self) -> None:
        self.server = OperatorImagePublisher("127.0.0.1", 0)
        self.url = f"tcp://127.0.0.1:{self.server.port}"
        vehicle = load_vehicle()
        cam = vehicle.camera
        self.intrinsics = CameraIntrinsics.from_fov(cam.width_px, cam.height_px, cam.hfov_deg, cam.vfov_deg)
        self.R_qc = cam.R_qc_matrix
        yy, xx = np.mgrid[0:cam.height_px, 0:cam.width_px]
        board = (((yy // 20) + (xx // 20)) % 2).astype(np.uint8)
        self.rgb = np.stack([60 + 120 * board, 90 + 100 * board, 60 + 60 * board], axis=-1).astype(np.uint8)
        self.scan_params = PanScanParams(True, 0.6, 1.5)
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        seq = 0
        out = SimpleNamespace(roll_rad=0.0, pitch_rad=0.0, yaw_rad=0.0, v_h_m_s=np.array([0.1, 0.05, 0.0]))
        # the avoidance's points (H) of three obstacles ahead of the camera (level vehicle, mount at the origin)
        points_h = np.array([[0.0, 0.0, 1.2], [0.25, -0.1, 1.5], [-0.2, 0.15, 0.6]]) @ self.R_qc.T
        while not self.stop.is_set():
            t = seq / 30.0
            scan = pan_scan(self.scan_params, t)
            ref = reference_velocity(OperatorInput(0.7, 0.0, 0.0), self.R_qc, scan, None, ReferenceParams())
            gyro_q = np.array([0.0, 0.0, scan.yaw_rate_rad_s])
            meta = operator_image_meta(t, out, ref, scan, self.scan_params, gyro_q, Mode.TELEOP, points_h, self.R_qc,
                                       np.zeros(3))
            self.server.publish(RgbdFrame(seq, t, self.rgb, None, self.intrinsics, self.R_qc, np.zeros(3)), meta)
            seq += 1
            self.stop.wait(1 / 30.0)

    def close(self) -> None:
        self.stop.set()
        self.thread.join(timeout=2.0)
        self.server.close()


def wait_for(condition: Callable[[], bool], timeout_s: float = 15.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.05)
    return condition()


@pytest.fixture(scope="module")
def running() -> Iterator[tuple[Station, FakeCompanion, ImageStreamFromCompanion]]:
    cfg = TeleopConfig()
    companion = FakeCompanion(cfg)
    images = ImageStreamFromCompanion()
    script = build_script(ScriptConfig(steps=[
        ScriptStepConfig(wait_s=0.3), ScriptStepConfig(button="arm"), ScriptStepConfig(button="pan_scan_toggle"),
        ScriptStepConfig(push="forward", force_n=PUSH_N, duration_s=600.0)]))
    device = VirtualDevice(cfg.device, ScriptedOperator(script))
    station = Station(cfg, device, f"udpout:127.0.0.1:{companion.port}", images.url, http_port=0)
    station.start()
    try:
        yield station, companion, images
    finally:
        station.close()
        images.close()
        companion.close()


def test_manual_control_flows_and_commands_are_acked(running):
    station, companion, _ = running
    assert wait_for(lambda: len(companion.manual) >= 50)
    assert wait_for(lambda: companion.manual[-1][0] > 0)          # the push commands forward motion
    x, y, z, r = companion.manual[-1]
    assert 0 < x <= 1000 and y == 0 and z == 500 and r == 0
    assert wait_for(lambda: any("arm: ACCEPTED" in a for a in station.status()["acks"]))
    assert mavlink.MAV_CMD_COMPONENT_ARM_DISARM in companion.commands
    assert wait_for(lambda: companion.params.get("PANSCAN_EN") == 1.0)
    assert wait_for(lambda: any("pan_scan_on: ACCEPTED" in a for a in station.status()["acks"]))
    status = station.status()
    assert status["link_ok"] and status["mode"] == "teleop" and status["battery_v"] == pytest.approx(11.7)
    assert status["min_obstacle_m"] == pytest.approx(0.9)


def test_force_opposes_the_push_when_the_vehicle_is_blocked(running):
    station, companion, _ = running
    cfg = station.cfg
    companion.follow = False
    assert wait_for(lambda: (f := station.force) is not None and f.link_gain == 1.0)
    time.sleep(1.0)   # settle (handle time constant m / (c + B) = 50 ms)
    f = station.force
    assert f is not None and f.q_tilde_m is not None
    # blocked: q~ is the handle position that commands rest, the command's onset (eq. (16) + dead-band)
    onset = mapping_gains(cfg.mapping, cfg.device).command_onset_m[0]
    assert f.q_tilde_m[0] == pytest.approx(onset, abs=1e-9)
    # equilibrium of eq. (1) with eq. (15): push = K_f q + K (q - onset), force = -push
    q_eq = (PUSH_N + cfg.force.K_n_m[0] * onset) / (cfg.force.K_f_n_m[0] + cfg.force.K_n_m[0])
    assert f.device.q_m[0] == pytest.approx(q_eq, rel=0.05)
    assert f.tau_d_n[0] == pytest.approx(-PUSH_N, rel=0.05)
    q_blocked = f.device.q_m[0]
    # when the vehicle flies the command, the cue vanishes and the handle goes further for the same push
    companion.follow = True
    assert wait_for(lambda: station.force.device.q_m[0] > 2.5 * q_blocked)   # type: ignore[union-attr]
    companion.follow = False


@pytest.mark.skipif(CHROMIUM is None, reason="chromium is not installed (apt-get install chromium)")
def test_page_screenshot_shows_compensated_view_with_obstacles(running, tmp_path):
    station, _, _ = running
    assert wait_for(lambda: station.view_frames >= 10)
    assert station.server is not None
    shot = tmp_path / "page.png"
    cmd = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
           "--disable-background-networking", "--disable-component-update", "--disable-sync",
           "--disable-dev-shm-usage", f"--user-data-dir={tmp_path / 'profile'}", f"--screenshot={shot}",
           "--window-size=600,560", "--virtual-time-budget=1500", station.server.url]
    subprocess.run(cmd, capture_output=True, timeout=90, check=False)
    assert shot.is_file(), "chromium wrote no screenshot"
    Path("/tmp/teleop_page_screenshot.png").write_bytes(shot.read_bytes())   # for a human look
    img = cv2.imread(str(shot))
    assert img is not None and img.shape[0] >= 500 and img.shape[1] >= 580
    view = img[8:8 + 420, 8:8 + 560]                       # the <img> at the page's top-left margin
    b, g, r = (view[..., i].astype(int) for i in range(3))
    marker = (r > 180) & (g < 170) & (b < 80)               # red (near) or orange (far) obstacle points
    assert marker.sum() > 50, "no obstacle points drawn"
    greenish = (g > 100) & (g > r + 10)
    assert greenish.sum() > 5000, "no camera image in the view"
    assert view.std() > 20
    assert station.bad_image_meta == 0   # every image's metadata decoded


def test_force_process_shares_state_and_buttons(tmp_path):
    """The force loop in its own process (quadlink teleop's default): motion in, force/q out, presses through."""
    from teleop.force import VehicleMotion
    from teleop.force_loop import DeviceSpec, ForceProcess, MotionInput

    script = tmp_path / "s.yaml"
    script.write_text("steps:\n  - button: arm\n  - push: forward\n    force_n: 2.0\n    duration_s: 600\n")
    cfg = TeleopConfig()
    proc = ForceProcess(DeviceSpec("virtual", str(script)), cfg)
    try:
        assert proc.name == "virtual" and proc.has_force_output
        blocked = MotionInput(0.0, VehicleMotion((0.0, 0.0, 0.0), 0.0, 0.0, 0.0), cue_wanted=True)
        deadline = time.monotonic() + 20.0
        presses: list[str] = []
        snap = None
        while time.monotonic() < deadline:
            proc.set_motion(MotionInput(time.perf_counter(), blocked.motion, True), 12.5)
            presses += proc.buttons()
            snap = proc.snapshot()
            if snap is not None and snap.link_gain == 1.0 and snap.cue_gain == 1.0 and presses:
                break
            time.sleep(0.02)
        time.sleep(0.5)
        proc.set_motion(MotionInput(time.perf_counter(), blocked.motion, True), 13.0)
        snap = proc.snapshot()
        assert presses == ["arm"]
        assert snap is not None and snap.q_tilde_m is not None
        onset = mapping_gains(cfg.mapping, cfg.device).command_onset_m[0]   # blocked: q~ = the onset
        q_eq = (2.0 + cfg.force.K_n_m[0] * onset) / (cfg.force.K_f_n_m[0] + cfg.force.K_n_m[0])
        assert snap.device.q_m[0] == pytest.approx(q_eq, rel=0.05)
        assert snap.tau_d_n[0] == pytest.approx(-2.0, rel=0.05)
        np.testing.assert_allclose(snap.device.operator_force_n, [2.0, 0.0, 0.0])
        assert proc.periods_s().size > 100 and not proc.finished
    finally:
        proc.close()
    assert not proc.alive

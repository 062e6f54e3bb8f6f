"""The operator image's metadata end to end: the real companion daemon publishes it (its real
OperatorImagePublisher), the ground station's real consumer (teleop.view_loop) decodes it and feeds the
pan-scan estimator and the overlay; and a viewer that never reads cannot slow the companion's loop."""

from __future__ import annotations

import dataclasses
import math
import socket
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from test_companion_daemon import Rig  # the daemon rig on loopback (real links, real camera stream)

from companion.image_publisher import OperatorImagePublisher
from perception.synthetic import qvga_intrinsics
from quadlink.camera import CameraStreamClient, RgbdFrame
from quadlink.errors import ProtocolError
from quadlink.mavlink import mavlink
from quadlink.operator_image import OperatorImageMeta
from teleop.config import TeleopConfig
from teleop.view.panscan import PanScanEstimate, PanScanEstimator
from teleop.view_loop import OperatorView, image_meta, make_estimator

pytestmark = pytest.mark.integration


class SpyEstimator(PanScanEstimator):
    """The station's real estimator, recording the arguments the view gives it."""

    def __init__(self, cfg: TeleopConfig) -> None:
        real = make_estimator(cfg)
        self.__dict__.update(real.__dict__)
        self.calls: list[tuple[float, float, bool, float]] = []

    def update(self, gyro_yaw_rate_rad_s: float, t_s: float, enabled: bool = True,
               operator_yaw_rate_cmd_rad_s: float = 0.0) -> PanScanEstimate:
        self.calls.append((gyro_yaw_rate_rad_s, t_s, enabled, operator_yaw_rate_cmd_rad_s))
        return super().update(gyro_yaw_rate_rad_s, t_s, enabled, operator_yaw_rate_cmd_rad_s)


STATUS: dict[str, Any] = {"battery_v": None, "min_obstacle_m": None, "link": "ok", "mode": "teleop", "armed": True,
                          "force_n": [0.0, 0.0, 0.0], "warnings": []}


def _read(client: CameraStreamClient, n: int, timeout_s: float = 5.0) -> list[RgbdFrame]:
    frames: list[RgbdFrame] = []
    deadline = time.monotonic() + timeout_s
    while len(frames) < n and time.monotonic() < deadline:
        f = client.read(0.1)
        if f is not None:
            frames.append(f)
            client.ack(f.seq)
    return frames


def test_view_gets_pan_scan_flag_and_overlay_from_the_companions_meta(tmp_path: Path) -> None:
    images = OperatorImagePublisher("127.0.0.1", 0)
    rig = Rig(tmp_path, images=images)
    client = CameraStreamClient(f"tcp://127.0.0.1:{images.port}")
    cfg = TeleopConfig()
    spy = SpyEstimator(cfg)
    view = OperatorView(cfg, estimator=spy)
    try:
        rig.gcs.link.mav.param_set_send(1, 191, b"PANSCAN_EN", 1.0, mavlink.MAV_PARAM_TYPE_REAL32)
        rig.take_off()
        deadline = time.monotonic() + 3.0
        while images.client_count == 0 and time.monotonic() < deadline:
            client.read(0.05)
            rig.frame(manual=(1000, 0, 500))

        def fly_and_view(n: int) -> list[tuple[RgbdFrame, OperatorImageMeta]]:
            got = []
            for _ in range(n):
                rig.frame(manual=(1000, 0, 500))
                got += [(f, image_meta(f)) for f in _read(client, 1, 1.0)]
            for f, meta in got:
                view.on_image(f, meta, 0.0, STATUS)
            return got

        spy.calls.clear()
        on = fly_and_view(20)
        assert len(on) >= 10
        assert all(m.pan_scan.enabled for _, m in on) and all(c[2] for c in spy.calls)
        assert [c[0] for c in spy.calls] == [m.gyro_yaw_rate_rad_s for _, m in on]
        # the pan-scan the companion runs: its commanded rate swings (eq. 4), and the meta carries it
        assert max(abs(m.pan_scan.yaw_rate_rad_s) for _, m in on) > 0.05
        # the overlay's commanded velocity is the setpoint the companion sent for that frame
        sp = {m.time_boot_ms: m for m in rig.ap.of_type("SET_POSITION_TARGET_LOCAL_NED")}
        matched = 0
        for f, meta in on:
            s = sp.get(int(f.stamp_s * 1e3))
            if s is not None:
                matched += 1
                assert meta.v_cmd_h_m_s == pytest.approx((s.vx, s.vy, s.vz), abs=1e-5)
        assert matched >= 5
        assert math.hypot(*on[-1][1].v_cmd_h_m_s[:2]) > 0.1   # forward on the handle

        # pan-scan off in the companion (the ground station's PARAM_SET) -> the estimator is told so
        rig.gcs.link.mav.param_set_send(1, 191, b"PANSCAN_EN", 0.0, mavlink.MAV_PARAM_TYPE_REAL32)
        rig.frame(manual=(1000, 0, 500))
        _read(client, 3, 1.0)
        spy.calls.clear()
        off = fly_and_view(15)
        assert len(off) >= 8
        assert not any(m.pan_scan.enabled for _, m in off) and not any(c[2] for c in spy.calls)
        assert all(m.pan_scan.yaw_rate_rad_s == 0.0 for _, m in off)

        # a renamed key on the wire is an error at the consumer, not a fallback
        f, _ = off[-1]
        for rename in (("v_cmd_h_m_s", "v_cmd_h"), ("pan_scan", "pan_scan_on")):
            wire = dict(f.meta)
            wire[rename[1]] = wire.pop(rename[0])
            with pytest.raises(ProtocolError):
                image_meta(RgbdFrame(f.seq, f.stamp_s, f.rgb, None, f.intrinsics, f.R_qc, f.p_qc_m, wire))
    finally:
        client.close()
        rig.close()


def test_a_viewer_that_never_reads_does_not_slow_the_companion(tmp_path: Path) -> None:
    """Issue 16: a client connected to the operator image port that never reads made the vehicle land."""
    images = OperatorImagePublisher("127.0.0.1", 0, stall_timeout_s=1.0)
    rig = Rig(tmp_path, images=images)
    # noise compresses badly: ~100 kB JPEG records, so a few seconds of them overflow any kernel buffer
    noise = np.random.default_rng(16).integers(0, 256, rig.template.rgb.shape, dtype=np.uint8)
    rig.template = dataclasses.replace(rig.template, rgb=noise)
    stuck = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    stuck.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)   # fills after a fraction of one frame
    try:
        stuck.connect(("127.0.0.1", images.port))
        deadline = time.monotonic() + 3.0
        while images.client_count == 0 and time.monotonic() < deadline:
            rig.frame(manual=(0, 0, 500), pace=False)
        assert images.client_count == 1
        n0 = len(rig.ap.of_type("SET_POSITION_TARGET_LOCAL_NED"))
        frame_s = []
        for _ in range(90):   # 3 s of frames: every one is acked (the companion processed it) promptly
            t0 = time.monotonic()
            rig.frame(manual=(0, 0, 500), pace=False)
            frame_s.append(time.monotonic() - t0)
            time.sleep(max(0.0, 1.0 / 30 - (time.monotonic() - t0)))
        time.sleep(0.05)
        rig.ap.poll()
        assert len(rig.ap.of_type("SET_POSITION_TARGET_LOCAL_NED")) - n0 >= 88   # a setpoint per frame
        # the old blocking sender waited up to 2 s per record on this viewer
        assert max(frame_s) < 0.5, f"slowest frame {max(frame_s):.3f} s"
        s = images.stats
        assert s.disconnected_stalled == 1 and images.client_count == 0
        assert s.skipped_busy >= 1
    finally:
        stuck.close()
        rig.close()


def test_publisher_drops_frames_whose_meta_would_not_decode() -> None:
    images = OperatorImagePublisher("127.0.0.1", 0)
    client = CameraStreamClient(f"tcp://127.0.0.1:{images.port}")
    try:
        k = qvga_intrinsics()
        rgb = np.zeros((k.height, k.width, 3), np.uint8)
        good = OperatorImageMeta.from_wire({
            "version": 2, "stamp_s": 1.0, "roll_rad": 0.0, "pitch_rad": 0.0, "yaw_rad": 0.0,
            "gyro_yaw_rate_rad_s": 0.1, "obstacle_points_c_m": [[0.0, 0.0, 1.0]], "v_cmd_h_m_s": [0.1, 0, 0],
            "v_est_h_m_s": [0, 0, 0], "mode": "teleop",
            "pan_scan": {"enabled": True, "yaw_rate_rad_s": 0.1, "yaw_offset_rad": 0.0, "alpha_rad": 0.7,
                         "amplitude_rad_s": 0.6, "omega_rad_s": 1.5},
            "vertical": {"height_m": 1.2, "floor_height_m": 0.3, "ceiling_height_m": None}})
        bad = OperatorImageMeta(**{**good.__dict__, "v_est_h_m_s": (math.nan, 0.0, 0.0)})
        deadline = time.monotonic() + 3.0
        while images.client_count == 0 and time.monotonic() < deadline:
            client.read(0.05)
        images.publish(RgbdFrame(1, 1.0, rgb, None, k), bad)
        time.sleep(0.2)
        images.publish(RgbdFrame(2, 1.1, rgb, None, k), good)
        got = _read(client, 1, 2.0)
        assert [f.seq for f in got] == [2] and image_meta(got[0]) == good
        assert images.stats.invalid_meta == 1
    finally:
        client.close()
        images.close()

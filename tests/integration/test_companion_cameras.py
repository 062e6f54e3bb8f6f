"""The companion's one camera interface: the SITL stream, TUM replay, optional sensors absent cleanly, URLs."""

from __future__ import annotations

import importlib.util
import threading
from pathlib import Path

import cv2
import numpy as np
import pytest

from companion.cameras import CameraUnavailable, StreamCamera, TumReplayCamera, open_camera
from perception.synthetic import pose, qvga_intrinsics, render
from quadlink.camera import CameraStreamServer, RgbdFrame
from quadlink.datasets.tum import associate

K = qvga_intrinsics()


def test_stream_camera_reads_frames_and_acks_for_lockstep() -> None:
    rgb, depth = render(pose(np.eye(3), [0.0, 0.0, 0.0]), K, supersample=1)
    server = CameraStreamServer("127.0.0.1", 0)
    acked: list[bool] = []

    def produce() -> None:
        if not server.wait_for_client(5.0):
            return
        for seq in (7, 8):
            server.publish(RgbdFrame(seq, seq / 30, rgb, depth, K))
            acked.append(server.wait_acks(seq, 5.0))

    thread = threading.Thread(target=produce, daemon=True)
    thread.start()
    cam = open_camera(f"tcp://127.0.0.1:{server.port}")
    assert isinstance(cam, StreamCamera)
    try:
        first = None
        for _ in range(50):
            first = cam.read(0.2)
            if first is not None:
                break
        assert first is not None and first.seq == 7 and first.depth_m is not None
        assert cam.connected
        assert np.allclose(first.depth_m, depth, atol=1e-3)  # millimetre wire format
        assert cam.read(0.3) is None  # the producer waits for our ack: nothing else comes
        assert acked == []
        cam.ack(first.seq)
        second = None
        for _ in range(25):
            second = cam.read(0.2)
            if second is not None:
                break
        assert second is not None and second.seq == 8
        cam.ack(second.seq)
        thread.join(2.0)
        assert acked == [True, True]
    finally:
        cam.close()
        server.close()


def test_stream_camera_without_a_producer_returns_none() -> None:
    server = CameraStreamServer("127.0.0.1", 0)
    port = server.port
    server.close()
    cam = StreamCamera(f"tcp://127.0.0.1:{port}")
    try:
        assert cam.read(0.05) is None and not cam.connected
    finally:
        cam.close()


def _write_sequence(folder: Path, n: int = 4) -> list[float]:
    (folder / "rgb").mkdir(parents=True)
    (folder / "depth").mkdir()
    rgb_lines, depth_lines, stamps = [], [], []
    for k in range(n):
        rgb, depth = render(pose(np.eye(3), [0.01 * k, 0.0, 0.0]), K, supersample=1)
        stamp = 1305031102.0 + k / 30
        cv2.imwrite(str(folder / "rgb" / f"{k}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        cv2.imwrite(str(folder / "depth" / f"{k}.png"), (depth * 5000).astype(np.uint16))
        rgb_lines.append(f"{stamp:.6f} rgb/{k}.png")
        depth_lines.append(f"{stamp + 0.004:.6f} depth/{k}.png")
        stamps.append(stamp)
    (folder / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (folder / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    return stamps


class _Clock:
    def __init__(self) -> None:
        self.t_s = 50.0
        self.slept: list[float] = []

    def __call__(self) -> float:
        return self.t_s

    def sleep(self, dt_s: float) -> None:
        self.slept.append(dt_s)
        self.t_s += dt_s


def test_tum_replay_keeps_the_recorded_pace_on_the_injected_clock(tmp_path: Path) -> None:
    stamps = _write_sequence(tmp_path / "seq")
    clock = _Clock()
    R_qc = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    cam = TumReplayCamera(tmp_path / "seq", clock, R_qc=R_qc, p_qc_m=np.array([0.1, 0.0, 0.0]), sleep=clock.sleep)
    frames = []
    for _ in range(20):
        f = cam.read(0.5)
        if f is not None:
            frames.append((clock.t_s, f))
        elif not cam.connected:
            break
    assert len(frames) == len(stamps) and not cam.connected
    got = np.array([f.stamp_s for _, f in frames])
    np.testing.assert_allclose(got, np.array(stamps) - stamps[0], atol=1e-6)  # shifted to start at 0
    walls = np.array([t for t, _ in frames])
    np.testing.assert_allclose(walls - walls[0], got, atol=1e-6)  # delivered at the recorded pace
    assert [f.seq for _, f in frames] == [1, 2, 3, 4]
    np.testing.assert_allclose(frames[0][1].R_qc, R_qc)
    assert frames[0][1].depth_m is not None and float(np.median(frames[0][1].depth_m[frames[0][1].depth_m > 0])) > 0.5


def test_open_camera_dispatches_by_url(tmp_path: Path) -> None:
    _write_sequence(tmp_path / "seq", n=2)
    assert isinstance(open_camera(str(tmp_path / "seq")), TumReplayCamera)
    assert isinstance(open_camera(f"tum://{tmp_path / 'seq'}"), TumReplayCamera)
    with pytest.raises(CameraUnavailable, match="tcp://HOST:PORT"):
        open_camera(str(tmp_path / "nowhere"))
    with pytest.raises(CameraUnavailable, match="rgb.txt"):
        (tmp_path / "empty").mkdir()
        open_camera(str(tmp_path / "empty"))
    with pytest.raises(CameraUnavailable, match="WIDTHxHEIGHT"):
        open_camera("realsense://?size=big")


def test_realsense_absent_is_a_one_line_error() -> None:
    """Without the SDK the error names the package; with it but no device, it says the device is missing."""
    have_sdk = importlib.util.find_spec("pyrealsense2") is not None
    with pytest.raises(CameraUnavailable, match="cannot start" if have_sdk else "pyrealsense2") as info:
        open_camera("realsense://640x480")
    assert "\n" not in str(info.value)


@pytest.mark.skipif(importlib.util.find_spec("openni") is not None, reason="openni installed")
def test_openni2_absent_is_a_one_line_error() -> None:
    with pytest.raises(CameraUnavailable, match="OpenNI2") as info:
        open_camera("openni://")
    assert "\n" not in str(info.value)


def test_tum_association_takes_the_nearest_pair_first() -> None:
    """TUM's associate.py: candidates within 20 ms, taken by increasing difference, each stamp once. A
    first-come pass would pair depth 1.015 with rgb 1.000 and leave rgb 1.010 (1 ms away) unpaired."""
    assert associate([1.000, 1.010], [1.011, 1.015]) == [(0, 1), (1, 0)]
    assert associate([0.0], [0.0201]) == []  # beyond 20 ms
    assert associate([0.0, 1.0], []) == []

"""The RealSense camera through the real pyrealsense2 library, without hardware: frames injected into its
software device (rs.software_device) and read back through librealsense's syncer, alignment, depth scale and
intrinsics — the code path of a live device. No part of the library's API is mocked."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from companion.cameras import CameraUnavailable, TumReplayCamera, camera_url, is_device_url, open_camera
from companion.cameras.device_clock import DeviceClockMap

pytestmark = pytest.mark.skipif(importlib.util.find_spec("pyrealsense2") is None, reason="needs pyrealsense2")


def _read_n(cam: object, n: int, timeout_s: float = 2.0, tries: int = 200) -> list:
    frames = []
    for _ in range(tries):
        f = cam.read(timeout_s)  # type: ignore[attr-defined]
        if f is not None:
            frames.append(f)
            cam.ack(f.seq)  # type: ignore[attr-defined]
        if len(frames) == n:
            break
    return frames


def test_tum_frames_through_the_software_device_keep_depth_intrinsics_and_stamps(tum_clip: Path) -> None:
    """Depth registered to colour with the device's scale (z16 mm) and the colour stream's intrinsics: the same
    depth (to the 1 mm quantum), intrinsics and stamps as the TUM replay read directly."""
    R_qc = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    cam = open_camera(f"realsense://software?source=tum://{tum_clip}", R_qc=R_qc, p_qc_m=np.zeros(3),
                      stamps="device")
    direct = TumReplayCamera(tum_clip)
    try:
        got = _read_n(cam, 5)
        want = _read_n(direct, 6)[1:]   # librealsense's syncer drops the first, unmatched frame (as a device's)
        assert len(got) == 5 and len(want) == 5
        for g, w in zip(got, want):
            # set on the software profiles, read back from the aligned colour; librealsense keeps them as float32
            # (fr3's fx 535.4 / 2 comes back as 267.70001220703125)
            assert (g.intrinsics.width, g.intrinsics.height) == (w.intrinsics.width, w.intrinsics.height)
            for key in ("fx", "fy", "cx", "cy"):
                assert getattr(g.intrinsics, key) == pytest.approx(getattr(w.intrinsics, key), rel=1e-6), key
            assert g.stamp_s == pytest.approx(w.stamp_s, abs=1e-6)   # the device's hardware clock, in s
            assert g.rgb.shape == w.rgb.shape and np.array_equal(g.rgb, w.rgb)
            valid = w.depth_m > 0
            assert valid.mean() > 0.5
            err = np.abs(g.depth_m[valid] - w.depth_m[valid])
            assert np.median(err) <= 0.0005 + 1e-6 and np.mean(err < 0.0011) > 0.95   # z16 mm quantum
            np.testing.assert_allclose(g.R_qc, R_qc)
        assert cam.camera.intrinsics is not None  # type: ignore[attr-defined]
        assert cam.camera._depth_scale_m == pytest.approx(0.001)  # type: ignore[attr-defined]
    finally:
        cam.close()
        direct.close()


def test_a_device_that_stops_delivering_returns_none_then_counts_as_lost() -> None:
    """A silent device (an unplugged cable: nothing arrives) never blocks a read beyond its timeout; after
    MAX_SILENT_READS empty reads the camera is not connected (the daemon's odometry fails, the vehicle holds)."""
    from companion.cameras.realsense import MAX_SILENT_READS, RealSenseCamera
    from companion.cameras.realsense_software import SoftwareRealSense
    from perception.synthetic import qvga_intrinsics

    device = SoftwareRealSense(qvga_intrinsics())
    cam = RealSenseCamera(device=device.device, stamps="device")
    try:
        for _ in range(MAX_SILENT_READS):
            assert cam.connected
            assert cam.read(0.02) is None
        assert not cam.connected
        assert cam.read(0.02) is None
    finally:
        cam.close()


def test_device_clock_maps_to_the_least_delayed_arrival_and_resets_on_a_jump() -> None:
    rng = np.random.default_rng(3)
    m = DeviceClockMap()
    offset = 1234.5
    device = np.arange(0.0, 10.0, 1 / 30)
    latency = 0.005 + rng.exponential(0.01, device.size)   # transport latency: >= 5 ms, never negative
    local = [m.to_local(d, d + offset + lat) for d, lat in zip(device, latency)]
    # once a least-delayed frame has been seen, every stamp is the device stamp on the local clock to within
    # the minimum latency plus the slow creep (never later than the arrival)
    err = np.asarray(local[60:]) - (device[60:] + offset)
    assert np.all(err >= 0.0) and np.all(err <= 0.0051 + 1e-4 * 10)
    assert np.all(np.asarray(local) <= device + offset + latency + 1e-9)
    # the device restarts (its clock back to zero): the map follows at once
    assert m.to_local(0.0, 2000.0) == pytest.approx(2000.0)


def test_cli_shorthands_map_to_urls() -> None:
    assert camera_url("realsense") == "realsense://"
    assert camera_url("realsense:123456789012") == "realsense://123456789012"
    assert camera_url("openni") == "openni://"
    assert camera_url("openni:1d27/0601@1/5") == "openni://1d27/0601@1/5"
    assert camera_url("tcp://127.0.0.1:5762") == "tcp://127.0.0.1:5762"
    assert is_device_url("realsense://") and is_device_url("openni://")
    assert not is_device_url("realsense://software?source=tum://x") and not is_device_url("tcp://h:1")
    with pytest.raises(CameraUnavailable, match="source"):
        open_camera("realsense://software")


def test_no_device_is_a_one_line_error_from_the_cli() -> None:
    """`quadlink companion --camera realsense:SERIAL` with no such device: one line, a non-zero status, no hang."""
    r = subprocess.run([sys.executable, "-m", "quadlink.cli", "companion", "--camera", "realsense:000000000000",
                        "--autopilot", "udpin:127.0.0.1:33101", "--gcs", "udpin:127.0.0.1:33102",
                        "--image-port", "0", "--duration", "1"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2
    errors = [line for line in r.stderr.splitlines() if line.startswith("quadlink: error:")]
    assert len(errors) == 1 and "RealSense" in errors[0] and "cannot start" in errors[0], r.stderr


@pytest.mark.skipif(importlib.util.find_spec("openni") is not None, reason="openni installed")
def test_openni_without_its_runtime_is_a_one_line_error_from_the_cli() -> None:
    r = subprocess.run([sys.executable, "-m", "quadlink.cli", "companion", "--camera", "openni",
                        "--autopilot", "udpin:127.0.0.1:33103", "--gcs", "udpin:127.0.0.1:33104",
                        "--image-port", "0", "--duration", "1"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2
    errors = [line for line in r.stderr.splitlines() if line.startswith("quadlink: error:")]
    assert len(errors) == 1 and "OpenNI2" in errors[0], r.stderr

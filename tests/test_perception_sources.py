"""Camera sources: the SITL stream behind the common interface, optional sensors absent cleanly."""

from __future__ import annotations

import importlib.util
import threading

import numpy as np
import pytest

from perception.sources import OpenNI2Source, RealSenseSource, SourceUnavailable, StreamSource
from perception.synthetic import pose, qvga_intrinsics, render
from quadlink.camera import CameraStreamServer, RgbdFrame
from quadlink.errors import LinkError


def test_stream_source_yields_frames_and_acks_after_processing() -> None:
    K = qvga_intrinsics()
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
    source = StreamSource(f"tcp://127.0.0.1:{server.port}", read_timeout_s=0.2, idle_timeout_s=5.0)
    try:
        frames = source.frames()
        first = next(frames)
        assert first.seq == 7 and first.depth_m is not None
        assert np.allclose(first.depth_m, depth, atol=1e-3)        # millimetre wire format
        assert acked == []                                            # not acked while being processed
        second = next(frames)                                         # resuming acks the first
        assert second.seq == 8
        frames.close()
        thread.join(1.0)
        assert acked[:1] == [True]
    finally:
        source.close()
        server.close()


def test_stream_source_gives_up_after_the_idle_timeout() -> None:
    server = CameraStreamServer("127.0.0.1", 0)
    source = StreamSource(f"tcp://127.0.0.1:{server.port}", read_timeout_s=0.1, idle_timeout_s=0.3)
    try:
        with pytest.raises(LinkError, match="no camera frame"):
            next(source.frames())
    finally:
        source.close()
        server.close()


@pytest.mark.skipif(importlib.util.find_spec("pyrealsense2") is not None, reason="pyrealsense2 installed")
def test_realsense_absent_is_a_clear_error() -> None:
    with pytest.raises(SourceUnavailable, match="pyrealsense2"):
        RealSenseSource()


@pytest.mark.skipif(importlib.util.find_spec("openni") is not None, reason="openni installed")
def test_openni2_absent_is_a_clear_error() -> None:
    with pytest.raises(SourceUnavailable, match="OpenNI2"):
        OpenNI2Source()

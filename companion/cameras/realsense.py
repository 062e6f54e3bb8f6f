"""``realsense://[WIDTHxHEIGHT]``: an Intel RealSense via pyrealsense2 (colour aligned to depth), 30 Hz."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion.cameras.base import CameraUnavailable, DeviceCamera
from quadlink.camera import CameraIntrinsics, RgbdFrame


class RealSenseCamera(DeviceCamera):
    """Frames stamped with the device's clock (s); ``read`` waits at most ``timeout_s`` (try_wait_for_frames)."""

    def __init__(self, width: int = 640, height: int = 480, rate_hz: int = 30,
                 R_qc: NDArray[np.float64] | None = None, p_qc_m: NDArray[np.float64] | None = None) -> None:
        super().__init__(R_qc, p_qc_m)
        try:
            import pyrealsense2 as rs  # type: ignore[import-not-found]
        except ImportError as exc:
            raise CameraUnavailable("RealSense camera needs pyrealsense2 (pip install pyrealsense2)") from exc
        self._rs = rs
        self._pipe = rs.pipeline()
        cfg = rs.config()
        cfg.enable_stream(rs.stream.depth, width, height, rs.format.z16, rate_hz)
        cfg.enable_stream(rs.stream.color, width, height, rs.format.rgb8, rate_hz)
        try:
            profile = self._pipe.start(cfg)
        except RuntimeError as exc:
            raise CameraUnavailable(f"RealSense: cannot start ({exc})") from exc
        self._depth_scale_m = profile.get_device().first_depth_sensor().get_depth_scale()
        self._align = rs.align(rs.stream.depth)
        intr = profile.get_stream(rs.stream.depth).as_video_stream_profile().get_intrinsics()
        self.intrinsics = CameraIntrinsics(intr.fx, intr.fy, intr.ppx, intr.ppy, intr.width, intr.height)

    def read(self, timeout_s: float) -> RgbdFrame | None:
        ok, fs = self._pipe.try_wait_for_frames(max(1, int(timeout_s * 1000)))
        if not ok:
            return None
        fs = self._align.process(fs)
        depth: NDArray[Any] = np.asanyarray(fs.get_depth_frame().get_data()).astype(np.float32) * self._depth_scale_m
        rgb = np.asanyarray(fs.get_color_frame().get_data()).copy()
        return self._frame(fs.get_timestamp() * 1e-3, rgb, depth, self.intrinsics)

    def _stop(self) -> None:
        self._pipe.stop()

"""``openni://``: an Asus Xtion / Kinect via the OpenNI2 Python bindings (``openni`` package), registered depth."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion.cameras.base import CameraUnavailable, DeviceCamera
from quadlink.camera import CameraIntrinsics, RgbdFrame


class OpenNI2Camera(DeviceCamera):
    """Depth (mm) registered to colour; ``read`` waits at most ``timeout_s`` per stream (wait_for_any_stream)."""

    def __init__(self, hfov_deg: float = 58.0, vfov_deg: float = 45.0, R_qc: NDArray[np.float64] | None = None,
                 p_qc_m: NDArray[np.float64] | None = None) -> None:
        super().__init__(R_qc, p_qc_m)
        try:
            from openni import openni2  # type: ignore[import-not-found]
        except ImportError as exc:
            raise CameraUnavailable("OpenNI2 camera needs the openni package and the OpenNI2 runtime") from exc
        try:
            openni2.initialize()
            self._dev = openni2.Device.open_any()
        except Exception as exc:  # noqa: BLE001 - the bindings raise their own untyped errors
            raise CameraUnavailable(f"OpenNI2: no device ({exc})") from exc
        self._dev.set_image_registration_mode(openni2.IMAGE_REGISTRATION_DEPTH_TO_COLOR)
        self._depth = self._dev.create_depth_stream()
        self._color = self._dev.create_color_stream()
        self._depth.start()
        self._color.start()
        self._openni2 = openni2
        self._fov = (hfov_deg, vfov_deg)

    def _ready(self, stream: Any, timeout_s: float) -> bool:
        return self._openni2.wait_for_any_stream([stream], timeout_s) is not None  # timeout in s (the bindings' unit)

    def read(self, timeout_s: float) -> RgbdFrame | None:
        if not self._ready(self._depth, timeout_s):
            return None
        d = self._depth.read_frame()
        if not self._ready(self._color, timeout_s):
            return None
        c = self._color.read_frame()
        depth = np.frombuffer(d.get_buffer_as_uint16(), dtype=np.uint16).reshape(d.height, d.width)
        rgb = np.frombuffer(c.get_buffer_as_triplet(), dtype=np.uint8).reshape(c.height, c.width, 3).copy()
        k = CameraIntrinsics.from_fov(d.width, d.height, *self._fov)
        return self._frame(d.timestamp * 1e-6, rgb, depth.astype(np.float32) * 1e-3, k)

    def _stop(self) -> None:
        self._depth.stop()
        self._color.stop()
        self._openni2.unload()

"""``openni://[URI]``: an Asus Xtion / Kinect via the OpenNI2 Python bindings (``openni`` package).

Depth registered to colour (IMAGE_REGISTRATION_DEPTH_TO_COLOR); the intrinsics from the depth stream's
fields of view and the depth unit from its pixel format, both read from the device; device timestamps (µs)
mapped to the companion's clock (``stamps="local"``); every wait bounded (``wait_for_any_stream`` with the
read's timeout). The bindings need the OpenNI2 runtime (``libOpenNI2.so`` and its drivers), which the pip
package does not ship: without it the camera fails to open with one line (see companion/README.md for the
installation on the Odroid).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from companion.cameras.base import CameraUnavailable, DeviceCamera
from companion.cameras.device_clock import DeviceClockMap
from quadlink.camera import CameraIntrinsics, RgbdFrame

US = 1e-6


class OpenNI2Camera(DeviceCamera):
    """See the module docstring; ``uri`` picks one device (None: any)."""

    def __init__(self, uri: str | None = None, R_qc: NDArray[np.float64] | None = None,
                 p_qc_m: NDArray[np.float64] | None = None, stamps: Literal["local", "device"] = "local",
                 clock: Callable[[], float] = time.monotonic) -> None:
        super().__init__(R_qc, p_qc_m)
        self._started = False
        try:
            from openni import openni2  # type: ignore[import-not-found]
        except ImportError as exc:
            raise CameraUnavailable("OpenNI2 camera needs the openni package (pip install openni) and the "
                                    "OpenNI2 runtime") from exc
        self._openni2 = openni2
        try:
            openni2.initialize()
        except Exception as exc:  # noqa: BLE001 - the bindings raise their own untyped errors
            raise CameraUnavailable(f"OpenNI2: runtime not found ({str(exc).splitlines()[0]}); install "
                                    "libopenni2 or set OPENNI2_REDIST") from exc
        try:
            self._dev = openni2.Device.open_file(uri.encode()) if uri and uri.endswith(".oni") else \
                openni2.Device(uri.encode() if uri else None)
            self._dev.set_image_registration_mode(openni2.IMAGE_REGISTRATION_DEPTH_TO_COLOR)
            self._depth = self._dev.create_depth_stream()
            self._color = self._dev.create_color_stream()
            self._depth.start()
            self._color.start()
        except Exception as exc:  # noqa: BLE001
            openni2.unload()
            raise CameraUnavailable(f"OpenNI2: no device{' ' + uri if uri else ''} "
                                    f"({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})") from exc
        self._started = True
        self._stamps = stamps
        self._clock = clock
        self._clock_map = DeviceClockMap()
        mode = self._depth.get_video_mode()
        self._depth_unit_m = 1e-4 if "100_UM" in str(mode.pixelFormat) else 1e-3
        self._fov_rad = (float(self._depth.get_horizontal_fov()), float(self._depth.get_vertical_fov()))

    def _wait(self, stream: Any, deadline_s: float) -> bool:
        left_s = deadline_s - self._clock()
        if left_s <= 0:
            return False
        return self._openni2.wait_for_any_stream([stream], left_s) is not None  # timeout in s (the bindings' unit)

    def read(self, timeout_s: float) -> RgbdFrame | None:
        if not self._running:
            return None
        deadline = self._clock() + timeout_s
        if not self._wait(self._depth, deadline):
            return None
        d = self._depth.read_frame()
        if not self._wait(self._color, deadline):
            return None
        c = self._color.read_frame()
        depth = np.frombuffer(d.get_buffer_as_uint16(), dtype=np.uint16).reshape(d.height, d.width)
        rgb = np.frombuffer(c.get_buffer_as_triplet(), dtype=np.uint8).reshape(c.height, c.width, 3).copy()
        hfov, vfov = self._fov_rad
        k = CameraIntrinsics.from_fov(d.width, d.height, math.degrees(hfov), math.degrees(vfov))
        device_s = d.timestamp * US
        stamp_s = self._clock_map.to_local(device_s, self._clock()) if self._stamps == "local" else device_s
        return self._frame(stamp_s, rgb, depth.astype(np.float32) * np.float32(self._depth_unit_m), k)

    def _stop(self) -> None:
        if self._started:
            self._depth.stop()
            self._color.stop()
            self._openni2.unload()

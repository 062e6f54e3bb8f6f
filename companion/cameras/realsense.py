"""``realsense://[SERIAL][?size=WxH]``: an Intel RealSense through pyrealsense2, depth registered to colour.

* depth aligned to the colour camera (``rs.align(rs.stream.color)``); the intrinsics are the colour
  stream's and the depth scale the depth sensor's, both read from the device;
* ``stamps="local"`` maps the device's timestamps to the companion's clock (:mod:`.device_clock`) — what
  ``camera_stamps: local`` expects; ``"device"`` passes them through (a software device replaying frames
  whose clock is the autopilot's, e.g. the SITL's);
* every read waits at most its timeout; a device that stops delivering (an unplugged cable) makes reads
  return None (the companion's odometry fails and the vehicle holds) and ``connected`` False.

The frames come from a live device (``rs.pipeline``) or from an ``rs.software_device`` given as ``device``
(:mod:`.realsense_software`): the same syncer, alignment, scale and intrinsics code reads both.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from companion.cameras.base import CameraUnavailable, DeviceCamera
from companion.cameras.device_clock import DeviceClockMap
from quadlink.camera import CameraIntrinsics, RgbdFrame

log = logging.getLogger(__name__)

MS = 1e-3
#: consecutive empty reads (each a full timeout) after which the device counts as gone
MAX_SILENT_READS = 10


def import_pyrealsense2() -> Any:
    try:
        import pyrealsense2 as rs  # type: ignore[import-not-found]
    except ImportError as exc:
        raise CameraUnavailable("RealSense camera needs pyrealsense2 (pip install pyrealsense2)") from exc
    return rs


class RealSenseCamera(DeviceCamera):
    """See the module docstring. ``serial`` picks one of several devices (None: the first)."""

    def __init__(self, width: int = 640, height: int = 480, rate_hz: int = 30, serial: str | None = None,
                 R_qc: NDArray[np.float64] | None = None, p_qc_m: NDArray[np.float64] | None = None,
                 stamps: Literal["local", "device"] = "local", clock: Callable[[], float] = time.monotonic,
                 device: Any = None) -> None:
        super().__init__(R_qc, p_qc_m)
        rs = import_pyrealsense2()
        self._rs = rs
        self._clock = clock
        self._stamps = stamps
        self._clock_map = DeviceClockMap()
        self._silent_reads = 0
        self._pipe: Any = None
        self._sensors: list[Any] = []
        try:
            if device is None:
                dev = self._start_pipeline(width, height, rate_hz, serial)
            else:
                dev = self._start_software(device)
            self._depth_scale_m = float(dev.first_depth_sensor().get_depth_scale())
        except RuntimeError as exc:  # librealsense reports a missing or busy device as RuntimeError
            self._stop()
            raise CameraUnavailable(f"RealSense{' ' + serial if serial else ''}: cannot start ({exc})") from exc
        self._align = rs.align(rs.stream.color)
        self.intrinsics: CameraIntrinsics | None = None   # from the first aligned frame's colour profile

    def _start_pipeline(self, width: int, height: int, rate_hz: int, serial: str | None) -> Any:
        rs = self._rs
        if not rs.context().query_devices().size():
            raise RuntimeError("no device connected")
        cfg = rs.config()
        if serial:
            cfg.enable_device(serial)
        cfg.enable_stream(rs.stream.depth, width, height, rs.format.z16, rate_hz)
        cfg.enable_stream(rs.stream.color, width, height, rs.format.rgb8, rate_hz)
        self._pipe = rs.pipeline()
        profile = self._pipe.start(cfg)
        return profile.get_device()

    def _start_software(self, device: Any) -> Any:
        """Open the depth (z16) and colour (rgb8) streams of a software device into one syncer."""
        rs = self._rs
        self._syncer = rs.syncer()
        for sensor in device.query_sensors():
            profiles = [p for p in sensor.get_stream_profiles()
                        if p.stream_type() in (rs.stream.depth, rs.stream.color)]
            if profiles:
                sensor.open(profiles)
                sensor.start(self._syncer)
                self._sensors.append(sensor)
        if len(self._sensors) < 2:
            raise RuntimeError("the software device needs a depth and a colour sensor")
        return device

    def _wait(self, timeout_ms: int) -> Any:
        source = self._pipe if self._pipe is not None else self._syncer
        ok, frames = source.try_wait_for_frames(timeout_ms)
        return frames if ok else None

    def read(self, timeout_s: float) -> RgbdFrame | None:
        if not self._running:
            return None
        deadline = self._clock() + timeout_s
        while True:   # a syncer may hand out a lone depth or colour frame first: wait for a matched pair
            left_ms = int((deadline - self._clock()) * 1000)
            try:
                fs = self._wait(max(1, left_ms))
            except RuntimeError as exc:   # the device went away under us
                log.error("RealSense: %s", exc)
                fs = None
                self._silent_reads = MAX_SILENT_READS
            if fs is not None and fs.get_depth_frame() and fs.get_color_frame():
                break
            if fs is None or left_ms <= 0:
                self._silent_reads += 1
                if self._silent_reads >= MAX_SILENT_READS and self._running:
                    log.error("RealSense: no frames for %d reads: device lost", self._silent_reads)
                    self.close()   # connected -> False; the daemon's odometry fails and the vehicle holds
                return None
        self._silent_reads = 0
        arrival_s = self._clock()
        aligned = self._align.process(fs)
        depth_frame, color_frame = aligned.get_depth_frame(), aligned.get_color_frame()
        if self.intrinsics is None:
            i = color_frame.profile.as_video_stream_profile().get_intrinsics()
            self.intrinsics = CameraIntrinsics(i.fx, i.fy, i.ppx, i.ppy, i.width, i.height)
        depth_m: NDArray[np.float32] = np.asanyarray(depth_frame.get_data()).astype(np.float32) \
            * np.float32(self._depth_scale_m)
        rgb: NDArray[np.uint8] = np.asanyarray(color_frame.get_data()).copy()
        device_s = aligned.get_timestamp() * MS
        stamp_s = self._clock_map.to_local(device_s, arrival_s) if self._stamps == "local" else device_s
        return self._frame(stamp_s, rgb, depth_m, self.intrinsics)

    def _stop(self) -> None:
        if self._pipe is not None:
            try:
                self._pipe.stop()
            except RuntimeError:
                pass
        for sensor in self._sensors:
            try:
                sensor.stop()
                sensor.close()
            except RuntimeError:
                pass
        self._sensors = []

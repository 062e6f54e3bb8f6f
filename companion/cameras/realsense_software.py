"""``realsense://software?source=URL``: frames of another camera fed through pyrealsense2's software device.

An ``rs.software_device`` with a depth sensor (z16, the depth unit as its read-only ``depth_units``
option) and a colour sensor (rgb8), the source's intrinsics on both stream profiles and identity
extrinsics between them (the source's depth is already registered to its colour). Each frame read from
the source (a TUM folder, the SITL's ``tcp://`` stream) is injected with ``on_video_frame`` and read back
by :class:`~companion.cameras.realsense.RealSenseCamera` — librealsense's syncer, alignment, depth scale
and intrinsics, the code path of a real device — so ``quadlink companion --camera realsense`` can be run
without the hardware. The source's stamps become the device's hardware clock (``stamps`` decides, as for
a real device, whether they are mapped to the local clock); acks go back to the source (lock-step SITL).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from companion.cameras.base import CameraInput, CameraUnavailable
from companion.cameras.realsense import RealSenseCamera, import_pyrealsense2
from quadlink.camera import CameraIntrinsics, RgbdFrame

DEPTH_UNIT_M = 0.001   # z16 in mm, as the D400 series
# an injected frame comes back through librealsense's threads (matcher, alignment) a few ms later: wait that
# long for it whatever the caller's poll timeout (the daemon polls for 4 ms; a frame read back late would
# count as a silent device read, and in lock-step the next one is only sent after this one's ack)
INJECTED_FRAME_TIMEOUT_S = 0.25
# librealsense's syncer pairs nothing whose hardware-clock stamps are small (measured with pyrealsense2 2.x: none
# below ~500 s, all from 5000 s), and a SITL's sim-time stamps start near 0: the software device's clock runs
# this far ahead of its source's, and the camera takes it off again (stamps "device")
DEVICE_CLOCK_OFFSET_S = 1.0e6


class SoftwareRealSense:
    """A software RealSense of a fixed size: ``inject(frame)`` makes one depth + colour pair arrive."""

    def __init__(self, intrinsics: CameraIntrinsics, rate_hz: int = 30, depth_unit_m: float = DEPTH_UNIT_M) -> None:
        rs = import_pyrealsense2()
        self._rs = rs
        self.intrinsics = intrinsics
        self.depth_unit_m = depth_unit_m
        self.device = rs.software_device()
        self._depth_sensor = self.device.add_sensor("Depth")
        self._color_sensor = self.device.add_sensor("Color")
        intr = rs.intrinsics()
        intr.width, intr.height = intrinsics.width, intrinsics.height
        intr.fx, intr.fy, intr.ppx, intr.ppy = intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy
        intr.model = rs.distortion.none
        intr.coeffs = [0.0] * 5
        self._depth_profile = self._depth_sensor.add_video_stream(
            self._stream(rs.stream.depth, 0, rs.format.z16, 2, rate_hz, intr)).as_video_stream_profile()
        self._color_profile = self._color_sensor.add_video_stream(
            self._stream(rs.stream.color, 1, rs.format.rgb8, 3, rate_hz, intr)).as_video_stream_profile()
        self._depth_sensor.add_read_only_option(rs.option.depth_units, depth_unit_m)
        identity = rs.extrinsics()
        identity.rotation = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
        identity.translation = [0.0, 0.0, 0.0]
        self._depth_profile.register_extrinsics_to(self._color_profile, identity)
        self.device.create_matcher(rs.matchers.default)   # pair depth and colour by timestamp
        self._number = 0

    def _stream(self, kind: Any, uid: int, fmt: Any, bpp: int, rate_hz: int, intr: Any) -> Any:
        vs = self._rs.video_stream()
        vs.type, vs.index, vs.uid = kind, 0, uid
        vs.width, vs.height, vs.fps, vs.bpp, vs.fmt = intr.width, intr.height, rate_hz, bpp, fmt
        vs.intrinsics = intr
        return vs

    def _video_frame(self, pixels: NDArray[Any], bpp: int, stamp_ms: float, profile: Any) -> Any:
        f = self._rs.software_video_frame()
        f.pixels = np.ascontiguousarray(pixels)
        f.stride, f.bpp = pixels.shape[1] * bpp, bpp
        f.timestamp, f.domain = stamp_ms, self._rs.timestamp_domain.hardware_clock
        f.frame_number, f.profile = self._number, profile
        return f

    def inject(self, frame: RgbdFrame) -> None:
        k = self.intrinsics
        if frame.depth_m is None or frame.rgb.shape[:2] != (k.height, k.width):
            raise CameraUnavailable(f"software RealSense: frame {frame.seq} is not a {k.width}x{k.height} RGB-D frame")
        depth = np.nan_to_num(np.asarray(frame.depth_m, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
        z16 = np.clip(np.round(depth / self.depth_unit_m), 0, 65535).astype(np.uint16)
        stamp_ms = (frame.stamp_s + DEVICE_CLOCK_OFFSET_S) * 1000.0
        self._number += 1
        self._depth_sensor.on_video_frame(self._video_frame(z16, 2, stamp_ms, self._depth_profile))
        self._color_sensor.on_video_frame(self._video_frame(np.asarray(frame.rgb, np.uint8), 3, stamp_ms,
                                                             self._color_profile))


class SoftwareRealSenseCamera:
    """A :class:`RealSenseCamera` on a :class:`SoftwareRealSense` fed from ``source`` (sized by its first frame)."""

    def __init__(self, source: CameraInput, R_qc: NDArray[np.float64] | None = None,
                 p_qc_m: NDArray[np.float64] | None = None, stamps: Literal["local", "device"] = "device",
                 clock: Callable[[], float] = time.monotonic, first_frame_timeout_s: float = 30.0) -> None:
        self._source = source
        self._R_qc, self._p_qc_m, self._stamps, self._clock = R_qc, p_qc_m, stamps, clock
        self._first_frame_timeout_s = first_frame_timeout_s
        self._device: SoftwareRealSense | None = None
        self.camera: RealSenseCamera | None = None
        self._source_seq: int | None = None

    @property
    def connected(self) -> bool:
        return self._source.connected and (self.camera is None or self.camera.connected)

    def read(self, timeout_s: float) -> RgbdFrame | None:
        frame = self._source.read(timeout_s)
        if frame is None:
            return None
        if self._device is None:
            self._device = SoftwareRealSense(frame.intrinsics)
            self.camera = RealSenseCamera(R_qc=self._R_qc, p_qc_m=self._p_qc_m, stamps=self._stamps, clock=self._clock,
                                          device=self._device.device)
        assert self.camera is not None
        self._device.inject(frame)
        self._source_seq = frame.seq
        out = self.camera.read(max(timeout_s, INJECTED_FRAME_TIMEOUT_S))
        if out is not None and self._stamps == "device":
            out = dataclasses.replace(out, stamp_s=out.stamp_s - DEVICE_CLOCK_OFFSET_S)
        if out is None:
            # librealsense's syncer drops the first unmatched frame (it learns the streams from it), and a
            # dropped frame is never acked by the daemon: ack it here, or a lock-step producer would wait on it
            self._source.ack(frame.seq)
        return out

    def ack(self, seq: int) -> None:
        if self._source_seq is not None:
            self._source.ack(self._source_seq)   # one frame in flight: the one just read back

    def close(self) -> None:
        if self.camera is not None:
            self.camera.close()
        self._source.close()

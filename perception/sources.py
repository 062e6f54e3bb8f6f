"""Camera sources behind one interface: every source yields :class:`quadlink.camera.RgbdFrame`.

* :class:`TumFolderSource` — a TUM RGB-D format folder (``rgb.txt``, ``depth.txt``, optional ``camera.yaml``
  with ``fx, fy, cx, cy, depth_scale``), colour PNG or JPEG, depth 16-bit PNG; colour and depth associated
  by nearest stamp (TUM's ``associate.py`` rule, max 20 ms).
* :class:`StreamSource` — the SITL camera stream (:class:`quadlink.camera.CameraStreamClient`).
* :class:`RealSenseSource`, :class:`OpenNI2Source` — optional real sensors; constructing one without the
  package raises :class:`SourceUnavailable` with a one-line reason.

This is an I/O module (the edge); the algorithms in this package never read files or sockets.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import cv2
import numpy as np
import yaml
from numpy.typing import NDArray

from quadlink.camera import CameraIntrinsics, CameraStreamClient, RgbdFrame
from quadlink.errors import ConfigError, LinkError, QuadlinkError

log = logging.getLogger(__name__)

TUM_DEPTH_SCALE = 5000.0  # TUM RGB-D depth PNGs: 5000 units per metre
TUM_DEFAULT = {"fx": 525.0, "fy": 525.0, "cx": 319.5, "cy": 239.5}  # TUM's recommended pre-registered values
MAX_ASSOCIATION_DT_S = 0.02


class SourceUnavailable(QuadlinkError):
    """A camera source cannot be opened (missing package, device or folder)."""


class FrameSource(Protocol):
    """Anything that yields RGB-D frames; ``close()`` releases the device/link."""

    def frames(self) -> Iterator[RgbdFrame]: ...

    def close(self) -> None: ...


@dataclass(frozen=True)
class TumCameraParams:
    """Pinhole intrinsics and depth scale (units per metre) of a TUM-format sequence."""

    fx: float
    fy: float
    cx: float
    cy: float
    depth_scale: float


def read_tum_list(path: Path) -> list[tuple[float, str]]:
    """``stamp rest...`` lines of a TUM list file (comments skipped)."""
    if not path.is_file():
        raise SourceUnavailable(f"{path}: file not found")
    out: list[tuple[float, str]] = []
    for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split(maxsplit=1)
        try:
            out.append((float(parts[0]), parts[1].strip() if len(parts) > 1 else ""))
        except ValueError as exc:
            raise SourceUnavailable(f"{path}:{n}: bad timestamp {parts[0]!r}") from exc
    return out


def associate(stamps_a: list[float], stamps_b: list[float], max_dt_s: float = MAX_ASSOCIATION_DT_S
              ) -> list[tuple[int, int]]:
    """Greedy nearest-stamp matching (each element used once), as TUM's ``associate.py``; sorted by a."""
    b = np.asarray(stamps_b, dtype=float)
    candidates = []
    for i, ta in enumerate(stamps_a):
        if b.size == 0:
            break
        d = np.abs(b - ta)
        for j in np.flatnonzero(d <= max_dt_s).tolist():
            candidates.append((float(d[j]), i, j))
    candidates.sort()
    used_a: set[int] = set()
    used_b: set[int] = set()
    pairs = []
    for _, i, j in candidates:
        if i not in used_a and j not in used_b:
            used_a.add(i)
            used_b.add(j)
            pairs.append((i, j))
    return sorted(pairs)


def read_camera_params(folder: Path, overrides: dict[str, float | None] | None = None) -> TumCameraParams:
    """Intrinsics from ``camera.yaml`` if present, else TUM defaults; ``overrides`` (non-None) win."""
    values: dict[str, float] = dict(TUM_DEFAULT, depth_scale=TUM_DEPTH_SCALE)
    cam_file = folder / "camera.yaml"
    if cam_file.is_file():
        try:
            data = yaml.safe_load(cam_file.read_text(encoding="utf-8")) or {}
        except yaml.YAMLError as exc:
            raise ConfigError(f"{cam_file}: cannot read YAML: {str(exc).splitlines()[0]}") from exc
        if not isinstance(data, dict):
            raise ConfigError(f"{cam_file}: expected a mapping")
        for key, value in data.items():
            if key not in values:
                raise ConfigError(f"{cam_file}: unknown key {key!r} (expected fx, fy, cx, cy, depth_scale)")
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ConfigError(f"{cam_file}: {key}: expected a number, got {value!r}")
            values[key] = float(value)
    for key, value in (overrides or {}).items():
        if value is not None:
            values[key] = float(value)
    if values["depth_scale"] <= 0 or values["fx"] <= 0 or values["fy"] <= 0:
        raise ConfigError(f"{folder}: fx, fy and depth_scale must be positive")
    return TumCameraParams(**values)


def _read_image(path: Path, flags: int) -> NDArray[Any]:
    img = cv2.imread(str(path), flags)
    if img is None:
        raise SourceUnavailable(f"{path}: cannot read image")
    return img


class TumFolderSource:
    """Frames of a TUM RGB-D format folder, in stamp order (colour stamp is the frame stamp)."""

    def __init__(self, folder: str | Path, overrides: dict[str, float | None] | None = None,
                 max_frames: int | None = None, resize_to: tuple[int, int] | None = None) -> None:
        self.folder = Path(folder)
        if not self.folder.is_dir():
            raise SourceUnavailable(f"{self.folder}: not a directory")
        self.params = read_camera_params(self.folder, overrides)
        rgb = read_tum_list(self.folder / "rgb.txt")
        depth = read_tum_list(self.folder / "depth.txt")
        pairs = associate([s for s, _ in rgb], [s for s, _ in depth])
        if not pairs:
            raise SourceUnavailable(f"{self.folder}: no colour/depth pairs within {MAX_ASSOCIATION_DT_S * 1e3:.0f} ms")
        self._items = [(rgb[i][0], rgb[i][1], depth[j][1]) for i, j in pairs]
        if max_frames is not None:
            self._items = self._items[:max_frames]
        self.resize_to = resize_to

    def __len__(self) -> int:
        return len(self._items)

    def stamps(self) -> list[float]:
        return [s for s, _, _ in self._items]

    def frames(self) -> Iterator[RgbdFrame]:
        p = self.params
        for seq, (stamp, rgb_name, depth_name) in enumerate(self._items):
            bgr = _read_image(self.folder / rgb_name, cv2.IMREAD_COLOR)
            raw = _read_image(self.folder / depth_name, cv2.IMREAD_UNCHANGED)
            if raw.ndim != 2:
                raise SourceUnavailable(f"{self.folder / depth_name}: depth must be single-channel 16-bit")
            depth_m: NDArray[Any] = raw.astype(np.float32) / np.float32(p.depth_scale)
            h, w = depth_m.shape
            k = CameraIntrinsics(p.fx, p.fy, p.cx, p.cy, w, h)
            rgb: NDArray[Any] = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
            if self.resize_to is not None and (w, h) != self.resize_to:
                factor = self.resize_to[0] / w
                rgb = cv2.resize(rgb, self.resize_to, interpolation=cv2.INTER_AREA)
                depth_m = cv2.resize(depth_m, self.resize_to, interpolation=cv2.INTER_NEAREST)
                k = k.scaled(factor)
            yield RgbdFrame(seq, stamp, rgb, depth_m, k, meta={"rgb": rgb_name, "depth": depth_name})

    def close(self) -> None:
        return None


class StreamSource:
    """The SITL camera stream; acknowledges each frame after the consumer has processed it."""

    def __init__(self, url: str = "tcp://127.0.0.1:5762", read_timeout_s: float = 1.0,
                 idle_timeout_s: float = 10.0) -> None:
        self.url = url
        self.read_timeout_s = read_timeout_s
        self.idle_timeout_s = idle_timeout_s
        self._client = CameraStreamClient(url)
        log.info("camera stream source %s", url)

    def frames(self) -> Iterator[RgbdFrame]:
        idle = 0.0
        while True:
            frame = self._client.read(self.read_timeout_s)
            if frame is None:
                idle += self.read_timeout_s
                if idle >= self.idle_timeout_s:
                    raise LinkError(f"{self.url}: no camera frame for {self.idle_timeout_s:.0f} s")
                continue
            idle = 0.0
            yield frame
            self._client.ack(frame.seq)  # after the consumer's loop body: lock-step contract

    def close(self) -> None:
        self._client.close()


class RealSenseSource:
    """Intel RealSense via pyrealsense2 (colour aligned to depth), 30 Hz."""

    def __init__(self, width: int = 640, height: int = 480, rate_hz: int = 30) -> None:
        try:
            import pyrealsense2 as rs  # type: ignore[import-not-found]
        except ImportError as exc:
            raise SourceUnavailable("RealSense source needs pyrealsense2 (pip install pyrealsense2)") from exc
        self._rs = rs
        self._pipe = rs.pipeline()
        cfg = rs.config()
        cfg.enable_stream(rs.stream.depth, width, height, rs.format.z16, rate_hz)
        cfg.enable_stream(rs.stream.color, width, height, rs.format.rgb8, rate_hz)
        try:
            profile = self._pipe.start(cfg)
        except RuntimeError as exc:
            raise SourceUnavailable(f"RealSense: cannot start ({exc})") from exc
        self._depth_scale_m = profile.get_device().first_depth_sensor().get_depth_scale()
        self._align = rs.align(rs.stream.depth)
        intr = profile.get_stream(rs.stream.depth).as_video_stream_profile().get_intrinsics()
        self.intrinsics = CameraIntrinsics(intr.fx, intr.fy, intr.ppx, intr.ppy, intr.width, intr.height)

    def frames(self) -> Iterator[RgbdFrame]:
        seq = 0
        while True:
            fs = self._align.process(self._pipe.wait_for_frames(5000))
            depth = np.asanyarray(fs.get_depth_frame().get_data()).astype(np.float32) * self._depth_scale_m
            rgb = np.asanyarray(fs.get_color_frame().get_data()).copy()
            yield RgbdFrame(seq, fs.get_timestamp() * 1e-3, rgb, depth, self.intrinsics)
            seq += 1

    def close(self) -> None:
        self._pipe.stop()


class OpenNI2Source:
    """Asus Xtion / Kinect via the OpenNI2 Python bindings (``openni`` package), registered depth."""

    def __init__(self, hfov_deg: float = 58.0, vfov_deg: float = 45.0) -> None:
        try:
            from openni import openni2  # type: ignore[import-not-found]
        except ImportError as exc:
            raise SourceUnavailable("OpenNI2 source needs the openni package and OpenNI2 runtime") from exc
        try:
            openni2.initialize()
            self._dev = openni2.Device.open_any()
        except Exception as exc:  # noqa: BLE001 - the bindings raise their own untyped errors
            raise SourceUnavailable(f"OpenNI2: no device ({exc})") from exc
        self._dev.set_image_registration_mode(openni2.IMAGE_REGISTRATION_DEPTH_TO_COLOR)
        self._depth = self._dev.create_depth_stream()
        self._color = self._dev.create_color_stream()
        self._depth.start()
        self._color.start()
        self._openni2 = openni2
        self._fov = (hfov_deg, vfov_deg)

    def frames(self) -> Iterator[RgbdFrame]:
        seq = 0
        while True:
            d = self._depth.read_frame()
            c = self._color.read_frame()
            depth = np.frombuffer(d.get_buffer_as_uint16(), dtype=np.uint16).reshape(d.height, d.width)
            rgb = np.frombuffer(c.get_buffer_as_triplet(), dtype=np.uint8).reshape(c.height, c.width, 3).copy()
            k = CameraIntrinsics.from_fov(d.width, d.height, *self._fov)
            yield RgbdFrame(seq, d.timestamp * 1e-6, rgb, depth.astype(np.float32) * 1e-3, k)
            seq += 1

    def close(self) -> None:
        self._depth.stop()
        self._color.stop()
        self._openni2.unload()


def read_tum_trajectory(path: str | Path) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``timestamp tx ty tz qx qy qz qw`` file -> (stamps (N,), 4x4 poses (N,4,4))."""
    from quadlink.frames import R_from_quat_wxyz

    rows = read_tum_list(Path(path))
    stamps, poses = [], []
    for stamp, rest in rows:
        v = [float(x) for x in rest.split()]
        if len(v) != 7 or not all(math.isfinite(x) for x in v):
            raise SourceUnavailable(f"{path}: bad trajectory line at stamp {stamp}")
        T = np.eye(4)
        T[:3, :3] = R_from_quat_wxyz([v[6], v[3], v[4], v[5]])  # file is [qx qy qz qw]
        T[:3, 3] = v[:3]
        stamps.append(stamp)
        poses.append(T)
    return np.asarray(stamps), np.asarray(poses)


def write_tum_trajectory(path: str | Path, stamps: list[float] | NDArray[np.float64],
                         poses: list[NDArray[np.float64]] | NDArray[np.float64]) -> None:
    """Write ``timestamp tx ty tz qx qy qz qw`` lines (quaternion x,y,z,w as TUM tools expect)."""
    from quadlink.frames import quat_wxyz_from_R

    lines = ["# timestamp tx ty tz qx qy qz qw"]
    for stamp, T in zip(stamps, poses, strict=True):
        w, x, y, z = quat_wxyz_from_R(T[:3, :3])
        t = T[:3, 3]
        lines.append(f"{stamp:.6f} {t[0]:.6f} {t[1]:.6f} {t[2]:.6f} {x:.6f} {y:.6f} {z:.6f} {w:.6f}")
    Path(path).write_text("\n".join(lines) + "\n", encoding="utf-8")

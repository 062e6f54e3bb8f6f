"""The TUM RGB-D benchmark format: sequences (colour + depth folders), trajectories, intrinsics.

* :class:`TumSequence` — a TUM-format folder (``rgb.txt``, ``depth.txt``, optional ``camera.yaml`` with
  ``fx, fy, cx, cy, depth_scale``), colour PNG or JPEG, depth 16-bit PNG. Colour and depth are paired by
  :func:`associate`, the rule of TUM's ``associate.py``: every pair within ``max_dt_s`` (20 ms) is a
  candidate, candidates are taken greedily by increasing stamp difference and each stamp is used at most
  once (nearest first, not merely the first match in time). A folder whose pairs were fixed by its maker
  carries them in ``associations.txt`` (``rgb_stamp rgb_file depth_stamp depth_file`` per line, the output of
  ``associate.py rgb.txt depth.txt`` that ORB-SLAM's TUM examples read), which then wins.
* :func:`read_tum_trajectory` / :func:`write_tum_trajectory` — ``timestamp tx ty tz qx qy qz qw`` files
  (the file's quaternion is [x, y, z, w]; quadlink's is [w, x, y, z], converted here only).

File I/O: used by the companion's replay camera (:mod:`companion.cameras.tum`), ``vo-eval`` and the
benchmarks. Perception's algorithms take the frames, never the files.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml
from numpy.typing import NDArray

from quadlink.camera import CameraIntrinsics, RgbdFrame
from quadlink.errors import ConfigError, QuadlinkError
from quadlink.frames import R_from_quat_wxyz, quat_wxyz_from_R

TUM_DEPTH_SCALE = 5000.0  # TUM RGB-D depth PNGs: 5000 units per metre
TUM_DEFAULT = {"fx": 525.0, "fy": 525.0, "cx": 319.5, "cy": 239.5}  # TUM's recommended pre-registered values
MAX_ASSOCIATION_DT_S = 0.02


class DatasetUnavailable(QuadlinkError):
    """A data set cannot be read (missing folder or file, bad line, unreadable image)."""


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
        raise DatasetUnavailable(f"{path}: file not found")
    out: list[tuple[float, str]] = []
    for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split(maxsplit=1)
        try:
            out.append((float(parts[0]), parts[1].strip() if len(parts) > 1 else ""))
        except ValueError as exc:
            raise DatasetUnavailable(f"{path}:{n}: bad timestamp {parts[0]!r}") from exc
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


def read_associations(path: Path) -> list[tuple[float, str, float, str]]:
    """``rgb_stamp rgb_file depth_stamp depth_file`` lines (comments skipped), in colour-stamp order."""
    out = []
    for stamp, rest in read_tum_list(path):
        parts = rest.split()
        try:
            if len(parts) != 3:
                raise ValueError
            out.append((stamp, parts[0], float(parts[1]), parts[2]))
        except ValueError as exc:
            raise DatasetUnavailable(f"{path}: expected 'rgb_stamp rgb_file depth_stamp depth_file', got "
                                     f"{stamp} {rest!r}") from exc
    return sorted(out)


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
        raise DatasetUnavailable(f"{path}: cannot read image")
    return img


class TumSequence:
    """Frames of a TUM RGB-D format folder, in stamp order (colour stamp is the frame stamp)."""

    def __init__(self, folder: str | Path, overrides: dict[str, float | None] | None = None,
                 max_frames: int | None = None, resize_to: tuple[int, int] | None = None) -> None:
        self.folder = Path(folder)
        if not self.folder.is_dir():
            raise DatasetUnavailable(f"{self.folder}: not a directory")
        self.params = read_camera_params(self.folder, overrides)
        # (colour stamp, colour file, depth stamp, depth file)
        self._items: list[tuple[float, str, float, str]]
        if (self.folder / "associations.txt").is_file():
            self._items = read_associations(self.folder / "associations.txt")
            if not self._items:
                raise DatasetUnavailable(f"{self.folder / 'associations.txt'}: no pairs")
        else:
            rgb = read_tum_list(self.folder / "rgb.txt")
            depth = read_tum_list(self.folder / "depth.txt")
            pairs = associate([s for s, _ in rgb], [s for s, _ in depth])
            if not pairs:
                raise DatasetUnavailable(f"{self.folder}: no colour/depth pairs within "
                                         f"{MAX_ASSOCIATION_DT_S * 1e3:.0f} ms")
            self._items = [(rgb[i][0], rgb[i][1], depth[j][0], depth[j][1]) for i, j in pairs]
        if max_frames is not None:
            self._items = self._items[:max_frames]
        self.resize_to = resize_to

    def __len__(self) -> int:
        return len(self._items)

    def stamps(self) -> list[float]:
        return [s for s, _, _, _ in self._items]

    def frames(self) -> Iterator[RgbdFrame]:
        p = self.params
        for seq, (stamp, rgb_name, depth_stamp, depth_name) in enumerate(self._items):
            bgr = _read_image(self.folder / rgb_name, cv2.IMREAD_COLOR)
            raw = _read_image(self.folder / depth_name, cv2.IMREAD_UNCHANGED)
            if raw.ndim != 2:
                raise DatasetUnavailable(f"{self.folder / depth_name}: depth must be single-channel 16-bit")
            depth_m: NDArray[Any] = raw.astype(np.float32) / np.float32(p.depth_scale)
            h, w = depth_m.shape
            k = CameraIntrinsics(p.fx, p.fy, p.cx, p.cy, w, h)
            rgb: NDArray[Any] = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
            if self.resize_to is not None and (w, h) != self.resize_to:
                factor = self.resize_to[0] / w
                rgb = cv2.resize(rgb, self.resize_to, interpolation=cv2.INTER_AREA)
                depth_m = cv2.resize(depth_m, self.resize_to, interpolation=cv2.INTER_NEAREST)
                k = k.scaled(factor)
            yield RgbdFrame(seq, stamp, rgb, depth_m, k,
                            meta={"rgb": rgb_name, "depth": depth_name, "depth_stamp_s": depth_stamp})


def read_tum_trajectory(path: str | Path) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``timestamp tx ty tz qx qy qz qw`` file -> (stamps (N,), 4x4 poses (N,4,4))."""
    rows = read_tum_list(Path(path))
    stamps, poses = [], []
    for stamp, rest in rows:
        v = [float(x) for x in rest.split()]
        if len(v) != 7 or not all(math.isfinite(x) for x in v):
            raise DatasetUnavailable(f"{path}: bad trajectory line at stamp {stamp}")
        T = np.eye(4)
        T[:3, :3] = R_from_quat_wxyz([v[6], v[3], v[4], v[5]])  # file is [qx qy qz qw]
        T[:3, 3] = v[:3]
        stamps.append(stamp)
        poses.append(T)
    return np.asarray(stamps), np.asarray(poses)


def write_tum_trajectory(path: str | Path, stamps: list[float] | NDArray[np.float64],
                         poses: list[NDArray[np.float64]] | NDArray[np.float64]) -> None:
    """Write ``timestamp tx ty tz qx qy qz qw`` lines (quaternion x,y,z,w as TUM tools expect)."""
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    for stamp, T in zip(stamps, poses, strict=True):
        w, x, y, z = quat_wxyz_from_R(T[:3, :3])
        t = T[:3, 3]
        lines.append(f"{stamp:.6f} {t[0]:.6f} {t[1]:.6f} {t[2]:.6f} {x:.6f} {y:.6f} {z:.6f} {w:.6f}")
    Path(path).write_text("\n".join(lines) + "\n", encoding="utf-8")

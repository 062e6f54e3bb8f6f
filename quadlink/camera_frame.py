"""An RGB-D frame and its pinhole intrinsics: what every camera source yields and every consumer reads
(the record codec :mod:`quadlink.camera_record`, the stream :mod:`quadlink.camera_stream`, perception)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ["CameraIntrinsics", "RgbdFrame"]


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics in pixels for an image of ``width`` x ``height``."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @classmethod
    def from_fov(cls, width: int, height: int, hfov_deg: float, vfov_deg: float) -> CameraIntrinsics:
        fx = (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
        fy = (height / 2.0) / math.tan(math.radians(vfov_deg) / 2.0)
        return cls(fx, fy, (width - 1) / 2.0, (height - 1) / 2.0, width, height)

    def matrix(self) -> NDArray[np.float64]:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def scaled(self, factor: float) -> CameraIntrinsics:
        """Intrinsics of the image resized by ``factor`` (pyramid levels)."""
        return CameraIntrinsics(self.fx * factor, self.fy * factor, (self.cx + 0.5) * factor - 0.5,
                                (self.cy + 0.5) * factor - 0.5, round(self.width * factor),
                                round(self.height * factor))


@dataclass(frozen=True)
class RgbdFrame:
    """One RGB-D frame. ``depth_m`` is float32 metres with 0 for invalid; ``R_qc`` maps camera to body."""

    seq: int
    stamp_s: float
    rgb: NDArray[np.uint8]
    depth_m: NDArray[np.float32] | None
    intrinsics: CameraIntrinsics
    R_qc: NDArray[np.float64] = field(default_factory=lambda: np.eye(3))
    p_qc_m: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    meta: dict[str, Any] = field(default_factory=dict)   # JSON-ready; see the module doc for who defines it

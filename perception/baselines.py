"""Reference RGB-D odometries for comparison (``quadlink vo-eval --method``, benchmarks).

* :class:`Open3dOdometry` — open3d's tensor ``rgbd_odometry_multi_scale`` with ``Method.Hybrid``
  (photometric + geometric, Park et al. 2017), default criteria (10, 5, 3 iterations).
* :class:`OpenCvOdometry` — OpenCV's ``cv2.Odometry`` of type ``RGB_DEPTH`` (Steinbruecker et al. 2011
  photometric + ICP), default settings.

Both expose the same ``process(...) -> OdometryResult`` as :class:`perception.odometry.RgbdOdometry`; they
ignore the IMU prior.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from perception.odometry import OdometryResult
from quadlink.camera import CameraIntrinsics
from quadlink.errors import QuadlinkError
from quadlink.lie import inv_T


def _to_working(rgb: NDArray[Any], depth_m: NDArray[Any], K: CameraIntrinsics, width: int
                ) -> tuple[NDArray[Any], NDArray[Any], CameraIntrinsics]:
    if rgb.shape[1] <= width:
        return rgb, depth_m, K
    f = width / rgb.shape[1]
    size = (width, round(rgb.shape[0] * f))
    return (cv2.resize(rgb, size, interpolation=cv2.INTER_AREA),
            cv2.resize(depth_m, size, interpolation=cv2.INTER_NEAREST), K.scaled(f))


class Open3dOdometry:
    """open3d tensor multi-scale RGB-D odometry (Hybrid), frame to frame."""

    def __init__(self, working_width_px: int = 320, depth_max_m: float = 6.0) -> None:
        try:
            import open3d as o3d
        except ImportError as exc:
            raise QuadlinkError("the open3d method needs the open3d package") from exc
        self._o3d = o3d
        self.working_width_px = working_width_px
        self.depth_max_m = depth_max_m
        self._ref = None
        self._T = np.eye(4)

    def _rgbd(self, rgb: NDArray[np.uint8], depth_m: NDArray[np.float32]):  # type: ignore[no-untyped-def]
        o3d = self._o3d
        colour = np.ascontiguousarray(rgb.astype(np.float32) / 255.0)
        return o3d.t.geometry.RGBDImage(o3d.t.geometry.Image(colour),
                                        o3d.t.geometry.Image(np.ascontiguousarray(depth_m.astype(np.float32))))

    def process(self, stamp_s: float, rgb: NDArray[np.uint8], depth_m: NDArray[np.float32], K: CameraIntrinsics,
                R_ckm1_ck_prior: NDArray[np.float64] | None = None) -> OdometryResult:
        o3d = self._o3d
        rgb, depth_m, K = _to_working(rgb, depth_m, K, self.working_width_px)
        cur = self._rgbd(rgb, depth_m)
        if self._ref is None:
            self._ref = cur
            return OdometryResult(stamp_s, self._T.copy(), np.eye(4), True, 1.0)
        intr = o3d.core.Tensor(K.matrix(), o3d.core.Dtype.Float64)
        res = o3d.t.pipelines.odometry.rgbd_odometry_multi_scale(
            self._ref, cur, intr, o3d.core.Tensor(np.eye(4)), 1.0, self.depth_max_m,
            method=o3d.t.pipelines.odometry.Method.Hybrid)
        self._ref = cur
        # transformation maps source (k-1) points into target (k): T_ck_ckm1
        T_ck_ckm1 = res.transformation.numpy()
        ok = bool(res.fitness > 0.1 and np.all(np.isfinite(T_ck_ckm1)))
        T_ckm1_ck = inv_T(T_ck_ckm1) if ok else np.eye(4)
        self._T = self._T @ T_ckm1_ck
        return OdometryResult(stamp_s, self._T.copy(), T_ckm1_ck, ok, float(res.fitness))


class OpenCvOdometry:
    """OpenCV ``cv2.Odometry`` RGB_DEPTH, frame to frame."""

    def __init__(self, working_width_px: int = 320) -> None:
        self.working_width_px = working_width_px
        self._odo: cv2.Odometry | None = None
        self._K: CameraIntrinsics | None = None
        self._ref: Any = None
        self._T = np.eye(4)

    def process(self, stamp_s: float, rgb: NDArray[np.uint8], depth_m: NDArray[np.float32], K: CameraIntrinsics,
                R_ckm1_ck_prior: NDArray[np.float64] | None = None) -> OdometryResult:
        rgb, depth_m, K = _to_working(rgb, depth_m, K, self.working_width_px)
        if self._odo is None or self._K != K:
            settings = cv2.OdometrySettings()
            settings.setCameraMatrix(K.matrix().astype(np.float32))
            self._odo = cv2.Odometry(cv2.OdometryType_RGB_DEPTH, settings, cv2.OdometryAlgoType_COMMON)
            self._K = K
        gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
        depth = np.where(depth_m > 0, depth_m, np.nan).astype(np.float32)
        cur = cv2.OdometryFrame(depth=depth, image=gray)
        self._odo.prepareFrame(cur)
        if self._ref is None:
            self._ref = cur
            return OdometryResult(stamp_s, self._T.copy(), np.eye(4), True, 1.0)
        ok, Rt = self._odo.compute(self._ref, cur)
        self._ref = cur
        # Rt * src = dst: maps points of k-1 into k
        T_ck_ckm1 = np.asarray(Rt, dtype=float) if ok else np.eye(4)
        T_ckm1_ck = inv_T(T_ck_ckm1)
        self._T = self._T @ T_ckm1_ck
        return OdometryResult(stamp_s, self._T.copy(), T_ckm1_ck, bool(ok), 1.0 if ok else 0.0)

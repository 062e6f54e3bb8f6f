"""The perception pipeline as the daemon holds it: built on the first camera frame, fed the IMU, never fatal.

The pipeline (:class:`companion.interfaces.Pipeline`) is made by its factory from the first frame (its
intrinsics and camera mount). A later frame with other intrinsics is refused: the camera does not change
mid-flight, so it is hostile input. A pipeline error costs one frame or one IMU sample, counted in
:class:`companion.stats.Stats`, never the loop.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion.guard import ErrorCounter
from companion.interfaces import Pipeline, PipelineFactory
from companion.stats import Stats
from perception.pipeline import PerceptionOutput
from quadlink.camera import RgbdFrame
from quadlink.errors import QuadlinkError

log = logging.getLogger("companion.daemon")


class PerceptionStage:
    """``factory`` builds the pipeline on the first frame; ``stats.pipeline_errors`` and ``errors`` count
    what it refused or failed on."""

    def __init__(self, factory: PipelineFactory, stats: Stats, errors: ErrorCounter) -> None:
        self._factory = factory
        self._stats, self._errors = stats, errors
        self.pipeline: Pipeline | None = None
        self._intrinsics: Any = None

    def on_frame(self, frame: RgbdFrame) -> PerceptionOutput | None:
        """The pipeline's output for ``frame``, or None (refused or failed)."""
        if self.pipeline is None:
            self.pipeline = self._factory(frame)
            self._intrinsics = frame.intrinsics
            log.info("perception started on %dx%d frames", frame.intrinsics.width, frame.intrinsics.height)
        elif frame.intrinsics != self._intrinsics:
            self._stats.pipeline_errors += 1
            self._errors.record("camera frame", ValueError(
                f"frame {frame.seq} is {frame.intrinsics.width}x{frame.intrinsics.height} with other intrinsics "
                "than the stream's first: not processed"))
            return None
        try:
            return self.pipeline.on_frame(frame)
        except (ValueError, ArithmeticError, np.linalg.LinAlgError, QuadlinkError) as exc:
            self._stats.pipeline_errors += 1
            log.warning("perception failed on frame %d: %s", frame.seq, exc)
            return None

    def on_imu(self, stamp_s: float, gyro_q_rad_s: NDArray[np.float64], accel_q_m_s2: NDArray[np.float64]) -> None:
        """One IMU sample (body Q frame), once the pipeline exists (before the first frame it is dropped)."""
        if self.pipeline is None:
            return
        try:
            self.pipeline.on_imu(stamp_s, gyro_q_rad_s, accel_q_m_s2)
        except (ValueError, ArithmeticError, QuadlinkError) as exc:
            self._stats.pipeline_errors += 1
            log.warning("perception rejected an IMU sample: %s", exc)

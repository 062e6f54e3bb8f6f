"""What the companion daemon is given: its links, its perception and where operator images go.

Each is a small protocol so the daemon can be wired to the real thing (pymavlink links, the perception
pipeline, :class:`companion.image_publisher.OperatorImagePublisher`) or to a test's stand-in.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from companion.config import CompanionConfig
from perception.pipeline import PerceptionConfig, PerceptionOutput
from quadlink.camera import RgbdFrame
from quadlink.errors import QuadlinkError
from quadlink.operator_image import OperatorImageMeta


class MavLink(Protocol):
    """What the daemon needs of a pymavlink ``mavfile``."""

    def recv_msg(self) -> Any: ...

    def write(self, buf: bytes) -> Any: ...

    def close(self) -> Any: ...


class Pipeline(Protocol):
    """The perception façade (``perception.pipeline.PerceptionPipeline``)."""

    def on_imu(self, stamp_s: float, gyro_q_rad_s: NDArray[np.float64], accel_q_m_s2: NDArray[np.float64]) -> None: ...

    def on_frame(self, frame: RgbdFrame) -> PerceptionOutput: ...


class ImageSink(Protocol):
    """Where operator images go (:class:`companion.image_publisher.OperatorImagePublisher`): ``publish``
    must never block."""

    @property
    def client_count(self) -> int: ...

    def publish(self, frame: RgbdFrame, meta: OperatorImageMeta) -> None: ...

    def close(self) -> None: ...


PipelineFactory = Callable[[RgbdFrame], Pipeline]


#: cameras whose missing depth is not a structured-light camera's: the hidden floor (perception.hidden_floor) reads
#: a structured-light camera's holes (a dark or specular surface); an active-stereo RealSense, its depth aligned to
#: the colour camera, has holes of its own on the floor (alignment, textureless patches), which read as objects
#: (the RealSense path's push in CI moved 0.3-0.5 m instead of > 0.6 m with it on)
HIDDEN_FLOOR_OFF_FOR = ("realsense://",)


def perception_config(cfg: CompanionConfig, camera: str | None = None) -> PerceptionConfig:
    """The perception configuration the companion's pipeline runs with (``perception_config``, or the defaults),
    for the camera at URL ``camera`` (:func:`for_camera`)."""
    from quadlink.config import load_config

    pcfg = load_config(cfg.perception_config, PerceptionConfig) if cfg.perception_config else PerceptionConfig()
    return for_camera(pcfg, camera)


def for_camera(pcfg: PerceptionConfig, camera: str | None) -> PerceptionConfig:
    """``pcfg`` as it runs for the camera at URL ``camera``: the hidden floor is off for a camera in
    :data:`HIDDEN_FLOOR_OFF_FOR`."""
    import dataclasses

    if camera is not None and camera.startswith(HIDDEN_FLOOR_OFF_FOR) and pcfg.hidden_floor.enabled:
        pcfg = dataclasses.replace(pcfg, hidden_floor=dataclasses.replace(pcfg.hidden_floor, enabled=False))
    return pcfg


def default_pipeline_factory(cfg: CompanionConfig, seed: int = 0, camera: str | None = None) -> PipelineFactory:
    """Builds ``perception.pipeline.PerceptionPipeline`` on the first frame (its intrinsics and mount), with the
    configuration :func:`perception_config` gives for ``camera``."""
    return pipeline_factory(perception_config(cfg, camera), seed)


def pipeline_factory(pcfg: PerceptionConfig, seed: int = 0) -> PipelineFactory:
    """Builds ``perception.pipeline.PerceptionPipeline`` with ``pcfg`` on the first frame (its intrinsics and
    mount)."""
    try:
        from perception.pipeline import PerceptionPipeline
    except ImportError as exc:
        raise QuadlinkError(f"perception pipeline not available ({exc}); the companion needs perception/pipeline.py"
                            ) from exc

    def make(frame: RgbdFrame) -> Pipeline:
        return PerceptionPipeline(pcfg, frame.intrinsics, frame.R_qc, frame.p_qc_m, np.random.default_rng(seed))

    return make

"""The companion's perception is bit-for-bit deterministic: the same frames and IMU samples give byte-identical
outputs, whatever OpenCV's thread count and however long each frame took (the clock only measures).

Two simulated flights must stay identical, so nothing in the pipeline may depend on thread-count-dependent
reductions, unseeded randomness, hash order or the wall clock. (Cross-process and BLAS-thread runs are checked
by hand: see the perception README's determinism note; the unit tier runs no subprocesses.)
"""

from __future__ import annotations

import dataclasses
import hashlib
import itertools
import struct
from collections.abc import Callable, Iterator

import cv2
import numpy as np
import pytest

from companion.config import CompanionConfig
from companion.interfaces import default_pipeline_factory
from perception.pipeline import PerceptionOutput, PerceptionPipeline
from perception.synthetic import SyntheticFlight, qvga_intrinsics, render
from quadlink.camera import RgbdFrame
from quadlink.vehicle import load_vehicle

K = qvga_intrinsics()
FRAME_EVERY = 17      # IMU samples (500 Hz) per frame: ~29.4 Hz, not synchronised with the IMU


Recording = tuple[list[tuple[float, np.ndarray, np.ndarray]], dict[int, RgbdFrame]]


@pytest.fixture(scope="module")
def recording() -> Recording:
    """0.8 s of a pan-scanning flight: noisy 500 Hz IMU and 24 rendered frames."""
    veh = load_vehicle()
    flight = SyntheticFlight(veh.camera.R_qc_matrix, np.asarray(veh.camera.p_qc_m), speed_m_s=0.4, yaw_amp_rad=0.4)
    rng = np.random.default_rng(99)
    imu: list[tuple[float, np.ndarray, np.ndarray]] = []
    frames: dict[int, RgbdFrame] = {}
    for i in range(400):
        t = i / 500
        imu.append((t, flight.gyro(t) + rng.normal(0, 0.01, 3), flight.specific_force(t) + rng.normal(0, 0.1, 3)))
        if i % FRAME_EVERY == 0:
            rgb, depth = render(flight.T_w_c(t), K, supersample=1)
            frames[i] = RgbdFrame(len(frames), t, rgb, depth, K, flight.R_qc, flight.p_qc_m)
    return imu, frames


def _feed(h: hashlib._Hash, v: object) -> None:
    """Every bit of an output (floats by their bytes), except the measured processing time."""
    if v is None or isinstance(v, (bool, int, str)):
        h.update(repr(v).encode())
    elif isinstance(v, float):
        h.update(struct.pack("<d", v))
    elif isinstance(v, np.ndarray):
        h.update(str((v.dtype, v.shape)).encode() + np.ascontiguousarray(v).tobytes())
    elif dataclasses.is_dataclass(v):
        for f in dataclasses.fields(v):
            if f.name != "processing_time_s":
                h.update(f.name.encode())
                _feed(h, getattr(v, f.name))
    else:
        raise TypeError(type(v))


def _digests(outputs: list[PerceptionOutput]) -> list[str]:
    out = []
    for o in outputs:
        h = hashlib.sha256()
        _feed(h, o)
        out.append(h.hexdigest())
    return out


def _fly(rec: Recording, seed: int = 0, clock: Callable[[], float] | None = None) -> list[PerceptionOutput]:
    """The recording through the pipeline the companion builds (its factory, default perception config)."""
    imu, frames = rec
    cfg = CompanionConfig(seed=seed)
    make = default_pipeline_factory(cfg, cfg.seed)    # as companion.cli builds it
    pipe = None
    outs = []
    for i, (t, gyro, accel) in enumerate(imu):
        if pipe is not None:
            pipe.on_imu(t, gyro, accel)
        if i in frames:
            if pipe is None:
                pipe = make(frames[i])
                assert isinstance(pipe, PerceptionPipeline)
                if clock is not None:
                    pipe._clock = clock
                pipe.on_imu(t, gyro, accel)
            outs.append(pipe.on_frame(frames[i]))
    return outs


def _erratic_clock() -> Callable[[], float]:
    """A clock whose frames take from microseconds to seconds: nothing but the statistics may notice."""
    steps: Iterator[float] = itertools.cycle([1e-6, 5.0, 0.0, 0.2, 1e3])
    now = [0.0]

    def clock() -> float:
        now[0] += next(steps)
        return now[0]

    return clock


def test_same_input_gives_byte_identical_outputs_whatever_the_threads_and_timing(recording: Recording) -> None:
    first = _fly(recording)
    assert all(o.odometry_ok for o in first) and any(len(o.obstacle_points_h_m) for o in first)
    threads = cv2.getNumThreads()
    try:
        cv2.setNumThreads(1)
        again = _fly(recording, clock=_erratic_clock())
    finally:
        cv2.setNumThreads(threads)
    assert _digests(again) == _digests(first)
    assert len({o.processing_time_s for o in again}) > 1     # the clock was used, and only measured


def test_outputs_depend_on_the_seed_only_through_the_map(recording: Recording) -> None:
    """The digests see the obstacle map's random copies (the comparison above is not vacuous), and the seed
    touches nothing else."""
    a, b = _fly(recording, seed=0), _fly(recording, seed=1)
    assert _digests(a) != _digests(b)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x.position_m, y.position_m)
        np.testing.assert_array_equal(x.v_h_m_s, y.v_h_m_s)
        np.testing.assert_array_equal(x.obstacle_points_c_m, y.obstacle_points_c_m)
        assert (x.roll_rad, x.pitch_rad, x.yaw_rad, x.odometry_fitness) == (y.roll_rad, y.pitch_rad, y.yaw_rad,
                                                                            y.odometry_fitness)

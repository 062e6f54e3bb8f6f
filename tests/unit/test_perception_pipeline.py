"""The perception façade on a synthetic flight through the textured room (exact truth, noisy IMU)."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
import pytest

from perception.pipeline import PerceptionConfig, PerceptionOutput, PerceptionPipeline
from perception.synthetic import SyntheticFlight, qvga_intrinsics, render
from quadlink.camera import RgbdFrame
from quadlink.config import from_dict
from quadlink.errors import ConfigError
from quadlink.frames import R_from_euler
from quadlink.vehicle import load_vehicle

K = qvga_intrinsics()


@dataclass
class Recording:
    flight: SyntheticFlight
    imu: list[tuple[float, np.ndarray, np.ndarray]]
    frames: dict[int, RgbdFrame]      # keyed by the IMU sample index they follow


@pytest.fixture(scope="module")
def recording() -> Recording:
    """3 s of a pan-scanning flight: noisy 500 Hz IMU (with gyro bias) and ~29.4 Hz frames, rendered once."""
    veh = load_vehicle()
    R_qc, p_qc = veh.camera.R_qc_matrix, np.asarray(veh.camera.p_qc_m)
    flight = SyntheticFlight(R_qc, p_qc, speed_m_s=0.4, yaw_amp_rad=0.4)
    rng = np.random.default_rng(20261123)
    gyro_bias = np.array([0.01, -0.01, 0.005])
    imu, frames = [], {}
    for i in range(int(3.0 * 500) + 1):
        t = i / 500
        imu.append((t, flight.gyro(t) + gyro_bias + rng.normal(0, 0.01, 3),
                    flight.specific_force(t) + rng.normal(0, 0.1, 3)))
        if i % 17 == 0:  # not synchronised with the IMU
            rgb, depth = render(flight.T_w_c(t), K, supersample=1)
            frames[i] = RgbdFrame(len(frames), t, rgb, depth, K)
    return Recording(flight, imu, frames)


def _fly(estimator: str, rec: Recording, until_s: float = 10.0, every_n: int = 1,
         calls: list[float] | None = None, world_tilt: np.ndarray | None = None) -> list[PerceptionOutput]:
    """Fly the recording; ``calls`` collects the stamps the odometry runs at, ``world_tilt`` (4x4) turns the
    odometry's world (its poses ``T_c0_ck`` become ``world_tilt @ T_c0_ck``)."""
    pipe = PerceptionPipeline(PerceptionConfig(estimator=estimator, odometry_every_n_frames=every_n), K,
                              rec.flight.R_qc, rec.flight.p_qc_m, np.random.default_rng(7))
    if calls is not None:
        process = pipe._odometry.process

        def counted(stamp_s: float, *args: object) -> object:
            calls.append(stamp_s)
            res = process(stamp_s, *args)   # type: ignore[arg-type]
            return res if world_tilt is None else dataclasses.replace(res, T_c0_ck=world_tilt @ res.T_c0_ck)

        pipe._odometry.process = counted  # type: ignore[method-assign]
    outs = []
    for i, (t, gyro, accel) in enumerate(rec.imu):
        if t > until_s:
            break
        pipe.on_imu(t, gyro, accel)
        if i in rec.frames:
            outs.append(pipe.on_frame(rec.frames[i]))
    return outs


@pytest.mark.parametrize("estimator", ["filters", "ukf"])
def test_velocity_in_h_tracks_truth_on_a_pan_scanning_flight(estimator: str, recording: Recording) -> None:
    outs, flight = _fly(estimator, recording), recording.flight
    assert all(o.odometry_ok for o in outs)
    errs = np.array([o.v_h_m_s - flight.v_h(o.stamp_s) for o in outs if o.stamp_s > 1.0])
    rmse = np.sqrt(np.mean(errs**2, axis=0))
    assert rmse.max() < 0.05, rmse
    last = outs[-1]
    roll, pitch, yaw = flight.euler(last.stamp_s)
    # the accelerometer cannot tell 0.2 m/s² of sustained acceleration from ~1.2° of tilt, and the gyro bias
    # (0.6° at kp = 1) is still being learned after 3 s: a complementary filter's honest error here
    assert abs(last.roll_rad - roll) < math.radians(2.5)
    assert abs(last.pitch_rad - pitch) < math.radians(2.5)
    assert abs(last.yaw_rad - (yaw - flight.euler(0.0)[2])) < math.radians(2.0)
    truth_p = flight.position(last.stamp_s) - flight.position(0.0)
    assert np.linalg.norm(last.position_m - truth_p) < 0.05
    assert last.estimator == estimator


def test_ukf_velocity_does_not_depend_on_the_tilt_of_the_odometry_world(recording: Recording) -> None:
    """The odometry's world is levelled once, by the first frame's roll and pitch, and its rotation chain drifts:
    its tilt is not gravity's. The UKF takes roll and pitch from the attitude filter (as eq. 13 does) and only
    the heading from the odometry, so tilting the odometry's world by 3 degrees leaves its velocity as it was
    (read as an accelerometer bias, the tilt cost 0.01 m/s RMSE a axis and moved with the yaw)."""
    rmse = {}
    for tilt_deg in (0.0, 3.0, -3.0):
        D = np.eye(4)
        D[:3, :3] = R_from_euler(math.radians(tilt_deg), 0.0, 0.0)
        calls: list[float] = []
        outs = _fly("ukf", recording, calls=calls, world_tilt=D)
        assert len(calls) == len(outs)
        errs = np.array([o.v_h_m_s - recording.flight.v_h(o.stamp_s) for o in outs if o.stamp_s > 1.0])
        rmse[tilt_deg] = np.sqrt(np.mean(errs**2, axis=0))
    assert rmse[0.0].max() < 0.05
    for tilt_deg in (3.0, -3.0):
        assert np.abs(rmse[tilt_deg] - rmse[0.0]).max() < 0.003, rmse


def test_odometry_at_half_the_camera_rate_keeps_the_velocity(recording: Recording) -> None:
    calls: list[float] = []
    outs, flight = _fly("filters", recording, every_n=2, calls=calls), recording.flight
    assert len(calls) == (len(outs) + 1) // 2          # every other frame, the first one included
    assert [o.stamp_s for o in outs[::2]] == calls
    errs = np.array([o.v_h_m_s - flight.v_h(o.stamp_s) for o in outs if o.stamp_s > 1.0])
    assert np.sqrt(np.mean(errs**2, axis=0)).max() < 0.05
    # the skipped frames still get their own obstacle sectors and attitude
    assert all(o.sectors.stamp_s == o.stamp_s for o in outs)
    assert len({round(o.roll_rad, 9) for o in outs}) > len(outs) * 0.9


def test_outputs_obstacles_and_sectors_of_the_room(recording: Recording) -> None:
    outs = _fly("filters", recording, until_s=1.0)
    o = outs[-1]
    assert o.obstacle_points_c_m.ndim == 2 and o.obstacle_points_c_m.shape[1] == 3
    assert o.obstacle_points_c_m.shape[0] > 0 and o.obstacle_points_h_m.shape[0] >= o.obstacle_points_c_m.shape[0]
    assert o.sectors.distances_m.shape == (72,)
    assert o.sectors.increment_deg == 5.0
    known = o.sectors.distances_m[np.isfinite(o.sectors.distances_m)]
    assert known.size > 0
    # walls of the room are 1.2 to 4 m away; everything reported lies within the map radius
    assert np.all(known <= 5.0)
    assert np.isnan(o.sectors.distances_m).sum() > 20          # behind the vehicle: never seen
    assert o.nearest_obstacle_h_m is not None
    assert np.linalg.norm(o.nearest_obstacle_h_m) == pytest.approx(
        np.min(np.linalg.norm(o.obstacle_points_h_m, axis=1)))
    assert o.v_h_cov.shape == (3, 3) and o.processing_time_s > 0.0


def test_obstacle_points_of_an_output_stay_as_they_were_at_that_frame(recording: Recording) -> None:
    """The map particles are handed out without a copy: later frames must not change an earlier output."""
    pipe = PerceptionPipeline(PerceptionConfig(), K, recording.flight.R_qc, recording.flight.p_qc_m,
                              np.random.default_rng(7))
    outs, copies = [], []
    for i, (t, gyro, accel) in enumerate(recording.imu[:400]):
        pipe.on_imu(t, gyro, accel)
        if i in recording.frames:
            outs.append(pipe.on_frame(recording.frames[i]))
            copies.append(outs[-1].obstacle_points_h_m.copy())
    assert len(outs) > 5 and copies[0].shape[0] > 0
    for out, points in zip(outs, copies, strict=True):
        assert np.array_equal(out.obstacle_points_h_m, points)


def test_each_output_counts_the_frames_the_odometry_could_not_align_so_far(recording: Recording) -> None:
    """Two blank frames (a dropout) in a flight: the odometry bridges them on the motion prior, and every output
    carries the counts as they stood at its frame (what the companion reports as ODO_*)."""
    keys = sorted(recording.frames)
    dark = set(keys[30:32])
    frames = {i: (dataclasses.replace(f, rgb=np.zeros_like(f.rgb), depth_m=np.zeros_like(f.depth_m))
                  if i in dark else f)
              for i, f in recording.frames.items()}
    outs = _fly("filters", dataclasses.replace(recording, frames=frames), until_s=1.5)
    bridged = np.cumsum([not o.odometry_ok for o in outs])
    assert bridged[-1] == 2
    assert [o.odometry_counts.fallbacks for o in outs] == bridged.tolist()
    assert all(o.odometry_counts.lost == 0 and o.odometry_counts.rejected_jumps == 0 for o in outs)


def test_bad_inputs_are_rejected_without_crashing() -> None:
    veh = load_vehicle()
    pipe = PerceptionPipeline(PerceptionConfig(), K, veh.camera.R_qc_matrix, np.asarray(veh.camera.p_qc_m),
                              np.random.default_rng(0))
    g = np.array([0.0, 0.0, -9.81])
    pipe.on_imu(0.0, np.zeros(3), g)
    pipe.on_imu(0.002, np.array([np.nan, 0, 0]), g)
    pipe.on_imu(0.004, np.zeros(3), g)
    pipe.on_imu(0.003, np.zeros(3), g)           # out of order
    pipe.on_imu(0.006, np.zeros(2), g)           # wrong shape
    assert pipe.rejected_imu == 3
    rgb = np.zeros((240, 320, 3), np.uint8)
    out = pipe.on_frame(RgbdFrame(0, 0.01, rgb, None, K))
    assert not out.odometry_ok
    assert np.all(np.isfinite(out.v_h_m_s))
    out = pipe.on_frame(RgbdFrame(1, 0.04, rgb, np.zeros((240, 320), np.float32), K))
    assert out.obstacle_points_c_m.shape == (0, 3)
    assert np.all(np.isnan(out.sectors.distances_m))


def test_config_from_yaml_dict_is_validated() -> None:
    cfg = from_dict(PerceptionConfig, {"estimator": "ukf", "odometry": {"iterations": [8, 5, 3]},
                                       "obstacle_map": {"copies": 3}})
    assert cfg.estimator == "ukf" and cfg.odometry.iterations == (8, 5, 3) and cfg.obstacle_map.copies == 3
    with pytest.raises(ConfigError, match="estimator"):
        from_dict(PerceptionConfig, {"estimator": "kalman"})
    with pytest.raises(ConfigError, match="odometry"):
        from_dict(PerceptionConfig, {"odometry": {"levelz": 3}})


def test_shipped_defaults_yaml_equals_the_code_defaults() -> None:
    from pathlib import Path

    from quadlink.config import load_config

    path = Path(__file__).resolve().parents[2] / "perception" / "defaults.yaml"
    assert load_config(path, PerceptionConfig) == PerceptionConfig()

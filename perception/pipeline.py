"""The perception façade the companion drives: IMU samples in at 500 Hz, RGB-D frames in at camera rate,
one :class:`PerceptionOutput` per frame (paper 000 Fig. 4: attitude filter, gyro low-pass, RGB-D odometry,
1€-filtered velocity in H, obstacle sectors and the local obstacle map; or paper 003's UKF for the
velocity).

Pure: time comes from the IMU and frame stamps (simulated time in the SITL), randomness from the injected
generator; ``clock`` only measures the processing time reported in the output.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from perception.floor import FloorConfig, measure_floor
from perception.hidden_floor import HiddenFloorConfig, HiddenFloorConfirm, hidden_floor_points_h
from perception.level import LevelConfig, OdometryLevel
from perception.obstacle_map import ObstacleMap, ObstacleMapConfig, ObstacleSectors
from perception.obstacles import ObstacleConfig, extract_obstacles
from perception.odometry import OdometryConfig, OdometryCounts, RgbdOdometry
from perception.ukf import Ukf, UkfConfig
from perception.velocity import VelocityConfig, VelocityEstimator, body_pose_in_world
from quadlink.attitude import AttitudeConfig, AttitudeFilter, orthonormalise
from quadlink.camera_frame import CameraIntrinsics, RgbdFrame
from quadlink.frames import R_hq, Rz, euler_from_R, euler_yaw_rate_rad_s

log = logging.getLogger(__name__)

#: the floor seen within this long still tells the obstacle summary which particles are floor (the vehicle
#: climbs or descends at most ~0.5 m/s: 0.5 m of error at worst, against the summary's 1 m height band)
FLOOR_FRESH_S = 1.0

__all__ = ["PerceptionConfig", "PerceptionOutput", "PerceptionPipeline", "ObstacleSectors"]


@dataclass(frozen=True)
class PerceptionConfig:
    """All perception parameters; defaults are the paper's choices (YAML: ``configs/perception.yaml``)."""

    estimator: Literal["filters", "ukf"] = "filters"   # eqs. (9)-(13) chain, or paper 003's UKF
    imu_rotation_prior: bool = True                     # gyro rotation between frames as odometry prior
    odometry_every_n_frames: int = 1                    # 2: odometry and velocity at half the camera rate
                                                        # (obstacles and map still every frame)
    odometry: OdometryConfig = field(default_factory=OdometryConfig)
    attitude: AttitudeConfig = field(default_factory=AttitudeConfig)
    velocity: VelocityConfig = field(default_factory=VelocityConfig)
    ukf: UkfConfig = field(default_factory=UkfConfig)
    obstacles: ObstacleConfig = field(default_factory=ObstacleConfig)
    obstacle_map: ObstacleMapConfig = field(default_factory=ObstacleMapConfig)
    floor: FloorConfig = field(default_factory=FloorConfig)   # the height above the floor seen in depth
    hidden_floor: HiddenFloorConfig = field(default_factory=HiddenFloorConfig)  # objects that return nothing
    level: LevelConfig = field(default_factory=LevelConfig)   # the roll and pitch that level the floor's depth


@dataclass(frozen=True)
class PerceptionOutput:
    stamp_s: float
    roll_rad: float
    pitch_rad: float
    yaw_rad: float                          # from VO (world = first frame, levelled, NED-like)
    omega_q_rad_s: NDArray[np.float64]      # filtered gyro (bias-corrected, low-passed)
    v_h_m_s: NDArray[np.float64]            # eq. (13) or UKF
    v_h_cov: NDArray[np.float64]
    position_m: NDArray[np.float64]         # VO position of the body in the local world
    odometry_ok: bool
    odometry_fitness: float
    obstacle_points_c_m: NDArray[np.float64]  # N×3 closest points of this frame's sectors, camera frame
    obstacle_points_h_m: NDArray[np.float64]  # M×3 local map particles in H
    sectors: ObstacleSectors                # 72 × 5° in H about z: inf = free, nan = unknown
    nearest_obstacle_h_m: NDArray[np.float64] | None
    processing_time_s: float
    yaw_rate_rad_s: float = 0.0             # Euler yaw rate from the filtered gyro and roll/pitch
    estimator: str = "filters"
    floor_height_m: float | None = None     # body centre above the floor seen in this frame (perception.floor)
    obstacle_ages_s: NDArray[np.float64] | None = None  # M: seconds since each map particle was measured
    obstacle_open_top: NDArray[np.bool_] | None = None  # M: no ray passed over the particle (ObstacleMap.open_top)
    odometry_counts: OdometryCounts = OdometryCounts()  # the odometry's bridged/held/refused/restarted frames so far


class PerceptionPipeline:
    def __init__(self, config: PerceptionConfig, intrinsics: CameraIntrinsics, R_qc: np.ndarray, p_qc_m: np.ndarray,
                 rng: np.random.Generator, clock: Callable[[], float] = time.perf_counter) -> None:
        self.config = config
        self.intrinsics = intrinsics
        self.R_qc = orthonormalise(np.asarray(R_qc, dtype=float))   # configs carry ~6 decimals
        self.p_qc_m = np.asarray(p_qc_m, dtype=float)
        self._rng = rng
        self._clock = clock
        self._attitude = AttitudeFilter(config.attitude)
        self._odometry = RgbdOdometry(config.odometry)
        self._velocity = VelocityEstimator(self.R_qc, self.p_qc_m, config.velocity)
        self._ukf = Ukf(config.ukf) if config.estimator == "ukf" else None
        self._map = ObstacleMap(config.obstacle_map)
        self._level = OdometryLevel(config.level)
        self._floor_seen: tuple[float, float] | None = None   # (stamp, floor depth below the body) last seen
        self._hidden_confirm = HiddenFloorConfirm()               # objects that return nothing: two frames running
        self._last_imu_stamp: float | None = None
        self._prev_R_wq: NDArray[np.float64] | None = None  # attitude at the previous frame
        self._imu_since_frame = False
        self._R_w_q0: NDArray[np.float64] | None = None
        self._prev_frame_stamp: float | None = None
        self._prev_v_h = np.zeros(3)
        self._prev_yaw_rate = 0.0
        self._odometry_due = 0          # frames until the odometry runs again (0 = this one)
        self._last_odo: tuple[bool, float, NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]] | None = None
        self.frames = 0
        self.imu_samples = 0
        self.rejected_imu = 0

    def on_imu(self, stamp_s: float, gyro_q_rad_s: np.ndarray, accel_q_m_s2: np.ndarray) -> None:
        # scalar Python on the 500 Hz path: numpy on 3-vectors costs more than the arithmetic
        gyro = np.asarray(gyro_q_rad_s, dtype=float)
        accel = np.asarray(accel_q_m_s2, dtype=float)
        if gyro.shape != (3,) or accel.shape != (3,):
            self.rejected_imu += 1
            return
        g, a = gyro.tolist(), accel.tolist()
        if not math.isfinite(sum(g) + sum(a)):      # any nan/inf (or absurd 1e308s) in the sample
            self.rejected_imu += 1
            return
        if self._last_imu_stamp is not None and stamp_s <= self._last_imu_stamp:
            self.rejected_imu += 1       # out of order / duplicate
            return
        self._attitude.update(stamp_s, g, a)
        if self._last_imu_stamp is not None:      # (the first sample only initialises the filter)
            self._imu_since_frame = True
        self._last_imu_stamp = stamp_s
        if self._ukf is not None:
            self._ukf.on_imu(stamp_s, gyro, accel)
        self.imu_samples += 1

    def on_frame(self, frame: RgbdFrame) -> PerceptionOutput:
        t_start = self._clock()
        cfg = self.config
        att = self._attitude.estimate(frame.stamp_s)
        roll, pitch, omega = att.roll_rad, att.pitch_rad, att.omega_q_rad_s
        K = frame.intrinsics
        # with odometry_every_n_frames > 1 the odometry skips frames while it tracks (never after a failure);
        # a skipped frame reuses the last pose and velocity, and the obstacles and map still run
        run_odometry = frame.depth_m is None or self._odometry_due <= 0 or self._last_odo is None \
            or not self._last_odo[0]
        if run_odometry:
            self._odometry_due = max(cfg.odometry_every_n_frames, 1) - 1
            R_prior = None
            if cfg.imu_rotation_prior and self._prev_R_wq is not None and self._imu_since_frame:
                # body rotation since the last odometry frame from the attitude filter (the bias-corrected
                # gyro with its small accelerometer corrections)
                R_q = self._prev_R_wq.T @ att.R_wq
                R_prior = self.R_qc.T @ R_q @ self.R_qc    # camera k-1 -> k rotation
            self._prev_R_wq = att.R_wq
            self._imu_since_frame = False
            if frame.depth_m is not None:
                odo = self._odometry.process(frame.stamp_s, frame.rgb, frame.depth_m, K, R_prior)
                odometry_ok, fitness, T_c0_ck = odo.ok, odo.fitness, odo.T_c0_ck
            else:
                odometry_ok, fitness, T_c0_ck = False, 0.0, self._odometry.T_c0_ck
            if self._R_w_q0 is None:
                self._R_w_q0 = R_hq(roll, pitch)   # world: level, heading of the first frame
            R_wq, p_w = body_pose_in_world(T_c0_ck, self.R_qc, self.p_qc_m, self._R_w_q0)
            # the floor is levelled with the odometry's attitude, its world held to gravity slowly
            # (perception.level): the filter's roll and pitch carry a manoeuvre's acceleration
            level_rp = self._level.update(frame.stamp_s, R_wq, roll, pitch) \
                if odometry_ok and cfg.level.time_constant_s > 0.0 else (roll, pitch)
            vel = self._velocity.update(frame.stamp_s, T_c0_ck, odometry_ok, omega, roll, pitch)
            v_h, v_h_cov = vel.v_h_m_s, vel.v_h_cov
            self._last_odo = (odometry_ok, float(fitness), R_wq, p_w, np.asarray(v_h_cov, dtype=float))
        else:
            self._odometry_due -= 1
            odometry_ok, fitness, R_wq, p_w, v_h_cov = self._last_odo   # type: ignore[misc]
            v_h = self._prev_v_h
            level_rp = (roll, pitch)
        yaw = euler_from_R(R_wq)[2]
        if self._ukf is not None:
            if run_odometry and (odometry_ok or not self._ukf.initialised):
                # attitude measurement: heading from the odometry, roll and pitch from the attitude filter
                # (gravity: drift-free), as the filter chain's eq. (13); the odometry's own tilt drifts, and the
                # UKF would read a tilted world as an accelerometer bias
                self._ukf.on_pose(frame.stamp_s, p_w, Rz(yaw) @ R_hq(roll, pitch))
            st = self._ukf.state        # the UKF runs on the IMU: fresh on every frame
            v_h, v_h_cov = st.v_h_m_s, st.v_h_cov
        yaw_rate = euler_yaw_rate_rad_s(omega, roll, pitch)
        # local obstacle map: time update to this frame (eq. 14), then the measurement
        if self._prev_frame_stamp is not None:
            dt = frame.stamp_s - self._prev_frame_stamp
            if 0.0 < dt < 1.0:
                self._map.predict(dt, self._prev_v_h, v_h, self._prev_yaw_rate, yaw_rate, self._rng)
        self._prev_frame_stamp = frame.stamp_s
        self._prev_v_h, self._prev_yaw_rate = v_h, yaw_rate
        floor = None
        if frame.depth_m is not None:
            floor = measure_floor(frame.depth_m, K, self.R_qc, self.p_qc_m, *level_rp, cfg.floor)
        if floor is not None:
            self._floor_seen = (frame.stamp_s, floor.height_m)
        floor_drop_m = None
        if self._floor_seen is not None and 0.0 <= frame.stamp_s - self._floor_seen[0] <= FLOOR_FRESH_S:
            floor_drop_m = self._floor_seen[1]
        if frame.depth_m is not None:
            obs = extract_obstacles(frame.depth_m, K, self.R_qc, self.p_qc_m, roll, pitch, cfg.obstacles)
            # objects that return nothing (dark, specular), found by the floor they hide (issue 29)
            unseen = self._hidden_confirm.update(hidden_floor_points_h(
                frame.depth_m, K, self.R_qc, self.p_qc_m, *level_rp, floor_drop_m, cfg.obstacles.min_range_m,
                cfg.obstacles.max_range_m, cfg.hidden_floor))
            self._map.measure(frame.stamp_s, obs, self._rng, unseen)
            points_c = obs.points_c_m
        else:
            points_c = np.zeros((0, 3))
        sectors = self._map.sectors(frame.stamp_s, floor_drop_m)
        self.frames += 1
        return PerceptionOutput(
            stamp_s=frame.stamp_s, roll_rad=roll, pitch_rad=pitch, yaw_rad=yaw, omega_q_rad_s=omega,
            v_h_m_s=np.asarray(v_h, dtype=float), v_h_cov=np.asarray(v_h_cov, dtype=float), position_m=p_w,
            odometry_ok=odometry_ok, odometry_fitness=float(fitness), obstacle_points_c_m=points_c,
            obstacle_points_h_m=self._map.points_h_m, sectors=sectors,   # a snapshot: the map never writes it
            nearest_obstacle_h_m=self._map.nearest_h(), processing_time_s=self._clock() - t_start,
            yaw_rate_rad_s=yaw_rate, estimator=cfg.estimator,
            floor_height_m=None if floor is None else floor.height_m, obstacle_ages_s=self._map.ages_s,
            obstacle_open_top=self._map.open_top, odometry_counts=self._odometry.counts)

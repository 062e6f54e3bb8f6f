"""The pipeline's odometry through a take-off in the in-process SITL (pybullet world, firmware, the IMU and RGB-D
camera models with their noise): the producer's own frames and IMU, the vehicle flown on its true state."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from perception.odometry import OdometryConfig
from perception.pipeline import PerceptionConfig, PerceptionPipeline
from perception.velocity import body_pose_in_world
from quadlink.lie import so3_log
from quadlink.vehicle import load_vehicle
from sim_sitl.camera_sim import RgbdCamera
from sim_sitl.config import load_scenario, load_sitl_config
from sim_sitl.firmware import AttitudeCommand
from sim_sitl.vehicle_sim import SimVehicle

TAKEOFF_S = 2.0   # the floor comes into the camera's range (0.5 m) at ~0.9 s; tracked from then on


def _world_tilt_after_takeoff_deg(odometry: OdometryConfig, seed: int) -> float:
    """The angle between the odometry's body attitude and the truth after a vertical take-off (yaw held at 0),
    both from the same start: its local world's tilt, which turns every later horizontal displacement into height."""
    veh = load_vehicle()
    cfg = load_sitl_config()
    sim = SimVehicle(veh, cfg, load_scenario("empty"), np.random.default_rng(seed))
    sim.power_up()
    cam = RgbdCamera(sim.world, veh.camera, cfg.camera_noise, np.random.default_rng(seed + 1))
    pipe = PerceptionPipeline(PerceptionConfig(odometry=odometry), cam.intrinsics, cam.R_qc, np.asarray(cam.p_qc_m),
                              np.random.default_rng(seed + 2))
    frame_every = round(cfg.firmware.loop_rate_hz / veh.camera.rate_hz)
    R_start = None
    try:
        while sim.t_s < TAKEOFF_S:
            res = sim.tick()
            s = res.state
            pipe.on_imu(res.t_s, res.imu.gyro_q_rad_s, res.imu.accel_q_m_s2)
            # climb along a ramp to 1.2 m at 0.37 m/s (as bench_perception --sitl-oval), level
            z_ref_m = -min(0.37 * res.t_s, 1.2)
            a_z = 4.0 * (z_ref_m - s.p_ned_m[2]) - 3.0 * s.v_ned_m_s[2]
            thrust = veh.hover_thrust_fraction * (1.0 - a_z / 9.81)
            sim.on_setpoint(AttitudeCommand(0.0, 0.0, 0.0, float(np.clip(thrust, 0.0, 1.0)), True, res.tick & 0xFF))
            if res.tick % frame_every == 0:
                pipe.on_frame(cam.render(s, res.tick // frame_every, res.t_s))
                if R_start is None:
                    R_start = s.R_ned_q.copy()
        R_est = body_pose_in_world(pipe._odometry.T_c0_ck, pipe.R_qc, pipe.p_qc_m, np.eye(3))[0]
        R_true = R_start.T @ s.R_ned_q   # type: ignore[union-attr]
        assert s.p_ned_m[2] < -0.4, "did not take off"
    finally:
        sim.close()
    return math.degrees(float(np.linalg.norm(so3_log(R_est.T @ R_true))))


@pytest.mark.parametrize("seed", [0, 1])
def test_a_take_off_is_not_tracked_on_a_sliver_of_floor(seed: int) -> None:
    """Climbing through the camera's minimum range, the first frames with depth see a sliver of floor at a grazing
    angle (1 % of the image, 742 points); aligned against such a keyframe, the next frames agreed photometrically
    with a wrong tilt, up to 1 deg a frame while the gyro said the vehicle was not turning, and the odometry's
    world stayed tilted by 2-5 deg (the paper 003 oval read it as +-0.1 m of height). With a reference needing
    ``min_reference_points`` (2000) the take-off is tracked once the floor fills more of the view: the tilt left
    is the attitude filter's own (its gyro bias not yet learnt, ~0.2-0.7 deg), which the prior carries over the
    untracked frames."""
    tilt = _world_tilt_after_takeoff_deg(OdometryConfig(), seed)
    before = _world_tilt_after_takeoff_deg(dataclasses.replace(OdometryConfig(), min_reference_points=100), seed)
    # the board now flies on its own attitude estimate (issue 29), so the take-off itself is not exactly level:
    # measured 0.77/0.78 deg with the gate and 1.84/2.94 deg without it (seeds 0/1; 0.2-0.7 and > 2 on the true
    # attitude); the bound widened from 0.5 deg to 1.0 with them, and the gate must still take off > 1 deg
    assert tilt < 1.0, (tilt, before)
    assert before - tilt > 1.0, (tilt, before)   # the take-off still shows the failure the gate is for

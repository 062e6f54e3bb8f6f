"""The firmware's board core (C, host build) flying sim_sitl's rigid body in closed loop, on its own estimate.

Everything between the wires is the firmware's: it gets the IMU counts that sim_sitl's IMU model produces
(bias, noise, rotor vibration, 10-bit quantisation through ``ImuSample.from_si``) and ``s`` frames over port 1,
and its motor bytes (HARDWARE.md: thrust = byte / 255 x max_thrust_n) drive sim_sitl's motor lag, rotor layout
and a rigid body. No truth reaches the board. Held still for its gyro calibration, armed and released in the air
(a hand launch), it must hold level, follow a 0.2 rad roll step and come back.
"""

from __future__ import annotations

import ctypes
import math

import numpy as np
from firmware_host import CBoard

from quadlink.frames import GRAVITY_M_S2, euler_from_R
from quadlink.mk.messages import AttitudeSetpoint, ImuSample, encode_message
from quadlink.vehicle import load_vehicle
from sim_sitl.board_estimators import baro_count_of_pressure
from sim_sitl.config import ImuNoiseConfig
from sim_sitl.imu import ImuModel
from sim_sitl.motors import body_wrench, motor_lag, rotor_layout

DT_S = 0.002
G_NED = np.array([0.0, 0.0, GRAVITY_M_S2])


def _expm_so3(phi: np.ndarray) -> np.ndarray:
    """Rotation matrix of the rotation vector phi (Rodrigues)."""
    angle = float(np.linalg.norm(phi))
    K = np.array([[0.0, -phi[2], phi[1]], [phi[2], 0.0, -phi[0]], [-phi[1], phi[0], 0.0]])
    if angle < 1e-12:
        return np.eye(3) + K
    return np.eye(3) + math.sin(angle) / angle * K + (1.0 - math.cos(angle)) / angle**2 * (K @ K)


def _valid_image(lib: ctypes.CDLL) -> bytes:
    from firmware_host import blob

    p = blob(lib, "qlh_params_size")
    lib.ql_params_defaults(p)
    out = (ctypes.c_uint8 * ctypes.c_int.in_dll(lib, "qlh_params_image_len").value)()
    lib.ql_params_store(p, out)
    return bytes(out)


def test_the_board_flies_the_rigid_body_on_its_own_estimate(firmware_lib: ctypes.CDLL,
                                                           rng: np.random.Generator) -> None:
    v = load_vehicle("vehicle")
    layout = rotor_layout(v)
    J = np.asarray(v.inertia_kg_m2, dtype=float)
    imu = ImuModel(ImuNoiseConfig(), rng, v.motor.max_thrust_n)
    board = CBoard(firmware_lib, _valid_image(firmware_lib))
    hover = v.hover_thrust_fraction

    R = np.eye(3)
    w = np.zeros(3)
    vel = np.zeros(3)
    pos = np.array([0.0, 0.0, -2.0])  # NED: 2 m up
    a_ned = np.zeros(3)
    thrusts = np.zeros(4)
    release_s, step_on_s, step_off_s, end_s = 0.8, 1.5, 2.0, 3.5
    log: list[tuple[float, float, float, float]] = []
    for k in range(int(end_s / DT_S)):
        t = k * DT_S
        if t >= release_s and k % 5 == 0:  # the companion's setpoints at 100 Hz
            roll_cmd = 0.2 if step_on_s <= t < step_off_s else 0.0
            board.rx(encode_message(AttitudeSetpoint(roll_cmd, 0.0, 0.0, hover, True, seq=k // 5)))
        reading = imu.measure(t, DT_S, R, a_ned, w, thrusts)
        sample = ImuSample.from_si(reading.accel_q_m_s2, reading.gyro_q_rad_s, v.imu, k)
        baro = round(baro_count_of_pressure(101_325.0 + 1.225 * GRAVITY_M_S2 * pos[2]))
        board.tick(accel=sample.accel_counts, gyro=sample.gyro_counts, baro=baro, battery=645)
        state = board.state()
        motor_cmd_n = np.array([state[f"m{i}"] for i in range(1, 5)]) / 255.0 * v.motor.max_thrust_n
        if t < release_s:
            continue  # held still in the hand: calibration, level, disarmed
        thrusts = motor_lag(thrusts, motor_cmd_n, v.motor.time_constant_s, DT_S)
        thrust_n, torque = body_wrench(layout, thrusts)
        w = w + DT_S * (torque - np.cross(w, J * w)) / J
        R = R @ _expm_so3(w * DT_S)
        a_ned = G_NED + R @ np.array([0.0, 0.0, -thrust_n / v.mass_kg])
        vel = vel + DT_S * a_ned
        pos = pos + DT_S * vel
        roll, pitch, yaw = euler_from_R(R)
        log.append((t, roll, pitch, yaw))
        assert state["armed"] == 1 and state["failsafe"] == 0

    arr = np.array(log)
    t, roll, pitch, yaw = arr.T
    before = (t > release_s + 0.3) & (t < step_on_s)
    during = (t > step_on_s + 0.3) & (t < step_off_s)
    after = t > step_off_s + 0.6
    # level after release; the roll step followed (the slow accelerometer gain pulls the in-flight estimate
    # towards level by ~0.04 rad over the 0.5 s step: a feature of accelerometer levelling, stated here)
    assert np.max(np.abs(roll[before])) < 0.05 and np.max(np.abs(pitch[before])) < 0.05
    assert np.all(np.abs(roll[during] - 0.2) < 0.07)
    assert np.max(np.abs(pitch[during])) < 0.05
    assert np.max(np.abs(roll[after])) < 0.05 and np.max(np.abs(pitch[after])) < 0.05
    assert abs(yaw[-1]) < 0.1
    board.close()

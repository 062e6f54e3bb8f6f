"""The firmware's attitude controller and mixer (C fixed point, host build) against sim_sitl's Python model.

Same inputs to both (the filter's integer attitude and rates, as floats for the Python): the C runs in
integers (thrust and torque in 2^-16 N and N m, gains rounded to integer multipliers at init), the Python in
float64. Stated tolerances: motor commands within 10 mN (0.2 % of a motor's 5 N) over hundreds of steps with the
integrators running, the integrators within 0.01 rad/s^2, the mixer within 10 mN including saturation (the
torque scale-down factor is Q8).
"""

from __future__ import annotations

import ctypes

import numpy as np
import pytest
from firmware_host import blob, f32

from quadlink.vehicle import load_vehicle
from sim_sitl.config import FirmwareConfig
from sim_sitl.firmware import AttitudeCommand, BoardSensing, Firmware
from sim_sitl.motors import mix, rotor_layout

PARAM_NAMES = ("angle_kp_1_s", "rate_kp_1_s", "rate_ki_1_s2", "rate_kd", "yaw_rate_kp_1_s", "yaw_rate_ki_1_s2",
               "max_tilt_rad", "max_rate_rad_s", "max_yaw_rate_rad_s", "integrator_limit_rad_s2",
               "setpoint_timeout_s", "landed_thrust_fraction")


@pytest.fixture
def params(firmware_lib: ctypes.CDLL) -> ctypes.Array[ctypes.c_uint8]:
    p = blob(firmware_lib, "qlh_params_size")
    firmware_lib.ql_params_defaults(p)
    return p


def c_params(lib: ctypes.CDLL, p: ctypes.Array[ctypes.c_uint8]) -> list[float]:
    out = (ctypes.c_float * 25)()
    lib.qlh_params_get(p, out)
    return list(out)


def test_defaults_are_sim_sitl_and_vehicle_config(firmware_lib: ctypes.CDLL, params: ctypes.Array) -> None:
    got = c_params(firmware_lib, params)
    cfg = FirmwareConfig()
    for i, name in enumerate(PARAM_NAMES):
        assert got[i] == pytest.approx(getattr(cfg, name), rel=1e-6), name
    v = load_vehicle("vehicle")
    assert got[13] == pytest.approx(cfg.failsafe_ground_speed_m_s, rel=1e-6)
    assert got[14:19] == pytest.approx([v.mass_kg, *v.inertia_kg_m2, v.arm_length_m], rel=1e-6)
    assert got[19] == (1.0 if v.frame == "x" else 0.0)
    assert got[20:23] == pytest.approx([v.motor.max_thrust_n, v.motor.idle_fraction,
                                        v.motor.drag_torque_per_thrust_m], rel=1e-6)
    assert firmware_lib.ql_hover_thrust_fraction(params) == pytest.approx(v.hover_thrust_fraction, rel=1e-6)


def test_mixer_matches_python(firmware_lib: ctypes.CDLL, params: ctypes.Array, rng: np.random.Generator) -> None:
    v = load_vehicle("vehicle")
    layout = rotor_layout(v)
    ctrl = blob(firmware_lib, "qlh_ctrl_size")
    firmware_lib.ql_ctrl_init(ctrl, params)
    lo, hi = v.motor.idle_fraction * v.motor.max_thrust_n, v.motor.max_thrust_n
    saturated = 0
    for _ in range(2000):
        thrust = float(rng.uniform(0.0, 4.0 * hi))
        # up to 4 N m per axis (the firmware's torque range; the motors give at most 1.6 N m in roll)
        torque = np.clip(rng.normal(0.0, [0.3, 0.3, 0.05]) * rng.choice([0.1, 1.0, 4.0]), -3.99, 3.99)
        out = (ctypes.c_float * 4)()
        firmware_lib.qlh_mix(ctrl, thrust, f32(torque), out)
        want = mix(layout, thrust, torque, lo, hi)
        np.testing.assert_allclose(list(out), want, atol=1e-2)
        saturated += int(np.any(np.isclose(want, lo)) or np.any(np.isclose(want, hi)))
    assert saturated > 200  # the saturation branches were exercised


def test_controller_matches_the_python_board_model(firmware_lib: ctypes.CDLL, params: ctypes.Array,
                                                   rng: np.random.Generator) -> None:
    v = load_vehicle("vehicle")
    cfg = FirmwareConfig()
    fw = Firmware(v, cfg)
    ctrl = blob(firmware_lib, "qlh_ctrl_size")
    firmware_lib.ql_ctrl_init(ctrl, params)
    dt = 1.0 / cfg.loop_rate_hz
    att = np.zeros(3)
    rates = np.zeros(3)
    rate_lsb = v.imu.gyro_lsb_rad_s / 256.0  # the filter's rate unit (R)
    worst = 0.0
    for k in range(600):
        t = k * dt
        if k % 50 == 0:  # a new setpoint every 0.1 s
            cmd = AttitudeCommand(float(rng.uniform(-0.5, 0.5)), float(rng.uniform(-0.5, 0.5)),
                                  float(rng.uniform(-2.0, 2.0)), float(rng.uniform(0.3, 0.8)), True, k // 50)
        fw.on_setpoint(cmd, t)
        rates = np.clip(rates + rng.normal(0.0, 0.05, 3), -3.0, 3.0)
        att = np.clip(att + rates * dt, -0.7, 0.7)
        att_q24 = np.rint(att * 2**24).astype(np.int64)  # what the filter hands the loop
        rate_r = np.rint(rates / rate_lsb).astype(np.int64)
        py = fw.step(t, dt, BoardSensing(float(att_q24[0] / 2**24), float(att_q24[1] / 2**24), 0.0,
                                         rate_r * rate_lsb, 0.0))
        out = (ctypes.c_float * 4)()
        firmware_lib.qlh_ctrl_step(ctrl, params, f32([cmd.roll_rad, cmd.pitch_rad, cmd.yaw_rate_rad_s, cmd.thrust]),
                                   0, (ctypes.c_int32 * 2)(*att_q24[:2]), (ctypes.c_int32 * 3)(*rate_r), out)
        worst = max(worst, float(np.max(np.abs(np.array(list(out)) - py.motor_cmd_n))))
        integ = (ctypes.c_float * 3)()
        firmware_lib.qlh_ctrl_integ(ctrl, integ)
        np.testing.assert_allclose(list(integ), fw._integ, atol=1e-2)
    assert worst < 1e-2, f"motor commands differ by up to {worst:.2e} N"


def test_landed_holds_the_integrators_and_extremes_stay_in_range(firmware_lib: ctypes.CDLL,
                                                                  params: ctypes.Array) -> None:
    ctrl = blob(firmware_lib, "qlh_ctrl_size")
    firmware_lib.ql_ctrl_init(ctrl, params)
    out = (ctypes.c_float * 4)()
    integ = (ctypes.c_float * 3)()
    cmd = f32([0.3, 0.0, 1.0, 0.1])
    level, still = (ctypes.c_int32 * 2)(0, 0), (ctypes.c_int32 * 3)(0, 0, 0)
    for _ in range(100):
        firmware_lib.qlh_ctrl_step(ctrl, params, cmd, 1, level, still, out)
    firmware_lib.qlh_ctrl_integ(ctrl, integ)
    assert list(integ) == [0.0, 0.0, 0.0]
    for _ in range(100):
        firmware_lib.qlh_ctrl_step(ctrl, params, cmd, 0, level, still, out)
    firmware_lib.qlh_ctrl_integ(ctrl, integ)
    assert integ[0] > 0.0 and integ[2] > 0.0
    # the loop's inputs are integers (a NaN cannot reach it); the most extreme ones still give motor commands
    # inside [idle, max] and integrators inside their limit
    for sign in (1, -1):
        for _ in range(2000):
            firmware_lib.qlh_ctrl_step(ctrl, params, f32([0.6 * sign, -0.6 * sign, 2.5 * sign, 1.0]), 0,
                                       (ctypes.c_int32 * 2)(-sign * 52707178, sign * 26353589),
                                       (ctypes.c_int32 * 3)(-sign * 261888, sign * 261888, -sign * 261888), out)
            assert all(0.4 - 1e-4 <= m <= 5.0 + 1e-4 for m in out)
        firmware_lib.qlh_ctrl_integ(ctrl, integ)
        assert max(abs(i) for i in integ) == pytest.approx(20.0, abs=1e-3)


def test_motor_byte(firmware_lib: ctypes.CDLL, params: ctypes.Array) -> None:
    ctrl = blob(firmware_lib, "qlh_ctrl_size")
    firmware_lib.ql_ctrl_init(ctrl, params)
    assert firmware_lib.qlh_motor_byte(ctrl, 0.0) == 1  # armed motors never read as stopped
    assert firmware_lib.qlh_motor_byte(ctrl, 0.4) == 20  # idle: 0.08 x 255 = 20.4
    assert firmware_lib.qlh_motor_byte(ctrl, 2.5) == 128
    assert firmware_lib.qlh_motor_byte(ctrl, 5.0) == 255
    assert firmware_lib.qlh_motor_byte(ctrl, 7.0) == 255

"""The firmware's attitude controller and mixer (C float, host build) against sim_sitl's Python board model.

Same inputs to both: the C runs in float32 with the gains folded with the inertia at init, the Python in
float64, so motor commands agree within 2 mN (0.04 % of a motor's 5 N) over hundreds of steps with the
integrators running, and the mixer within 0.1 mN including saturation.
"""

from __future__ import annotations

import ctypes
import math

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
        torque = rng.normal(0.0, [0.3, 0.3, 0.05]) * rng.choice([0.1, 1.0, 4.0])
        out = (ctypes.c_float * 4)()
        firmware_lib.ql_mix(ctrl, thrust, f32(torque), lo, hi, out)
        want = mix(layout, thrust, torque, lo, hi)
        np.testing.assert_allclose(list(out), want, atol=1e-4)
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
    worst = 0.0
    for k in range(600):
        t = k * dt
        if k % 50 == 0:  # a new setpoint every 0.1 s
            cmd = AttitudeCommand(float(rng.uniform(-0.5, 0.5)), float(rng.uniform(-0.5, 0.5)),
                                  float(rng.uniform(-2.0, 2.0)), float(rng.uniform(0.3, 0.8)), True, k // 50)
        fw.on_setpoint(cmd, t)
        rates = np.clip(rates + rng.normal(0.0, 0.05, 3), -3.0, 3.0)
        att = np.clip(att + rates * dt, -0.7, 0.7)
        py = fw.step(t, dt, BoardSensing(float(att[0]), float(att[1]), float(att[2]), rates.copy(), 0.0))
        out = (ctypes.c_float * 4)()
        firmware_lib.qlh_ctrl_step(ctrl, params, f32([cmd.roll_rad, cmd.pitch_rad, cmd.yaw_rate_rad_s, cmd.thrust]),
                                   0, f32(att[:2]), f32(rates), dt, out)
        worst = max(worst, float(np.max(np.abs(np.array(list(out)) - py.motor_cmd_n))))
        integ = (ctypes.c_float * 3)()
        firmware_lib.qlh_ctrl_integ(ctrl, integ)
        np.testing.assert_allclose(np.array(list(integ)) / np.asarray(v.inertia_kg_m2), fw._integ, atol=2e-3)
    assert worst < 2e-3, f"motor commands differ by up to {worst:.2e} N"


def test_landed_holds_the_integrators_and_nan_is_never_flown(firmware_lib: ctypes.CDLL,
                                                             params: ctypes.Array) -> None:
    ctrl = blob(firmware_lib, "qlh_ctrl_size")
    firmware_lib.ql_ctrl_init(ctrl, params)
    out = (ctypes.c_float * 4)()
    integ = (ctypes.c_float * 3)()
    cmd = f32([0.3, 0.0, 1.0, 0.1])
    for _ in range(100):
        firmware_lib.qlh_ctrl_step(ctrl, params, cmd, 1, f32([0.0, 0.0]), f32([0.0, 0.0, 0.0]), 0.002, out)
    firmware_lib.qlh_ctrl_integ(ctrl, integ)
    assert list(integ) == [0.0, 0.0, 0.0]
    for _ in range(100):
        firmware_lib.qlh_ctrl_step(ctrl, params, cmd, 0, f32([0.0, 0.0]), f32([0.0, 0.0, 0.0]), 0.002, out)
    firmware_lib.qlh_ctrl_integ(ctrl, integ)
    assert integ[0] > 0.0 and integ[2] > 0.0
    firmware_lib.qlh_ctrl_step(ctrl, params, f32([0.0, 0.0, 0.0, 0.5]), 0, f32([math.nan, 0.0]),
                               f32([0.0, math.nan, 0.0]), 0.002, out)
    assert all(math.isfinite(m) for m in out)
    assert list(out) == pytest.approx([0.5 * 20.0 / 4] * 4)  # torque dropped, collective kept
    firmware_lib.qlh_ctrl_integ(ctrl, integ)
    assert list(integ) == [0.0, 0.0, 0.0]
    firmware_lib.qlh_ctrl_step(ctrl, params, f32([0.0, 0.0, 0.0, math.nan]), 0, f32([0.0, 0.0]),
                               f32([0.0, 0.0, 0.0]), 0.002, out)
    assert list(out) == pytest.approx([0.4] * 4)  # NaN thrust -> idle (0.08 x 5 N)


def test_motor_byte(firmware_lib: ctypes.CDLL) -> None:
    per_n = 255.0 / 5.0
    assert firmware_lib.ql_motor_byte(0.0, per_n) == 1  # armed motors never read as stopped
    assert firmware_lib.ql_motor_byte(0.4, per_n) == 20  # idle: 0.08 x 255 = 20.4
    assert firmware_lib.ql_motor_byte(2.5, per_n) == 128
    assert firmware_lib.ql_motor_byte(5.0, per_n) == 255
    assert firmware_lib.ql_motor_byte(7.0, per_n) == 255
    assert firmware_lib.ql_motor_byte(math.nan, per_n) == 1

"""The firmware's arming and failsafe state machine (C, host build), tick by tick at 500 Hz.

Timeout while flying -> level descent held on the baro climb rate -> touchdown (still for 0.5 s after at least
1 s of failsafe) -> motor cut; timeout while not flying -> cut at once; a setpoint ends a failsafe; clearing
the armed flag cuts at once.
"""

from __future__ import annotations

import ctypes

import pytest
from firmware_host import blob

from quadlink.mk.flags import BoardError, BoardFlightState
from quadlink.vehicle import load_vehicle

HZ = 500
TIMEOUT_TICKS = HZ // 2  # setpoint_timeout_s = 0.5


class Safety:
    def __init__(self, lib: ctypes.CDLL) -> None:
        self.lib = lib
        self.params = blob(lib, "qlh_params_size")
        lib.ql_params_defaults(self.params)
        self.s = blob(lib, "qlh_safety_size")
        lib.ql_safety_init(self.s, self.params)
        self.fly = (ctypes.c_float * 4)()

    def setpoint(self, tick: int, thrust: float, armed: bool = True, roll_cdeg: int = 0, seq: int = 0) -> int:
        return self.lib.qlh_safety_on_setpoint(self.s, self.params, roll_cdeg, 0, 0, round(thrust * 65535),
                                               int(armed), seq, tick)

    def step(self, tick: int, climb: float = 0.0, valid: bool = True, acc1g: bool = True) -> bool:
        return bool(self.lib.qlh_safety_step(self.s, self.params, tick, climb, int(valid), int(acc1g), self.fly))

    def state(self) -> dict[str, int]:
        out = (ctypes.c_int32 * 4)()
        self.lib.qlh_safety_state(self.s, out)
        return dict(zip(("armed", "failsafe", "flight_state", "error_flags"), out, strict=True))


@pytest.fixture
def safety(firmware_lib: ctypes.CDLL) -> Safety:
    return Safety(firmware_lib)


def fly_to(safety: Safety, until: int, thrust: float = 0.6) -> None:
    for tick in range(until):
        safety.setpoint(tick, thrust, seq=tick & 0xFF)
        assert safety.step(tick)


def test_arming_follows_the_flag_and_a_clear_cuts_at_once(safety: Safety) -> None:
    assert not safety.step(0)
    assert safety.setpoint(1, 0.6) == 1  # arming edge reported once
    assert safety.setpoint(2, 0.6) == 0
    assert safety.step(2) and safety.state()["flight_state"] == BoardFlightState.FLYING
    assert safety.fly[3] == pytest.approx(0.6, abs=1e-4)
    safety.setpoint(3, 0.6, armed=False)
    assert not safety.step(3)
    assert safety.state() == {"armed": 0, "failsafe": 0, "flight_state": BoardFlightState.LANDED, "error_flags": 0}


def test_setpoints_are_clamped_to_the_board_limits(safety: Safety) -> None:
    safety.setpoint(0, 1.0, roll_cdeg=9000)  # 90 deg asked, 0.6 rad flown
    safety.step(0)
    assert safety.fly[0] == pytest.approx(0.6, abs=1e-6)


def test_timeout_while_not_flying_cuts_at_once(safety: Safety) -> None:
    fly_to(safety, 100, thrust=0.1)  # armed, idling on the ground (below the 0.15 landed threshold)
    assert safety.state()["flight_state"] == BoardFlightState.LANDED
    for tick in range(100, 100 + TIMEOUT_TICKS):
        assert safety.step(tick)
    assert not safety.step(100 + TIMEOUT_TICKS)  # 0.5 s + one tick after the last setpoint
    st = safety.state()
    assert st["armed"] == 0 and st["failsafe"] == 0 and st["error_flags"] & BoardError.SETPOINT_TIMEOUT


def test_timeout_in_flight_descends_then_cuts_on_touchdown(safety: Safety, firmware_lib: ctypes.CDLL) -> None:
    fly_to(safety, 1000)
    hover = firmware_lib.ql_hover_thrust_fraction(safety.params)
    tick = 1000
    while safety.state()["failsafe"] == 0:
        assert safety.step(tick)
        tick += 1
    assert tick - 1000 == TIMEOUT_TICKS + 1
    st = safety.state()
    assert st["flight_state"] == BoardFlightState.FAILSAFE_DESCEND and st["error_flags"] & BoardError.SETPOINT_TIMEOUT
    # level, zero yaw rate, thrust held on the climb rate: hover at the 0.5 m/s target, more when sinking faster
    assert safety.step(tick, climb=-0.5)
    assert list(safety.fly[:3]) == [0.0, 0.0, 0.0]
    assert safety.fly[3] == pytest.approx(hover, rel=1e-5)
    assert safety.step(tick, climb=-1.5) and safety.fly[3] == pytest.approx(hover * 1.1, rel=1e-5)  # capped
    assert safety.step(tick, climb=0.0) and safety.fly[3] == pytest.approx(hover * 0.85, rel=1e-5)
    # descending for 3 s: never cut while the baro says it is moving
    for _ in range(3 * HZ):
        assert safety.step(tick, climb=-0.5)
        tick += 1
    # on the ground: still for 0.5 s -> cut
    landed_at = tick
    while safety.step(tick, climb=0.02):
        tick += 1
    assert tick - landed_at == 251
    assert safety.state()["armed"] == 0 and safety.state()["flight_state"] == BoardFlightState.LANDED


def test_touchdown_needs_the_accelerometer_and_one_second(safety: Safety) -> None:
    fly_to(safety, 10)
    tick = 10
    while safety.state()["failsafe"] == 0:
        safety.step(tick)
        tick += 1
    start = tick
    for _ in range(2 * HZ):  # baro still but the accelerometer is not at 1 g (falling): no cut
        assert safety.step(tick, climb=0.0, acc1g=False)
        tick += 1
    while safety.step(tick, climb=0.0):
        tick += 1
    assert tick - start >= 2 * HZ + 250
    # without the baro (invalid), the accelerometer alone decides, no earlier than 1 s into the failsafe
    s2 = Safety(safety.lib)
    fly_to(s2, 10)
    tick = 10
    while s2.state()["failsafe"] == 0:
        s2.step(tick)
        tick += 1
    start = tick
    while s2.step(tick, climb=-3.0, valid=False):
        tick += 1
    assert tick - (start - 1) == 500 + 251  # the failsafe began on the tick before `start`


def test_a_setpoint_ends_the_failsafe(safety: Safety) -> None:
    fly_to(safety, 500)
    tick = 500
    while safety.state()["failsafe"] == 0:
        safety.step(tick)
        tick += 1
    for _ in range(100):
        assert safety.step(tick, climb=-0.5)
        tick += 1
    safety.setpoint(tick, 0.55, seq=42)
    assert safety.step(tick, climb=-0.5)
    st = safety.state()
    assert st["failsafe"] == 0 and st["flight_state"] == BoardFlightState.FLYING
    assert not st["error_flags"] & BoardError.SETPOINT_TIMEOUT
    assert safety.fly[3] == pytest.approx(0.55, abs=1e-4)


def test_hover_fraction_is_the_vehicle_s(safety: Safety, firmware_lib: ctypes.CDLL) -> None:
    assert firmware_lib.ql_hover_thrust_fraction(safety.params) == pytest.approx(
        load_vehicle("vehicle").hover_thrust_fraction, rel=1e-6)

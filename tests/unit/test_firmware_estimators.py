"""The firmware's attitude filter and baro estimator (C, host build) against their Python mirror and the physics.

* The mirror (``sim_sitl/board_estimators.py``) must equal the C bit for bit: random count streams go to both
  and every integer state is compared after every tick.
* The filter converges to a tilt from still counts, tracks simulated rotations (within 0.01-0.02 rad) and
  handles gyro zero offsets; the baro follows HARDWARE.md's amplifier law and a 0.5 m/s descent.
"""

from __future__ import annotations

import ctypes
import math

import numpy as np
import pytest
from firmware_host import blob, u16

from quadlink.vehicle import load_vehicle
from sim_sitl import board_estimators as be


class CAttitude:
    def __init__(self, lib: ctypes.CDLL) -> None:
        self.lib = lib
        self.state = blob(lib, "qlh_att_size")
        lib.ql_attitude_init(self.state)

    def update(self, accel: list[int], gyro: list[int], armed: bool, flying: bool) -> list[int]:
        self.lib.ql_attitude_update(self.state, u16(accel), u16(gyro), int(armed), int(flying))
        out = (ctypes.c_int32 * 11)()
        self.lib.qlh_att_get(self.state, out)
        return list(out)


class CBaro:
    def __init__(self, lib: ctypes.CDLL) -> None:
        self.lib = lib
        self.state = blob(lib, "qlh_baro_size")
        lib.ql_baro_init(self.state)

    def update(self, counts: list[int], armed: bool) -> list[int]:
        self.lib.ql_baro_update(self.state, u16(counts), int(armed))
        out = (ctypes.c_int32 * 9)()
        self.lib.qlh_baro_get(self.state, out)
        return list(out)


def mirror_att_state(f: be.BoardAttitudeFilter) -> list[int]:
    return [f.roll_q24, f.pitch_q24, f.yaw_q24, *f.rate_q8, *f.bias_q16, int(f.calibrated), int(f.saturated)]


def mirror_baro_state(b: be.BoardBaro) -> list[int]:
    return [b.p16, b.pf16, b.pref_q12, b.h_q8, b.v_t16, int(b.valid), int(b.saturated), b.altitude_cm, b.climb_cm_s]


def test_mirror_constants_match_the_c(firmware_lib: ctypes.CDLL) -> None:
    imu = load_vehicle("vehicle").imu
    assert ctypes.c_double.in_dll(firmware_lib, "qlh_gyro_lsb_rad_s").value == pytest.approx(be.GYRO_LSB_RAD_S,
                                                                                             rel=1e-6)
    assert be.GYRO_LSB_RAD_S == pytest.approx(imu.gyro_lsb_rad_s, rel=1e-6)
    assert ctypes.c_int.in_dll(firmware_lib, "qlh_imu_zero_count").value == be.IMU_ZERO_COUNT == imu.zero_count
    assert ctypes.c_int.in_dll(firmware_lib, "qlh_att_cal_ticks").value == be.ATT_CAL_TICKS
    assert ctypes.c_int.in_dll(firmware_lib, "qlh_baro_oversample").value == be.BARO_OVERSAMPLE


def test_fixed_point_helpers_equal_and_accurate(firmware_lib: ctypes.CDLL, rng: np.random.Generator) -> None:
    for a in rng.integers(-4 * be.PI_Q24, 4 * be.PI_Q24, 2000):
        a = int(a)
        assert firmware_lib.ql_sin_q12(a) == be.sin_q12(a)
        assert firmware_lib.ql_cos_q12(a) == be.cos_q12(a)
        assert abs(be.sin_q12(a) / 4096 - math.sin(a / be.Q24_ONE)) < 2e-3
    for y, x in rng.integers(-1100, 1100, (2000, 2)):
        y, x = int(y), int(x)
        assert firmware_lib.ql_atan2_q24(y, x) == be.atan2_q24(y, x)
        if x or y:
            err = be.atan2_q24(y, x) / be.Q24_ONE - math.atan2(y, x)
            assert abs((err + math.pi) % (2 * math.pi) - math.pi) < 2e-3
    for n in rng.integers(0, 2**31, 500):
        assert firmware_lib.ql_isqrt32(int(n)) == math.isqrt(int(n))


def _random_imu_stream(rng: np.random.Generator, n: int) -> list[tuple[list[int], list[int], bool, bool]]:
    """Counts that wander over the whole ADC range (rails included), with bursts of stillness, arm and flight
    toggles."""
    ticks = []
    accel = np.array([512.0, 512.0, 256.0])
    gyro = np.array([512.0, 512.0, 512.0])
    armed = flying = False
    for k in range(n):
        if rng.random() < 0.02:
            armed = not armed
        if rng.random() < 0.02:
            flying = not flying
        if k % 700 < 350:  # still: small noise around a level board
            a = accel + rng.normal(0, 1.5, 3)
            g = gyro + rng.normal(0, 1.0, 3)
        else:  # manoeuvring, sometimes to the rails
            a = rng.normal([512, 512, 300], [150, 150, 200])
            g = rng.normal(512, 180, 3)
        ticks.append(([int(c) for c in np.clip(np.rint(a), 0, 1023)],
                      [int(c) for c in np.clip(np.rint(g), 0, 1023)], armed, armed and flying))
    return ticks


def test_attitude_mirror_is_bit_exact(firmware_lib: ctypes.CDLL, rng: np.random.Generator) -> None:
    c = CAttitude(firmware_lib)
    py = be.BoardAttitudeFilter()
    for k, (accel, gyro, armed, flying) in enumerate(_random_imu_stream(rng, 4000)):
        c_state = c.update(accel, gyro, armed, flying)
        py.update(accel, gyro, armed, flying)
        assert c_state == mirror_att_state(py), f"tick {k}: C {c_state} != mirror {mirror_att_state(py)}"


def test_baro_mirror_is_bit_exact(firmware_lib: ctypes.CDLL, rng: np.random.Generator) -> None:
    c = CBaro(firmware_lib)
    py = be.BoardBaro()
    level = 600.0
    armed = False
    for k in range(4000):
        if rng.random() < 0.01:
            armed = not armed
        level = float(np.clip(level + rng.normal(0, 3), -50, 1100))
        counts = [int(v) for v in np.clip(np.rint(level + rng.normal(0, 2, 8)), 0, 1023)]
        c_state = c.update(counts, armed)
        py.update(counts, armed)
        assert c_state == mirror_baro_state(py), f"tick {k}: C {c_state} != mirror {mirror_baro_state(py)}"


# --- the filter against the physics ----------------------------------------------------------------------------

G = 9.80665
IMU = load_vehicle("vehicle").imu


def accel_counts(roll: float, pitch: float, a_g: float = 1.0) -> list[int]:
    """Specific force of a still body at (roll, pitch), FRD, as rounded ADC counts."""
    f = np.array([math.sin(pitch), -math.sin(roll) * math.cos(pitch), -math.cos(roll) * math.cos(pitch)]) * G * a_g
    return [int(np.clip(round(v / IMU.accel_lsb_m_s2) + 512, 0, 1023)) for v in f]


def gyro_counts(rates: np.ndarray, offset: tuple[int, int, int] = (0, 0, 0)) -> list[int]:
    return [int(round(r / IMU.gyro_lsb_rad_s)) + 512 + o for r, o in zip(rates, offset, strict=True)]


def calibrate(f: be.BoardAttitudeFilter, accel: list[int], gyro: list[int]) -> None:
    for _ in range(be.ATT_CAL_TICKS):
        f.update(accel, gyro)
    assert f.calibrated


def test_converges_to_a_tilt_from_still_counts() -> None:
    roll, pitch = 0.3, -0.2
    f = be.BoardAttitudeFilter()
    acc = accel_counts(roll, pitch)
    calibrate(f, acc, [512, 512, 512])
    for _ in range(1000):  # 2 s still, disarmed
        est = f.update(acc, [512, 512, 512])
    # one accelerometer count is 0.0039 g: 0.22 deg of tilt resolution near level
    assert est.roll_rad == pytest.approx(roll, abs=math.radians(0.5))
    assert est.pitch_rad == pytest.approx(pitch, abs=math.radians(0.5))
    assert est.yaw_rad == pytest.approx(0.0, abs=1e-6)
    # a wrong start (set level) converges too, fast while disarmed
    f.roll_q24 = f.pitch_q24 = 0
    for _ in range(250):
        est = f.update(acc, [512, 512, 512])
    assert est.roll_rad == pytest.approx(roll, abs=math.radians(0.5))
    assert est.pitch_rad == pytest.approx(pitch, abs=math.radians(0.5))


def _fly(f: be.BoardAttitudeFilter, euler0: tuple[float, float, float], euler_rates: tuple[float, float, float],
         seconds: float, armed: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Rotate with constant ZYX Euler rates; feed the body rates and gravity as counts. Returns truth, estimate."""
    dt = 1.0 / be.LOOP_HZ
    phi, theta, psi = euler0
    dphi, dtheta, dpsi = euler_rates
    for _ in range(int(seconds * be.LOOP_HZ)):
        mid_phi, mid_theta = phi + 0.5 * dt * dphi, theta + 0.5 * dt * dtheta
        # body rates from Euler rates (the inverse of the kinematics the filter integrates)
        p = dphi - math.sin(mid_theta) * dpsi
        q = math.cos(mid_phi) * dtheta + math.sin(mid_phi) * math.cos(mid_theta) * dpsi
        r = -math.sin(mid_phi) * dtheta + math.cos(mid_phi) * math.cos(mid_theta) * dpsi
        phi, theta, psi = phi + dt * dphi, theta + dt * dtheta, psi + dt * dpsi
        est = f.update(accel_counts(phi, theta), gyro_counts(np.array([p, q, r])), armed, flying=armed)
    wrap = (psi + math.pi) % (2 * math.pi) - math.pi
    return np.array([phi, theta, wrap]), np.array([est.roll_rad, est.pitch_rad, est.yaw_rad])


@pytest.mark.parametrize("rates", [(1.0, 0.0, 0.0), (0.0, -0.8, 0.0), (0.0, 0.0, 1.5), (0.6, 0.4, 0.0)])
def test_tracks_a_simulated_rotation_from_level(rates: tuple[float, float, float]) -> None:
    f = be.BoardAttitudeFilter()
    calibrate(f, accel_counts(0.0, 0.0), [512, 512, 512])
    truth, est = _fly(f, (0.0, 0.0, 0.0), rates, 0.5)
    # gyro quantisation (0.01 rad/s per count) over 0.5 s and the Q12 trigonometry: within 0.01 rad
    np.testing.assert_allclose(est, truth, atol=0.01)


def test_yaw_while_tilted_keeps_the_tilt() -> None:
    """A pure heading change at 0.3 rad pitch and 0.2 rad roll: all three body rates turn; the Euler kinematics
    must turn them back into a constant tilt and a heading rate."""
    f = be.BoardAttitudeFilter()
    calibrate(f, accel_counts(0.2, 0.3), [512, 512, 512])
    for _ in range(500):
        f.update(accel_counts(0.2, 0.3), [512, 512, 512])
    truth, est = _fly(f, (0.2, 0.3, 0.0), (0.0, 0.0, 1.0), 2.0)
    np.testing.assert_allclose(est[:2], truth[:2], atol=0.02)
    assert abs((est[2] - truth[2] + math.pi) % (2 * math.pi) - math.pi) < 0.03


def test_gyro_offsets_are_removed_at_power_up_and_tracked_while_still() -> None:
    offset = (7, -5, 3)  # counts: 0.07 rad/s of bias on x
    f = be.BoardAttitudeFilter()
    acc = accel_counts(0.0, 0.0)
    calibrate(f, acc, gyro_counts(np.zeros(3), offset))
    for _ in range(10 * be.LOOP_HZ):  # 10 s still, armed (slow accelerometer): no drift from the offsets
        est = f.update(acc, gyro_counts(np.zeros(3), offset), armed=True, flying=True)
    assert max(abs(est.roll_rad), abs(est.pitch_rad)) < math.radians(0.5)
    assert abs(est.yaw_rad) < math.radians(1.0)
    assert max(abs(r) for r in est.rates_q_rad_s) < IMU.gyro_lsb_rad_s
    # the offset moves by 2 counts (warm-up): tracked while disarmed and still, frozen while armed
    moved = (offset[0] + 2, offset[1], offset[2])
    for _ in range(3 * be.LOOP_HZ):
        f.update(acc, gyro_counts(np.zeros(3), moved), armed=True)
    assert f.bias_q16[0] == pytest.approx((512 + offset[0]) * 65536, abs=65536 // 4)
    for _ in range(5 * be.LOOP_HZ):
        est = f.update(acc, gyro_counts(np.zeros(3), moved), armed=False)
    assert f.bias_q16[0] == pytest.approx((512 + moved[0]) * 65536, abs=65536 // 8)
    assert abs(est.rates_q_rad_s[0]) < IMU.gyro_lsb_rad_s / 4


# --- baro -------------------------------------------------------------------------------------------------------

def test_pressure_follows_the_hardware_law(firmware_lib: ctypes.CDLL) -> None:
    """HARDWARE.md: V_sensor = 5 (0.009 P_kPa - 0.095), V_adc = 2.5 + 10 (V_sensor - 4.05), count = V_adc/5*1024."""
    for count in (1, 100, 383, 512, 700, 1022):
        b = be.BoardBaro()
        for _ in range(400):
            est = b.update([count] * 8)
        law_pa = 1000.0 * ((4.05 + (count * 5.0 / 1024.0 - 2.5) / 10.0) / 5.0 + 0.095) / 0.009
        assert est.pressure_pa == pytest.approx(law_pa, abs=1.0)
        assert be.baro_count_of_pressure(law_pa) == pytest.approx(count, abs=1e-9)
        c = CBaro(firmware_lib)
        for _ in range(400):
            c.update([count] * 8, False)
        assert firmware_lib.ql_baro_pressure_pa(c.state) == est.pressure_pa


def test_baro_follows_a_descent_and_retakes_its_reference_at_arming(rng: np.random.Generator) -> None:
    b = be.BoardBaro()
    p0 = 101_325.0
    rho_g = 1.225 * G

    def counts(alt_m: float) -> list[int]:
        c = be.baro_count_of_pressure(p0 - rho_g * alt_m)
        return [int(v) for v in np.clip(np.rint(c + rng.normal(0.0, 0.7, 8)), 0, 1023)]  # sensor noise dithers

    for _ in range(1000):
        est = b.update(counts(0.0))
    assert est.valid and abs(est.altitude_m) < 0.5
    b.update(counts(3.0), armed=True)  # armed at 3 m (a hand launch): the reference stays the ground's
    alt = 3.0
    climbs = []
    for k in range(6 * be.LOOP_HZ):  # 6 s descending at 0.5 m/s
        alt -= 0.5 / be.LOOP_HZ
        est = b.update(counts(alt), armed=True)
        if k > 2 * be.LOOP_HZ:
            climbs.append(est.climb_m_s)
            assert est.altitude_m == pytest.approx(alt, abs=1.2)
    assert np.mean(climbs) == pytest.approx(-0.5, abs=0.1)
    assert np.max(np.abs(np.array(climbs) + 0.5)) < 0.45


def test_baro_reference_is_the_disarmed_average() -> None:
    b = be.BoardBaro()
    for _ in range(600):
        b.update([500] * 8)
    for _ in range(2500):  # carried 18 m up while disarmed: the reference (tau 0.5 s) follows
        est = b.update([480] * 8)
    assert abs(est.altitude_m) < 0.1 and abs(est.climb_m_s) < 0.05
    b.update([480] * 8, armed=True)
    for _ in range(1500):
        est = b.update([470] * 8, armed=True)  # 10 counts = 108.5 Pa less = 9.0 m higher
    assert est.altitude_m == pytest.approx(108.5 / (1.225 * G), abs=0.2)
    assert est.climb_m_s == pytest.approx(0.0, abs=0.05)

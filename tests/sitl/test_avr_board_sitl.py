"""The firmware binary flying the pybullet vehicle (``--board avr``): in process against the Python board model on
the same scripted setpoints, the failsafe on setpoint silence with physics, and a whole flight through the real
bridge (take off, hover, land) judged on the SITL's ground truth.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from avr_firmware import firmware_elf  # noqa: F401  (fixture)
from test_bridge_sitl import BRIDGE_SITL, PX4_LOITER, Gcs, Odometry, Stack, wait_for

from quadlink.frames import euler_from_R
from quadlink.mavlink import mavlink
from quadlink.mk.messages import AttitudeSetpoint, encode_message
from quadlink.vehicle import load_vehicle
from sim_sitl.avr_board import AvrBoard
from sim_sitl.config import load_scenario, load_sitl_config
from sim_sitl.firmware import AttitudeCommand
from sim_sitl.vehicle_sim import SimVehicle

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(600)]

Script = Callable[[float, float], tuple[float, float, float, float, bool]]


BARO_SETTLE_S = 8.0  # simulated seconds on the floor before the bridge flight arms
GROUND_S = 2.0  # disarmed on the floor first, as before any flight: the board takes its pressure reference
STEP_S = GROUND_S + 1.4  # the attitude steps start here, 0.5 s each: +roll, -roll, +pitch, -pitch, yaw rate
STEPS = ((0.15, 0.0, 0.0), (-0.15, 0.0, 0.0), (0.0, 0.15, 0.0), (0.0, -0.15, 0.0), (0.0, 0.0, 0.5))


def steps(t: float, hover: float) -> tuple[float, float, float, float, bool]:
    """Arm, climb, then roll, pitch and yaw-rate steps (roll rad, pitch rad, yaw rate rad/s, thrust, armed)."""
    if t < GROUND_S:
        return 0.0, 0.0, 0.0, 0.0, False
    if t < GROUND_S + 0.3:
        return 0.0, 0.0, 0.0, 0.0, True
    if t < STEP_S - 0.4:
        return 0.0, 0.0, 0.0, hover * 1.12, True
    for k, (roll, pitch, yaw_rate) in enumerate(STEPS):
        if STEP_S + 0.5 * k <= t < STEP_S + 0.5 * (k + 1):
            return roll, pitch, yaw_rate, hover, True
    return 0.0, 0.0, 0.0, hover, True


def fly_in_process(script: Script, seconds: float, elf: Path | None, stop_setpoints_at_s: float = math.inf,
                   seed: int = 1) -> tuple[np.ndarray, AvrBoard | None]:
    """Rows of (t, roll, pitch, yaw, height, motor thrust sum, armed) per tick; the same world, IMU and seed for
    both boards, setpoints at 100 Hz until ``stop_setpoints_at_s``."""
    vehicle, cfg = load_vehicle(), load_sitl_config()
    sim = SimVehicle(vehicle, cfg, load_scenario("empty"), np.random.default_rng(seed))
    board = None
    if elf is not None:
        board = AvrBoard(elf, vehicle, cfg.baro, np.random.default_rng(seed + 2), sim.tick_s)
        sim.board = board
    rows = []
    try:
        for k in range(round(seconds / sim.tick_s)):
            t = sim.t_s
            if k % 5 == 0 and t < stop_setpoints_at_s:
                roll, pitch, yaw_rate, thrust, armed = script(t, vehicle.hover_thrust_fraction)
                if board is not None:
                    board.on_port1(encode_message(AttitudeSetpoint(roll, pitch, yaw_rate, thrust, armed, k // 5)))
                else:
                    sim.on_setpoint(AttitudeCommand(roll, pitch, yaw_rate, thrust, armed, (k // 5) & 0xFF))
            res = sim.tick()
            r, p, y = euler_from_R(res.state.R_ned_q)
            rows.append((t, r, p, y, -float(res.state.p_ned_m[2]), float(np.sum(res.firmware.motor_cmd_n)),
                         float(res.firmware.armed)))
    finally:
        sim.close()
        if board is not None:
            board.close()
    return np.array(rows), board


def test_avr_board_and_python_model_agree_on_the_same_setpoints(firmware_elf: Path) -> None:  # noqa: F811
    seconds = STEP_S + 0.5 * len(STEPS) + 0.7
    model, _ = fly_in_process(steps, seconds, None)
    avr, board = fly_in_process(steps, seconds, firmware_elf)
    t = model[:, 0]
    # both sit still disarmed, then climb alike (thrust passes through both boards the same way)
    ground = t < GROUND_S
    assert np.all(avr[ground, 5] == 0.0) and np.all(avr[ground, 6] == 0.0)
    i_climb = int(STEP_S / 0.002)
    assert avr[i_climb, 4] == pytest.approx(model[i_climb, 4], abs=0.15)
    assert avr[i_climb, 4] > 0.4
    # the steps: each board reaches the commanded tilt and the two attitude histories stay close. The firmware
    # flies its own estimate from the noisy IMU (the model flies the true attitude), hence 4 degrees.
    window = (t >= STEP_S) & (t < STEP_S + 2.0)
    for axis, name in ((1, "roll"), (2, "pitch")):
        diff_deg = np.degrees(np.sqrt(np.mean((model[window, axis] - avr[window, axis]) ** 2)))
        assert diff_deg < 4.0, f"{name}: RMS difference {diff_deg:.1f} deg"
    for k, (roll, pitch, _) in enumerate(STEPS[:4]):
        axis, want = (1, roll) if roll else (2, pitch)
        settled = (t >= STEP_S + 0.5 * k + 0.3) & (t < STEP_S + 0.5 * (k + 1))  # the last 0.2 s of the step
        got, got_model = float(np.mean(avr[settled, axis])), float(np.mean(model[settled, axis]))
        assert got == pytest.approx(want, abs=math.radians(4.0)), f"step {k}: {math.degrees(got):.1f} deg"
        assert abs(got - got_model) < math.radians(4.0)
    # the yaw-rate step turns both by about 0.5 rad/s x 0.5 s
    i0, i1 = int((STEP_S + 2.0) / 0.002), int((STEP_S + 2.7) / 0.002)
    for rows in (model, avr):
        turned = (rows[i1, 3] - rows[i0, 3] + math.pi) % (2 * math.pi) - math.pi
        assert turned == pytest.approx(0.25, abs=0.08)
    assert board is not None and board.imu_stream.stats.lost == 0


def test_the_avr_board_is_deterministic(firmware_elf: Path) -> None:  # noqa: F811
    """The same seed and setpoints give the same flight, tick for tick (what the deterministic lock-step needs)."""
    a, _ = fly_in_process(steps, GROUND_S + 2.0, firmware_elf)
    b, _ = fly_in_process(steps, GROUND_S + 2.0, firmware_elf)
    assert a[-1, 4] > 0.2  # it flew
    np.testing.assert_array_equal(a, b)
    c, _ = fly_in_process(steps, GROUND_S + 2.0, firmware_elf, seed=2)
    assert not np.array_equal(a, c)  # ... and the seed matters (sensor noise reaches the pins)


def test_failsafe_on_setpoint_silence_descends_and_cuts_on_the_floor(firmware_elf: Path) -> None:  # noqa: F811
    silence_s = GROUND_S + 2.5

    def climb_and_hold(t: float, hover: float) -> tuple[float, float, float, float, bool]:
        if t < GROUND_S:
            return 0.0, 0.0, 0.0, 0.0, False
        return 0.0, 0.0, 0.0, (hover * 1.12 if t < GROUND_S + 1.2 else hover), True

    rows, board = fly_in_process(climb_and_hold, silence_s + 12.0, firmware_elf, stop_setpoints_at_s=silence_s)
    t, height, thrust, armed = rows[:, 0], rows[:, 4], rows[:, 5], rows[:, 6]
    i_silence = int(silence_s / 0.002)
    assert height[i_silence] > 0.5, "it never flew"
    after = slice(i_silence, None)
    # not cut in the air: the motors keep running while it comes down ...
    airborne = (t > silence_s) & (height > 0.15)
    assert np.all(thrust[airborne] > 0.0)
    assert np.all(armed[airborne] == 1.0)
    # ... at a sink rate a landing survives, not a fall
    z = height[after]
    vz = np.diff(z) / 0.002
    assert vz.min() > -1.5, f"fell at {vz.min():.2f} m/s"
    # then, on the floor, the board cuts the motors and disarms
    assert height[-1] < 0.1
    assert thrust[-1] == 0.0 and armed[-1] == 0.0
    touchdown = t[np.argmax((t > silence_s) & (height < 0.12))]
    cut = t[np.argmax((t > silence_s) & (armed == 0.0))]
    assert touchdown < cut < touchdown + 5.0
    assert board is not None and board.failsafe is False and board.last_status is not None


def test_flight_through_the_bridge_takes_off_hovers_and_lands(firmware_elf: Path, tmp_path: Path) -> None:  # noqa: F811
    stack = Stack(tmp_path, replace(BRIDGE_SITL, board="avr", firmware_elf=firmware_elf))
    gcs = odom = None
    try:
        gcs = Gcs(stack.gcs_port)
        odom = Odometry(stack, gcs)
        assert gcs.recv("HEARTBEAT", 30.0) is not None
        wait_for(lambda: stack.truth_count > 10, 15.0, "truth")
        odom.start()
        # powered up on the floor for a while before arming, as a board is: its barometer settles (about 6 s
        # after power-up; armed earlier, its altitude and climb still carry the start-up transient)
        wait_for(lambda: stack.sim_time_s >= BARO_SETTLE_S, 180.0, f"{BARO_SETTLE_S:.0f} s of simulated time")
        assert gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mavlink.MAV_RESULT_ACCEPTED
        assert gcs.command(mavlink.MAV_CMD_NAV_TAKEOFF, *([math.nan] * 7)) == mavlink.MAV_RESULT_ACCEPTED
        assert gcs.recv("HEARTBEAT", 150.0, lambda m: m.custom_mode == PX4_LOITER) is not None  # slow under load
        # hover: 4 s of simulated time near the take-off altitude, level and still
        t0 = stack.sim_time_s
        heights, tilts, speeds = [], [], []
        while stack.sim_time_s - t0 < 4.0:
            p, v, q = stack.state()
            heights.append(-p[2])
            r, pi, _ = euler_from_R(_R(q))
            tilts.append(max(abs(r), abs(pi)))
            speeds.append(float(np.linalg.norm(v)))
            wait_for(lambda n=stack.truth_count: stack.truth_count > n, 10.0, "truth")
        at_loiter = -stack.state()[0][2] if not heights else heights[0]
        assert np.mean(heights) == pytest.approx(1.0, abs=0.3), \
            f"hover height {np.mean(heights):.2f} m (from {at_loiter:.2f} to {heights[-1]:.2f} m)"
        assert np.ptp(heights) < 0.4
        assert max(tilts) < math.radians(10.0)
        assert np.median(speeds) < 0.3
        assert gcs.command(mavlink.MAV_CMD_NAV_LAND) == mavlink.MAV_RESULT_ACCEPTED
        assert gcs.recv("HEARTBEAT", 150.0, lambda m: not m.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED) \
            is not None
        p, _, _ = stack.state()
        assert abs(p[2]) < 0.15
    finally:
        if odom is not None:
            odom.stop.set()
        if gcs is not None:
            gcs.close()
        stack.close()


# ---------------------------------------------------------------- helpers


def _R(q: np.ndarray) -> np.ndarray:
    from quadlink.frames import R_from_quat_wxyz

    return R_from_quat_wxyz(q)


def _lockstep_flight(elf: Path, jitter_s: float, seed: int) -> tuple[object, object, np.ndarray]:
    import threading
    import time

    from test_sitl_lockstep import FakeBridge

    from sim_sitl.config import SitlConfig
    from sim_sitl.runner import Sitl, SitlOptions

    cfg = SitlConfig(scenario="empty", board="avr", firmware_elf=str(elf))
    sitl = Sitl(SitlOptions(config=cfg, port1=0, port2=0, camera_port=0, camera=False, truth_url=None,
                            progress_every_s=60.0, lockstep=True, lockstep_port=0, lockstep_participants=("bridge",),
                            duration_s=1.0))
    thread = threading.Thread(target=sitl.run, daemon=True)
    thread.start()
    try:
        time.sleep(0.3)
        assert sitl.sim.t_s == 0.0
        bridge = FakeBridge(sitl, jitter_s, seed)
        bridge.run()
        thread.join(20.0)
        assert not thread.is_alive()
        s = sitl.sim.world.state
        return sitl, bridge, np.concatenate([s.p_ned_m, s.v_ned_m_s, s.R_ned_q.ravel()])
    finally:
        sitl.stop()


def test_deterministic_lockstep_with_the_avr_board(firmware_elf: Path) -> None:  # noqa: F811
    """quadlink.lockstep with --board avr: the same inputs at different wall times are the same flight, bit for bit."""
    sitl_a, bridge_a, truth_a = _lockstep_flight(firmware_elf, 0.0, 1)
    sitl_b, bridge_b, truth_b = _lockstep_flight(firmware_elf, 0.004, 2)
    for sitl, bridge in ((sitl_a, bridge_a), (sitl_b, bridge_b)):
        assert bridge.ended is not None and "duration" in bridge.ended  # type: ignore[attr-defined]
        assert [i for i, _ in bridge.steps] == list(range(100))  # type: ignore[attr-defined]
        assert 495 <= bridge.samples <= 500  # type: ignore[attr-defined]  # the board's first frame a tick in
        assert sitl.stats.setpoints == 99  # type: ignore[attr-defined]
        assert sitl.armed  # type: ignore[attr-defined]
    assert truth_a[2] < -0.02  # it lifted off
    assert np.array_equal(truth_a, truth_b)

"""Issue 30 over the real ports, in real time, on the shipped timeouts: the vehicle without its companion.

* The companion killed in a hover: the bridge lands the vehicle on its own (odometry lost -> brake, level, the
  blind descent on the accelerometer fused with the board's barometer 'Z'): touchdown at <= 0.7 m/s (PX4 lands at
  MPC_LAND_SPEED 0.7 m/s, ArduPilot at LAND_SPEED 0.5 m/s), drift <= 0.5 m.
* The companion stalled (SIGSTOP) while the operator pushes toward a wall: the failsafe that starts next to the wall
  must not carry the vehicle into it (clearance >= 0.40 m, the whole flight).
"""

from __future__ import annotations

import signal
from pathlib import Path

import numpy as np
import pytest
import yaml
from flight_harness import Flight, companion_config_with, flight

from harness.campaign.draws import draw_vehicle_and_sensors
from harness.ports import PORT_SLOT_STRIDE, free_port_offset
from quadlink.ids import COMPANION_COMPONENT_ID
from quadlink.mavlink import mavlink

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(600)]

MIN_CLEARANCE_M = 0.40
MAX_TOUCHDOWN_M_S = 0.7
# drift from the kill to touchdown: the 0.5 m. Measured on 3d2cd2f+ (the blind descent holding on the nominal
# drag, BRG_DRAG_K_NOM): 0.11-0.12 m at 1.9 m, 0.04-0.10 m at 1.2 m, 0.06-0.07 m at 0.5 m (three runs each); before it,
# level on the board's own attitude estimate, 0.56-0.63 m at 1.9 m and the bound was widened to 0.75 m
MAX_DRIFT_M = 0.5
OFFSET = free_port_offset(slots=2)   # harness.ports: free now, reserved for this session
DRAWN_SEED = 20261207                # the drawn landings' seed (not a campaign's)
LONG_DRAWN_SEED = 20261208           # the drawn landings after a long hover
LONG_HOVER_S = 150.0


def _hover_at(f: Flight, height_m: float) -> None:
    """Climb or descend on the handle until the centre of mass is within 5 cm of ``height_m`` above the floor."""
    def z_cmd() -> None:
        err = height_m - f.log.samples[-1].clearance.floor_m if f.log.samples else 0.0
        f.manual(0, 0, int(np.clip(500 + 900 * err, 150, 850)))

    f.run_for(20.0, z_cmd, until=lambda: bool(f.log.samples) and
              abs(f.log.samples[-1].clearance.floor_m - height_m) < 0.05)
    f.run_for(2.0, lambda: f.manual(0))


def _kill_in_a_hover(tmp_path: Path, height_m: float, sitl_config: Path | None = None, hover_s: float = 0.0,
                     land: bool = False) -> None:
    """The companion killed in a hover (or, ``land``, the ground station's LAND through the companion: its last
    BRG_LAND_LVL_ALT is the same level descent on the baro): touchdown, clearance and the drift judged on the truth."""
    config = companion_config_with(tmp_path, reference={"room_height_m": 3.0})
    with flight(tmp_path, offset=OFFSET, lockstep=False, shipped_timeouts=True, companion_config=config,
                sitl_config=sitl_config) as f:
        f.take_off()
        _hover_at(f, height_m)
        f.run_for(hover_s, lambda: f.manual(0))   # the baro drifts on from the take-off's ground reference
        t_kill, p_kill = f.t_s, f.p_arena.copy()
        if land:
            f.gcs.mav.command_long_send(1, COMPANION_COMPONENT_ID, mavlink.MAV_CMD_NAV_LAND, 0, 0, 0, 0, 0, 0, 0, 0)
        else:
            f.signal_part("companion", signal.SIGKILL)
        f.run_for(25.0, None, until=lambda: f.log.touchdown(t_kill) is not None and f.t_s > t_kill + 2.0)
        f.run_for(2.0, None)
        td = f.log.touchdown(t_kill)
        assert td is not None, f"never came down from {height_m} m: {f.log.summary()}"
        t_td, vz_td = td
        drift = float(np.linalg.norm(f.p_arena[:2] - p_kill[:2]))
        print(f"{'LAND' if land else 'companion killed'} at {height_m} m after {hover_s:.0f} s of hover: touchdown "
              f"after {t_td - t_kill:.1f} s at {vz_td:.2f} m/s, "
              f"drift {drift:.2f} m; {f.log.summary()}")
        assert vz_td <= MAX_TOUCHDOWN_M_S, f"touched down at {vz_td:.2f} m/s"
        assert drift <= MAX_DRIFT_M, f"drifted {drift:.2f} m"
        s = f.log.min_surface()
        assert s is not None and s.clearance.surface_m >= MIN_CLEARANCE_M, f.log.summary()


@pytest.mark.parametrize("height_m", [1.2, pytest.param(0.5, marks=pytest.mark.slow),
                                      pytest.param(1.9, marks=pytest.mark.slow)])
def test_the_companion_killed_in_a_hover_lands_gently(tmp_path: Path, height_m: float) -> None:
    """1.9 m: the highest hover under the companion's 2.0 m altitude fence (the bridge's descent starts there); the
    operator entered paper-arena's 3.0 m (without an entry the companion assumes a 2.0 m room: 1.55 m at most)."""
    _kill_in_a_hover(tmp_path, height_m)


@pytest.mark.slow
@pytest.mark.parametrize("index", range(8))
def test_the_companion_killed_over_drawn_vehicles_lands_gently(tmp_path: Path, index: int) -> None:
    """The same on vehicles and sensors drawn as a campaign draws them (harness.campaign.draws: mass x U(0.9, 1.1)
    that the stack's nominal model does not know, IMU bias spreads, and the SITL's seed, so the baro's offset, drift
    and noise and the IMU's biases), at a height drawn in 0.5-1.9 m, from a seed of its own. The SITL's default
    vehicle is what the landing was measured and mended on (the baro drifted 0.13-0.18 m low there, one draw)."""
    _kill_drawn(tmp_path, DRAWN_SEED, index, hover_s=0.0)


@pytest.mark.slow
@pytest.mark.parametrize("index", range(6))
def test_after_a_long_hover_a_landing_touches_down_gently(tmp_path: Path, index: int) -> None:
    """The same after LONG_HOVER_S of hover on odometry: the baro drifts on from the take-off's ground reference
    (the SITL's random walk: about 0.3 m of one sigma after 2.5 min), so the estimate reads the floor further above
    or below it than in a short flight. Drawn vehicles and heights from a seed of their own; even draws kill the
    companion, odd ones land through it (the last BRG_LAND_LVL_ALT of every landing is the same descent).

    The board's level drifts in the long hover (its gyro bias, held from the ground: 7.7 deg on draw 1), and the
    pan-scan swings the vehicle at up to 0.3 m/s: a kill or a LAND in the swing carried draw 1 0.52-1.00 m until the
    level trim, the hold's tilt bounds, the resting test and the hold through the level part were mended
    (``fbe9f79``; then 0.08-0.30 m over the six draws, draw 1's kill re-flown 0.48 m)."""
    _kill_drawn(tmp_path, LONG_DRAWN_SEED, index, hover_s=LONG_HOVER_S, land=index % 2 == 1)


def _kill_drawn(tmp_path: Path, seed: int, index: int, hover_s: float, land: bool = False) -> None:
    seq = np.random.SeedSequence(seed, spawn_key=(index,))
    vehicle_ss, sitl_ss, height_ss = seq.spawn(3)
    vehicle, sitl, record = draw_vehicle_and_sensors(vehicle_ss, sitl_ss)
    height_m = round(float(np.random.default_rng(height_ss).uniform(0.5, 1.9)), 2)
    (tmp_path / "vehicle.yaml").write_text(yaml.safe_dump(vehicle, sort_keys=False))
    (tmp_path / "sitl.yaml").write_text(yaml.safe_dump({**sitl, "vehicle": str(tmp_path / "vehicle.yaml")},
                                                       sort_keys=False))
    print(f"draw {index} of seed {seed}: {height_m} m, {record}")
    _kill_in_a_hover(tmp_path, height_m, tmp_path / "sitl.yaml", hover_s=hover_s, land=land)


def test_a_companion_stalled_beside_a_wall_does_not_carry_the_vehicle_into_it(tmp_path: Path) -> None:
    with flight(tmp_path, offset=OFFSET + PORT_SLOT_STRIDE, lockstep=False, shipped_timeouts=True) as f:
        f.take_off()
        f.run_for(25.0, lambda: f.manual(700), until=lambda: f.log.samples[-1].clearance.surface_m < 0.65)
        t_stall = f.t_s
        f.signal_part("companion", signal.SIGSTOP)   # a starved or hung companion: no setpoints, no odometry
        f.run_for(25.0, None, until=lambda: f.log.touchdown(t_stall) is not None and f.t_s > t_stall + 2.0)
        f.run_for(2.0, None)
        print(f"stalled at t={t_stall:.1f} s: {f.log.summary()}; touchdown {f.log.touchdown(t_stall)}")
        assert f.log.touchdown(t_stall) is not None, "the bridge did not land the vehicle"
        s = f.log.min_surface()
        assert s is not None and s.clearance.surface_m >= MIN_CLEARANCE_M, f.log.summary()

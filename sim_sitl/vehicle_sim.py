"""The simulated vehicle without I/O: pybullet world + board firmware + IMU, advanced in board ticks.

One board tick is 1 / ``firmware.loop_rate_hz`` (2 ms): the firmware runs on the state at the tick,
IMU sample ``k`` is taken at board time ``k * 2 ms``, then physics advances to the next tick (in
``physics.rate_hz / loop_rate_hz`` substeps). Time comes only from the tick counter.

The Python firmware model flies by default; a :class:`FlightBoard` (the firmware binary in simavr,
:class:`sim_sitl.avr_board.AvrBoard`) flies instead when one is given: it sees only the IMU reading, the
state's height through its pressure sensor, and the battery.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from quadlink.mk.flags import BoardFlightState
from quadlink.vehicle import VehicleConfig
from sim_sitl.board_sensing import ModelBoardSensing
from sim_sitl.config import ScenarioConfig, SitlConfig
from sim_sitl.disturbance import DisturbanceSchedule
from sim_sitl.firmware import AttitudeCommand, Firmware, FirmwareOutput
from sim_sitl.imu import ImuModel, ImuReading
from sim_sitl.world import RigidState, World


@dataclass(frozen=True)
class TickResult:
    tick: int  # index of the IMU sample taken at this tick
    t_s: float
    imu: ImuReading
    state: RigidState  # the true state at t_s (before the physics advanced)
    firmware: FirmwareOutput


class FlightBoard(Protocol):
    """A board that flies the motors from its sensor pins, one board tick at a time."""

    def control(self, t_s: float, state: RigidState, imu: ImuReading, battery_mv: float) -> FirmwareOutput: ...


class SimVehicle:
    def __init__(self, vehicle: VehicleConfig, cfg: SitlConfig, scenario: ScenarioConfig,
                 rng: np.random.Generator) -> None:
        self.vehicle = vehicle
        self.cfg = cfg
        self.tick_s = 1.0 / cfg.firmware.loop_rate_hz
        self.substeps = max(1, round(cfg.physics.rate_hz / cfg.firmware.loop_rate_hz))
        self.world = World(vehicle, cfg, scenario, rng)
        # the physics step is derived from the board tick so time stays on the 2 ms grid
        self.world.dt_s = self.tick_s / self.substeps
        import pybullet as p

        p.setTimeStep(self.world.dt_s, physicsClientId=self.world.client)
        self.firmware = Firmware(vehicle, cfg.firmware)
        self.imu = ImuModel(cfg.imu_noise, rng, vehicle.motor.max_thrust_n)
        # the model board's own sensing (its pressure sensor draws from a child stream: the IMU's draws unchanged)
        self.sensing = ModelBoardSensing(vehicle, cfg.baro, rng.spawn(1)[0])
        self.ticks = 0
        self.flying_time_s = 0.0
        self.disturbances = DisturbanceSchedule(scenario.disturbances)  # scripted pushes; .push() adds more
        self.board: FlightBoard | None = None  # None: the Python firmware model flies

    @property
    def t_s(self) -> float:
        return self.ticks * self.tick_s

    def power_up(self, seconds: float = 0.6) -> None:
        """The Python board powered up still and level on the ground before t = 0, for ``seconds`` (its gyro
        calibration takes 0.5 s: firmware/src/attitude.c): for a test that places the vehicle in the air at once.
        Simulated time and the physics do not move; only the board's filters see the IMU at rest."""
        level, zero = np.eye(3), np.zeros(3)
        for _ in range(round(seconds / self.tick_s)):
            reading = self.imu.measure(0.0, self.tick_s, level, zero, zero, np.zeros(4))
            self.sensing.sense(self.world.state, reading, self.tick_s, armed=False, flying=False)

    def on_setpoint(self, cmd: AttitudeCommand) -> None:
        self.firmware.on_setpoint(cmd, self.t_s)

    def tick(self) -> TickResult:
        t = self.t_s
        s = self.world.state
        reading = self.imu.measure(t, self.tick_s, s.R_ned_q, s.a_ned_m_s2, s.omega_q_rad_s, s.motor_thrust_n)
        if self.board is None:   # the model flies on its own estimate, as the firmware does (no truth)
            fw = self.firmware
            sensing = self.sensing.sense(s, reading, self.tick_s, fw.armed,
                                         fw.flight_state != BoardFlightState.LANDED)
            out = fw.step(t, self.tick_s, sensing)
        else:
            out = self.board.control(t, s, reading, self.battery_mv())
        for i in range(self.substeps):
            self.world.external_force_ned_n = self.disturbances.force_ned_n(t + i * self.world.dt_s)
            self.world.step(out.motor_cmd_n)
        if out.armed:
            self.flying_time_s += self.tick_s
        result = TickResult(self.ticks, t, reading, s, out)
        self.ticks += 1
        return result

    def battery_mv(self) -> int:
        b = self.vehicle.battery
        full_mv = b.cells * b.full_cell_v * 1000.0
        empty_mv = b.cells * b.empty_cell_v * 1000.0
        sag_mv = 60.0 * float(np.sum(self.world.motor_thrust_n))  # internal resistance under load
        return int(max(empty_mv, full_mv - self.cfg.battery_drain_mv_per_s * self.flying_time_s - sag_mv))

    def close(self) -> None:
        self.world.close()

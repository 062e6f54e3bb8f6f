"""What the Python board model knows of itself: its own IMU counts and pressure sensor, never the truth (issue 29).

The firmware (``firmware/src/attitude.c``, ``baro.c``) estimates its attitude from the six raw IMU counts and its
height from the MPX4115A on ADC6; the Python board model runs the very same arithmetic through the bit-exact mirror
(:mod:`sim_sitl.board_estimators`), fed with the counts the ``I`` frame carries and the ADC6 count the pressure
model (:mod:`sim_sitl.baro`) gives. So a drawn gyro bias tilts the vehicle as it would on the real board, and the
board's failsafe lands on its barometer, not on the true vertical speed.
"""

from __future__ import annotations

import numpy as np

from quadlink.mk.messages import ImuSample
from quadlink.vehicle import VehicleConfig
from sim_sitl.baro import BaroConfig, BaroModel, adc_count
from sim_sitl.board_estimators import BoardAttitude, BoardAttitudeFilter, BoardBaro, BoardBaroEstimate
from sim_sitl.firmware import BoardSensing
from sim_sitl.imu import ImuReading
from sim_sitl.world import RigidState


class ModelBoardSensing:
    """Feed :meth:`sense` once per 2 ms tick; it returns what the model's attitude loop flies on."""

    def __init__(self, vehicle: VehicleConfig, baro_cfg: BaroConfig, rng: np.random.Generator) -> None:
        self.imu_cfg = vehicle.imu
        self.attitude_filter = BoardAttitudeFilter()
        self.pressure_sensor = BaroModel(baro_cfg, rng)
        self.baro_filter = BoardBaro()
        self.attitude: BoardAttitude = self.attitude_filter.estimate()
        self.baro: BoardBaroEstimate = self.baro_filter.estimate()

    def sense(self, state: RigidState, reading: ImuReading, tick_s: float, armed: bool, flying: bool
              ) -> BoardSensing:
        """The board's estimate after this tick's samples (the IMU reading quantised as the ``I`` frame carries it;
        the pressure at the centre of mass's height above the arena floor)."""
        sample = ImuSample.from_si(reading.accel_q_m_s2, reading.gyro_q_rad_s, self.imu_cfg, 0)
        self.attitude = self.attitude_filter.update(sample.accel_counts, sample.gyro_counts, armed, flying)
        height_m = -float(state.p_ned_m[2])   # arena NED: the floor at z = 0
        self.baro = self.baro_filter.update(adc_count(self.pressure_sensor.measure(height_m, tick_s)), armed)
        a = self.attitude
        return BoardSensing(a.roll_rad, a.pitch_rad, a.yaw_rad, np.asarray(a.rates_q_rad_s, dtype=float),
                            -self.baro.climb_m_s)

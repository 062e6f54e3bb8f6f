"""The MK board's flight firmware as the SITL runs it (pure, step-based, 500 Hz).

Attitude loop as on the FlightCtrl: angle (P) and rate (PID) control on roll and pitch, rate (PI)
control on yaw, collective thrust passed through (fraction of ``VehicleConfig.max_total_thrust_n``,
no tilt compensation: the companion's velocity tracker compensates gravity). Arming follows
``AttitudeSetpoint.armed``; clearing it cuts the motors at once. When setpoints stop for
``setpoint_timeout_s`` the board enters failsafe: level attitude, zero yaw rate and a slow descent,
then it cuts the motors once it is on the ground (or at once if it was not flying).

The firmware sees the attitude and rates the way the real board's own filter would (the SITL feeds it
the true values) and a vertical speed from its pressure sensor.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from quadlink.mk.flags import BoardError, BoardFlightState
from quadlink.vehicle import VehicleConfig
from sim_sitl.config import FirmwareConfig
from sim_sitl.motors import mix, rotor_layout


@dataclass(frozen=True)
class AttitudeCommand:
    """What the firmware flies (decoded from an ``AttitudeSetpoint`` 's' frame)."""

    roll_rad: float = 0.0
    pitch_rad: float = 0.0
    yaw_rate_rad_s: float = 0.0
    thrust: float = 0.0  # fraction 0..1 of max total thrust
    armed: bool = False
    seq: int = 0


@dataclass(frozen=True)
class BoardSensing:
    """The board's view of its state (FRD body rates, ZYX Euler angles, NED vertical speed)."""

    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    rates_q_rad_s: NDArray[np.float64]
    vz_ned_m_s: float


@dataclass(frozen=True)
class FirmwareOutput:
    motor_cmd_n: NDArray[np.float64]
    armed: bool
    flight_state: int
    failsafe: bool


class Firmware:
    """Step it at ``loop_rate_hz`` with :meth:`step`; feed setpoints with :meth:`on_setpoint`."""

    def __init__(self, vehicle: VehicleConfig, cfg: FirmwareConfig) -> None:
        self.vehicle = vehicle
        self.cfg = cfg
        self.layout = rotor_layout(vehicle)
        self.inertia = np.asarray(vehicle.inertia_kg_m2, dtype=float)
        self.command = AttitudeCommand()
        self.last_setpoint_t_s: float | None = None
        self.armed = False
        self.failsafe = False
        self.flight_state = BoardFlightState.LANDED
        self.error_flags = 0
        self.setpoints_received = 0
        self.rejected_setpoints = 0
        self._integ = np.zeros(3)
        self._prev_rates: NDArray[np.float64] | None = None
        self._failsafe_start_s = 0.0
        self._still_since_s: float | None = None

    def on_setpoint(self, cmd: AttitudeCommand, t_s: float) -> None:
        """Accept a setpoint (clamped to the board's limits); a setpoint ends a failsafe."""
        c = self.cfg
        clamped = AttitudeCommand(
            float(np.clip(cmd.roll_rad, -c.max_tilt_rad, c.max_tilt_rad)),
            float(np.clip(cmd.pitch_rad, -c.max_tilt_rad, c.max_tilt_rad)),
            float(np.clip(cmd.yaw_rate_rad_s, -c.max_yaw_rate_rad_s, c.max_yaw_rate_rad_s)),
            float(np.clip(cmd.thrust, 0.0, 1.0)), bool(cmd.armed), int(cmd.seq) & 0xFF)
        if not np.isfinite([cmd.roll_rad, cmd.pitch_rad, cmd.yaw_rate_rad_s, cmd.thrust]).all():
            self.rejected_setpoints += 1
            return  # never fly a NaN
        self.command = clamped
        self.last_setpoint_t_s = t_s
        self.setpoints_received += 1
        if self.failsafe:
            self.failsafe = False
            self.error_flags &= ~int(BoardError.SETPOINT_TIMEOUT)
        if clamped.armed and not self.armed:
            self._reset_loops()
        self.armed = clamped.armed

    def _reset_loops(self) -> None:
        self._integ[:] = 0.0
        self._prev_rates = None

    def _disarm(self) -> None:
        self.armed = False
        self.command = AttitudeCommand(armed=False, seq=self.command.seq)
        self._reset_loops()

    def step(self, t_s: float, dt_s: float, sense: BoardSensing) -> FirmwareOutput:
        c = self.cfg
        m = self.vehicle.motor
        if self.armed and not self.failsafe and self.last_setpoint_t_s is not None \
                and t_s - self.last_setpoint_t_s > c.setpoint_timeout_s:
            self.error_flags |= BoardError.SETPOINT_TIMEOUT
            if self.flight_state == BoardFlightState.FLYING:
                self.failsafe = True
                self._failsafe_start_s = t_s
                self._still_since_s = None
            else:
                self._disarm()  # not flying: just cut
        if not self.armed:
            self.flight_state = BoardFlightState.LANDED
            self.failsafe = False
            return FirmwareOutput(np.zeros(4), False, BoardFlightState.LANDED, False)

        if self.failsafe:
            # hold level attitude and descend; cut once stopped on the ground
            descend = self.vehicle.hover_thrust_fraction * c.failsafe_descent_thrust_fraction
            cmd = AttitudeCommand(0.0, 0.0, 0.0, descend, True, self.command.seq)
            moving = abs(sense.vz_ned_m_s) > c.failsafe_ground_speed_m_s
            if moving or t_s - self._failsafe_start_s < 1.0:
                self._still_since_s = None
            elif self._still_since_s is None:
                self._still_since_s = t_s
            elif t_s - self._still_since_s > 0.5:
                self._disarm()
                return FirmwareOutput(np.zeros(4), False, BoardFlightState.LANDED, False)
        else:
            cmd = self.command
        self.flight_state = BoardFlightState.FAILSAFE_DESCEND if self.failsafe else (
            BoardFlightState.FLYING if cmd.thrust > c.landed_thrust_fraction else BoardFlightState.LANDED)

        rates = np.asarray(sense.rates_q_rad_s, dtype=float)
        rate_sp = np.array([
            np.clip(c.angle_kp_1_s * (cmd.roll_rad - sense.roll_rad), -c.max_rate_rad_s, c.max_rate_rad_s),
            np.clip(c.angle_kp_1_s * (cmd.pitch_rad - sense.pitch_rad), -c.max_rate_rad_s, c.max_rate_rad_s),
            cmd.yaw_rate_rad_s,
        ])
        err = rate_sp - rates
        if self.flight_state == BoardFlightState.LANDED:
            self._integ[:] = 0.0  # no wind-up while sitting on the ground
        else:
            self._integ[:2] += c.rate_ki_1_s2 * err[:2] * dt_s
            self._integ[2] += c.yaw_rate_ki_1_s2 * err[2] * dt_s
            np.clip(self._integ, -c.integrator_limit_rad_s2, c.integrator_limit_rad_s2, out=self._integ)
        d_rates = np.zeros(3) if self._prev_rates is None else (rates - self._prev_rates) / dt_s
        self._prev_rates = rates
        alpha = np.empty(3)
        alpha[:2] = c.rate_kp_1_s * err[:2] + self._integ[:2] - c.rate_kd * d_rates[:2]
        alpha[2] = c.yaw_rate_kp_1_s * err[2] + self._integ[2]
        torque = self.inertia * alpha + np.cross(rates, self.inertia * rates)  # gyroscopic feed-forward
        thrust_n = cmd.thrust * self.vehicle.max_total_thrust_n
        motor_cmd = mix(self.layout, thrust_n, torque, m.idle_fraction * m.max_thrust_n, m.max_thrust_n)
        return FirmwareOutput(motor_cmd, True, self.flight_state, self.failsafe)

"""``AvrBoard``: the FlightCtrl binary in simavr standing in for the Python board model inside the SITL.

Per 2 ms board tick (:meth:`AvrBoard.control`, called by :class:`sim_sitl.vehicle_sim.SimVehicle`): the IMU
model's reading, the pressure sensor (:mod:`sim_sitl.baro`) and the battery become voltages on ADC0..7 by the laws
of ``firmware/HARDWARE.md``; the MCU runs the tick's 40,000 cycles; the four BL-Ctrl bytes become motor thrust
commands (byte / 255 x ``max_thrust_n``); the bytes both USARTs sent are kept, with the cycle each one left, for the
runner to hand to the ports (the UARTs already paced them at the baud rate: they are not paced again). Port 1's
received bytes go to USART0's receiver, which takes them at the line rate. Nothing true reaches the firmware except
through its pins.

Causality is the Python model's: the firmware flies tick k from the sensors of tick k and its motor bytes at the end
of the tick's cycles act during the physics of tick k.
"""

from __future__ import annotations

import bisect
import logging
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from quadlink import REPO_ROOT
from quadlink.errors import ConfigError
from quadlink.mk.flags import BoardFlightState
from quadlink.mk.messages import AttitudeSetpoint, BoardStatus, ImuSample, decode_message
from quadlink.mk.protocol import ADDR_ANY, ADDR_FC, Frame, FrameDecoder
from quadlink.vehicle import ImuConfig, VehicleConfig
from sim_sitl.avr.sim import F_CPU_HZ, AvrSim
from sim_sitl.baro import ADC_REF_V, BaroConfig, BaroModel, adc_count
from sim_sitl.firmware import FirmwareOutput
from sim_sitl.imu import ImuReading
from sim_sitl.world import RigidState

log = logging.getLogger(__name__)

DEFAULT_ELF = REPO_ROOT / "firmware" / "build" / "quadlink-fc.elf"
BATTERY_DIVIDER = 4.0
CH_GYRO, CH_ACCEL, CH_PRESSURE, CH_BATTERY = 0, 3, 6, 7  # AvrBoard.control drives them in this order
PIN_LOOP_BUSY, PIN_LED = 0, 1
MOTOR_BYTE_FULL = 255
IMU_COUNTER_MODULO = 4096


def imu_volts(si: float, lsb: float, zero_count: int) -> float:
    """An IMU sensor's output voltage for a reading ``si`` (zero at ``zero_count``, ``lsb`` per count)."""
    return (zero_count + si / lsb) * ADC_REF_V / 1024.0


def elf_path(configured: str | None) -> Path:
    """The firmware ELF to fly; ConfigError with the fix when it is missing."""
    path = Path(configured) if configured else DEFAULT_ELF
    if not path.is_file():
        raise ConfigError(f"firmware ELF {path} not found: build it with make -C firmware")
    return path


def frames_with_cycles(decoder: FrameDecoder, data: bytes, cycles: list[int]) -> list[tuple[Frame, int]]:
    """Feed a UART's bytes to ``decoder``; each complete frame with the cycle its last byte (``'\\r'``) left."""
    out: list[tuple[Frame, int]] = []
    start = 0
    for end, byte in enumerate(data):
        if byte == 0x0D:  # frames end on '\r' (never inside one)
            out += [(frame, cycles[end]) for frame in decoder.feed(data[start:end + 1])]
            start = end + 1
    if start < len(data):
        out += [(frame, cycles[-1]) for frame in decoder.feed(data[start:])]
    return out


@dataclass
class ImuStreamStats:
    """The ``I`` stream as port 2 carried it: frames, lost samples (counter gaps) and late frames."""

    frames: int = 0
    lost: int = 0  # samples missing between two frames (sample_counter gaps)
    late: int = 0  # frames whose last byte left more than ``late_after_cycles`` after their slot
    max_lag_cycles: int = 0  # worst (last byte's cycle - the slot's cycle), slot = first frame's + k x period
    bad_frames: int = 0
    first_cycle: int | None = None
    last_cycle: int = 0


class ImuStreamMonitor:
    """Decodes port 2's bytes (with their cycles) and checks the 500 Hz ``I`` stream against its own timeline."""

    def __init__(self, period_cycles: int, late_after_cycles: int) -> None:
        self.period = period_cycles
        self.late_after = late_after_cycles
        self.decoder = FrameDecoder()
        self.stats = ImuStreamStats()
        self._index = -1  # unwrapped sample index of the last frame
        self._counter = -1
        self._origin = 0

    def feed(self, data: bytes, cycles: list[int]) -> None:
        for frame, cycle in frames_with_cycles(self.decoder, data, cycles):
            msg = decode_message(frame)
            if isinstance(msg, ImuSample):
                self._on_sample(msg.sample_counter, cycle)
            else:
                self.stats.bad_frames += 1

    def _on_sample(self, counter: int, cycle: int) -> None:
        s = self.stats
        if self._counter < 0:
            self._index, self._origin, s.first_cycle = 0, cycle, cycle
        else:
            gap = (counter - self._counter) % IMU_COUNTER_MODULO
            s.lost += max(0, gap - 1)
            self._index += max(gap, 1)
        self._counter = counter
        lag = cycle - (self._origin + self._index * self.period)
        s.max_lag_cycles = max(s.max_lag_cycles, lag)
        if lag > self.late_after:
            s.late += 1
        s.frames += 1
        s.last_cycle = cycle


@dataclass
class LoopTiming:
    """The 500 Hz loop's busy time from PB0's edges (cycles), the most recent ``keep`` loops."""

    keep: int = 100_000
    busy_cycles: deque[int] = field(default_factory=deque)
    starts: int = 0
    busy_max: int = 0  # the worst loop since the start (busy_cycles keeps only the last ``keep``)
    _rise: int | None = None

    def on_edge(self, cycle: int, level: int) -> None:
        if level:
            self._rise = cycle
            self.starts += 1
        elif self._rise is not None:
            busy = cycle - self._rise
            self.busy_cycles.append(busy)
            if busy > self.busy_max:
                self.busy_max = busy
            if len(self.busy_cycles) > self.keep:
                self.busy_cycles.popleft()
            self._rise = None


class AvrBoard:
    """The board for ``--board avr``. ``close()`` frees the simulated MCU."""

    def __init__(self, elf: Path, vehicle: VehicleConfig, baro_cfg: BaroConfig, rng: np.random.Generator,
                 tick_s: float, late_after_s: float = 0.004, frequency_hz: int = F_CPU_HZ) -> None:
        self.vehicle = vehicle
        self.imu_cfg: ImuConfig = vehicle.imu
        self.mcu = AvrSim(elf, frequency_hz)
        self.mcu_elf = elf
        self.baro = BaroModel(baro_cfg, rng)
        self.tick_s = tick_s
        self.cycles_per_tick = round(tick_s * frequency_hz)
        self.ticks = 0
        self.loop = LoopTiming()
        self.imu_stream = ImuStreamMonitor(self.cycles_per_tick, round(late_after_s * frequency_hz))
        self.armed = False
        self.flight_state = int(BoardFlightState.LANDED)
        self.failsafe = False
        self.last_status: BoardStatus | None = None
        self.setpoints_sent = 0
        self._out: list[tuple[bytes, list[int]]] = [(b"", []), (b"", [])]
        # bytes a UART started in a chunk whose stop bit leaves in the next one: they wait for their time
        self._in_flight: list[tuple[bytes, list[int]]] = [(b"", []), (b"", [])]
        self._port1_out = FrameDecoder()
        self._port1_in = FrameDecoder()

    def close(self) -> None:
        self.mcu.close()

    # ------------------------------------------------------------------ the tick
    def control(self, t_s: float, state: RigidState, imu: ImuReading, battery_mv: float) -> FirmwareOutput:
        """Sensors of tick ``ticks`` to the pins, run the tick's cycles, the motor bytes as thrust commands."""
        cfg = self.imu_cfg
        mcu = self.mcu
        gyro, accel = imu.gyro_q_rad_s.tolist(), imu.accel_q_m_s2.tolist()
        zero = cfg.zero_count
        # ADC0..7 in channel order (CH_GYRO 0..2, CH_ACCEL 3..5, CH_PRESSURE 6, CH_BATTERY 7), one shim call
        height_m = -float(state.p_ned_m[2])  # arena NED: the floor at z = 0
        mcu.set_adc_counts([adc_count(imu_volts(g, cfg.gyro_lsb_rad_s, zero)) for g in gyro]
                           + [adc_count(imu_volts(a, cfg.accel_lsb_m_s2, zero)) for a in accel]
                           + [adc_count(self.baro.measure(height_m, self.tick_s)),
                              adc_count(battery_mv / 1000.0 / BATTERY_DIVIDER)])
        self.ticks += 1
        mcu.run_until(self.ticks * self.cycles_per_tick)
        on_edge = self.loop.on_edge
        for edge in mcu.take_edges():
            if edge.pin == PIN_LOOP_BUSY:
                on_edge(edge.cycle, edge.level)
        out1, out2 = self._left(0), self._left(1)
        self._out = [out1, out2]
        self.imu_stream.feed(*out2)
        self._watch_status(out1[0])
        self.armed = mcu.portb(PIN_LED) == 1
        motor_bytes = mcu.motors().bytes
        cmd = np.array(motor_bytes, dtype=float) / MOTOR_BYTE_FULL * self.vehicle.motor.max_thrust_n
        return FirmwareOutput(cmd, self.armed, self.flight_state, self.failsafe)

    def _left(self, port: int) -> tuple[bytes, list[int]]:
        """The bytes of USART``port`` whose stop bit has left by now, with their cycles (oldest first)."""
        data, cycles = self.mcu.take_tx(port)
        held, held_cycles = self._in_flight[port]
        data, cycles = held + data, held_cycles + cycles
        n = bisect.bisect_right(cycles, self.mcu.cycle)
        self._in_flight[port] = (data[n:], cycles[n:])
        return data[:n], cycles[:n]

    def _watch_status(self, port1_bytes: bytes) -> None:
        """The flight state and failsafe flag as the board reports them in ``S`` (for the runner's end rules)."""
        if not port1_bytes:
            return
        for frame in self._port1_out.feed(port1_bytes):
            msg = decode_message(frame)
            if isinstance(msg, BoardStatus):
                self.last_status = msg
                self.flight_state, self.failsafe = int(msg.flight_state), bool(msg.failsafe)

    # ------------------------------------------------------------------ the ports
    def take_port_bytes(self) -> tuple[bytes, bytes]:
        """Port 1's and port 2's bytes of the last tick (all of them left the UARTs within it)."""
        (b1, _), (b2, _) = self._out
        self._out = [(b"", []), (b"", [])]
        return b1, b2

    def on_port1(self, data: bytes) -> int:
        """Bytes from port 1's client to USART0's receiver; returns the setpoints among them (the lock-step gate
        counts them; the firmware decodes the bytes itself)."""
        taken = self.mcu.send_port1(data)
        if taken < len(data):
            log.warning("USART0's input queue is full: %d port-1 bytes dropped", len(data) - taken)
        n = 0
        for frame in self._port1_in.feed(data):
            if frame.address in (ADDR_ANY, ADDR_FC) and isinstance(decode_message(frame), AttitudeSetpoint):
                n += 1
        self.setpoints_sent += n
        return n

"""The board's side of the MK serial protocol on port 1 (pure: bytes and time in, frames out).

Port 1 (commands and telemetry): ``'v'`` -> ``'V'`` :class:`Version`; ``'d'`` / ``'c'`` start periodic
``'D'`` :class:`DebugData` / ``'C'`` :class:`Data3D` at the requested interval (10 ms units, 0 stops),
each stopping ``stream_timeout_s`` (4 s, as MK's FlightCtrl) after the last request; ``'a'`` -> ``'A'``
debug labels; ``'s'`` :class:`AttitudeSetpoint` goes to the firmware; ``'b'`` :class:`ExternControl`
is acknowledged with ``'B'`` (the stack's firmware does not fly it); ``'S'`` :class:`BoardStatus` at
10 Hz and at once on every change of the arm state; ``'Z'`` :class:`BaroAltitude` at 50 Hz (the board's
barometric estimate, :mod:`sim_sitl.board_sensing`). Requests addressed to another node are ignored.
Port 2 carries only ``'I'`` :class:`ImuSample` at 500 Hz (built by the runner).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

from quadlink.mk.messages import (
    AttitudeSetpoint,
    BaroAltitude,
    BoardStatus,
    Data3D,
    Data3DRequest,
    DebugData,
    DebugLabel,
    DebugLabelRequest,
    DebugRequest,
    ExternControl,
    ExternControlAck,
    Version,
    VersionRequest,
    decode_message,
    encode_message,
)
from quadlink.mk.protocol import ADDR_ANY, ADDR_FC, FrameDecoder
from sim_sitl.board_estimators import BoardBaroEstimate
from sim_sitl.firmware import AttitudeCommand

log = logging.getLogger(__name__)

SITL_VERSION = Version(sw_major=2, sw_minor=1, proto_major=11, proto_minor=0, sw_patch=0)

DEBUG_LABELS = (
    "Roll 0.1deg", "Pitch 0.1deg", "Yaw 0.1deg", "Thrust %", "Motor1 cN", "Motor2 cN", "Motor3 cN", "Motor4 cN",
    "Battery 10mV", "Armed", "Flight state", "Setpoints/s", "Gyro x cnt", "Gyro y cnt", "Gyro z cnt", "Acc z cnt",
)


@dataclass(frozen=True)
class BoardTelemetry:
    """A snapshot of what the board reports."""

    t_s: float
    imu_sample_count: int
    armed: bool
    flight_state: int
    failsafe: bool
    battery_mv: int
    error_flags: int
    last_setpoint_seq: int
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    thrust_fraction: float
    motor_thrust_n: tuple[float, float, float, float]
    imu_counts: tuple[int, int, int, int, int, int] = (512,) * 6
    baro: BoardBaroEstimate | None = None   # the board's barometric estimate ('Z' at 50 Hz when given)


class _Stream:
    def __init__(self) -> None:
        self.interval_s = 0.0
        self.until_s = -1.0
        self.next_s = 0.0

    def request(self, interval_10ms: int, t_s: float, timeout_s: float) -> None:
        self.interval_s = interval_10ms * 0.01
        self.until_s = t_s + timeout_s if interval_10ms > 0 else -1.0
        self.next_s = t_s  # first frame at once

    def due(self, t_s: float) -> bool:
        if self.interval_s <= 0.0 or t_s > self.until_s or t_s + 1e-9 < self.next_s:
            return False
        self.next_s = max(self.next_s + self.interval_s, t_s - self.interval_s)
        return True


class Port1Protocol:
    def __init__(self, stream_timeout_s: float = 4.0, status_rate_hz: float = 10.0,
                 baro_rate_hz: float = 50.0) -> None:
        self.decoder = FrameDecoder()
        self.baro_period_s = 1.0 / baro_rate_hz
        self._next_baro_s = 0.0
        self._baro_seq = 0
        self.stream_timeout_s = stream_timeout_s
        self.status_period_s = 1.0 / status_rate_hz
        self._debug = _Stream()
        self._data3d = _Stream()
        self._next_status_s = 0.0
        self._last_armed: bool | None = None
        self.frames_received = 0
        self.frames_ignored = 0

    def on_bytes(self, data: bytes, t_s: float) -> tuple[list[AttitudeCommand], list[bytes]]:
        """Decode received bytes: setpoints for the firmware and the immediate replies (frames)."""
        commands: list[AttitudeCommand] = []
        replies: list[bytes] = []
        for frame in self.decoder.feed(data):
            if frame.address not in (ADDR_ANY, ADDR_FC):
                self.frames_ignored += 1
                continue
            msg = decode_message(frame)
            self.frames_received += 1
            if isinstance(msg, AttitudeSetpoint):
                commands.append(AttitudeCommand(msg.roll_rad, msg.pitch_rad, msg.yaw_rate_rad_s, msg.thrust,
                                                msg.armed, msg.seq))
            elif isinstance(msg, VersionRequest):
                replies.append(encode_message(SITL_VERSION))
            elif isinstance(msg, DebugRequest):
                self._debug.request(msg.interval_10ms, t_s, self.stream_timeout_s)
            elif isinstance(msg, Data3DRequest):
                self._data3d.request(msg.interval_10ms, t_s, self.stream_timeout_s)
            elif isinstance(msg, DebugLabelRequest):
                label = DEBUG_LABELS[msg.index] if msg.index < len(DEBUG_LABELS) else f"Analog{msg.index}"
                replies.append(encode_message(DebugLabel(msg.index, label)))
            elif isinstance(msg, ExternControl):
                replies.append(encode_message(ExternControlAck(msg.frame)))
            else:
                self.frames_ignored += 1
        return commands, replies

    @property
    def rx_frames_dropped(self) -> int:
        return int(self.decoder.stats.frames_dropped)

    def anything_due(self, t_s: float, armed: bool) -> bool:
        """Cheap check before building a telemetry snapshot for :meth:`poll`."""
        return (armed != self._last_armed or t_s + 1e-9 >= self._next_status_s or t_s + 1e-9 >= self._next_baro_s
                or (self._debug.interval_s > 0 and t_s + 1e-9 >= self._debug.next_s)
                or (self._data3d.interval_s > 0 and t_s + 1e-9 >= self._data3d.next_s))

    def poll(self, telem: BoardTelemetry) -> list[bytes]:
        """Periodic frames due at ``telem.t_s`` (status at 10 Hz and on arm change, requested streams)."""
        out: list[bytes] = []
        t = telem.t_s
        if telem.armed != self._last_armed or t + 1e-9 >= self._next_status_s:
            self._last_armed = telem.armed
            self._next_status_s = t + self.status_period_s
            out.append(encode_message(BoardStatus(
                armed=telem.armed, flight_state=telem.flight_state, failsafe=telem.failsafe,
                battery_mv=telem.battery_mv, error_flags=telem.error_flags,
                board_time_ms=int(round(telem.imu_sample_count * 2)) & 0xFFFFFFFF,
                imu_sample_count=telem.imu_sample_count, last_setpoint_seq=telem.last_setpoint_seq)))
        if telem.baro is not None and t + 1e-9 >= self._next_baro_s:
            self._next_baro_s = t + self.baro_period_s
            b = telem.baro
            out.append(encode_message(BaroAltitude(b.altitude_m, b.climb_m_s, float(b.pressure_pa), b.valid,
                                                   b.saturated, self._baro_seq)))
            self._baro_seq = (self._baro_seq + 1) & 0xFF
        if self._data3d.due(t):
            out.append(encode_message(Data3D(telem.roll_rad, telem.pitch_rad, telem.yaw_rad)))
        if self._debug.due(t):
            deci = math.degrees(1.0) * 10.0
            analog = [
                round(telem.roll_rad * deci), round(telem.pitch_rad * deci), round(telem.yaw_rad * deci),
                round(telem.thrust_fraction * 100.0), *(round(f * 100.0) for f in telem.motor_thrust_n),
                round(telem.battery_mv / 10.0), int(telem.armed), telem.flight_state, 0,
                telem.imu_counts[3], telem.imu_counts[4], telem.imu_counts[5], telem.imu_counts[2],
            ]
            out.append(encode_message(DebugData((int(telem.armed), telem.flight_state),
                                                tuple(analog + [0] * (32 - len(analog))))))
        return out

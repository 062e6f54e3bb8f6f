"""The ground station's vehicle link, 50 Hz (``mapping.rate_hz``): MAVLink in (telemetry,
TELEOP_FEEDBACK, acks, parameter echoes), MANUAL_CONTROL and HEARTBEAT out, buttons -> commands,
warnings and the CSV log.

TELEOP_FEEDBACK drives the force loop's motion input (the vehicle's velocity, alpha, gyro yaw rate and
the pan-scan rate removed in eq. (17): estimated from the gyro or the commanded one).
"""

from __future__ import annotations

import logging
import math
import queue
from dataclasses import replace
from typing import TYPE_CHECKING, Any

import numpy as np

from quadlink.client import CommandLong, GroundClient
from quadlink.mavlink import mavlink
from quadlink.mavlink.statustext import StatusTextAssembler
from quadlink.mavlink.timesync import NS, TimesyncConfig, TimesyncEstimator
from teleop.commands import OutgoingCommand
from teleop.delay import link_delay
from teleop.force import VehicleMotion
from teleop.force_loop import MotionInput
from teleop.mapping import map_device_to_command
from teleop.recording import CsvLog, csv_row
from teleop.telemetry import Feedback, Telemetry, apply_message
from teleop.view_loop import make_estimator

if TYPE_CHECKING:
    from teleop.station import Station

log = logging.getLogger(__name__)

MAX_MESSAGES_PER_TICK = 1000
TIMESYNC_PERIOD_S = 0.5      # TIMESYNC requests to the companion (the round trip on the page)
TIMESYNC_MAX_RTT_S = 2.0     # a ground link through the internet: round trips above this are stalled samples


def send_command(client: GroundClient, out: OutgoingCommand) -> None:
    """A COMMAND_LONG or PARAM_SET of the command tracker on the link (never waits: the tracker sees the acks)."""
    if out.kind == "command_long":
        client.send_command_long(CommandLong(out.command, out.params), out.confirmation, out.target_system,
                                 out.target_component)
    else:
        client.send_param_set(out.param_id, out.param_value, mavlink.MAV_PARAM_TYPE_REAL32, out.target_system,
                              out.target_component)


class VehicleLink:
    """The vehicle link of a :class:`teleop.station.Station`: :meth:`_receive` and :meth:`tick`, called by the
    station's one loop (:meth:`teleop.station.Station._loop`) on the wall clock or on the lock-step's simulated
    time."""

    def __init__(self, station: Station) -> None:
        self.station = station
        self.cfg = station.cfg
        self.estimator = make_estimator(station.cfg)
        self.sync = TimesyncEstimator(TimesyncConfig(max_rtt_s=TIMESYNC_MAX_RTT_S))
        self.statustexts = StatusTextAssembler()   # the vehicle's long texts come in chunks
        self.next_timesync = -math.inf             # on the station's clock (the first tick sends)
        self.receive_limited = False               # the last _receive stopped at its message limit

    def tick(self, client: GroundClient, t: float, tel: Telemetry, csv_log: CsvLog | None, t0: float) -> None:
        """One tick of the link at time ``t`` (the station's clock): buttons -> commands, MANUAL_CONTROL (with its
        COMMAND_STAMP), the 1 Hz HEARTBEAT, the TIMESYNC request, the published state and the CSV row."""
        st, cfg = self.station, self.cfg
        self._buttons(client, tel, t)
        # operator command, eqs. (2)-(3), after its send time (COMMAND_STAMP, issue 18)
        force = st.force
        q = force.device.q_m if force else np.zeros(3)
        cmd = map_device_to_command(q, cfg.mapping, cfg.device)
        client.send_manual_control(cmd.x, cmd.y, cmd.z, cmd.r, cmd.buttons)
        st.manual_control_sent += 1
        client.heartbeat_if_due(t)
        if t >= self.next_timesync:
            self.next_timesync = t + TIMESYNC_PERIOD_S
            client.send_timesync_request()
        delay = link_delay(self.sync)
        st._set_link_state(tel, cmd, t, delay)
        if csv_log is not None:
            csv_log.write(csv_row(t - t0, force, cmd, tel, st._motion, delay))

    def _receive(self, client: GroundClient, tel: Telemetry, t: float) -> Telemetry:
        """Handle the messages readable now (at most MAX_MESSAGES_PER_TICK), received at ``t``."""
        cfg = self.cfg
        ap = (cfg.commands.autopilot_system, cfg.commands.autopilot_component)
        self.receive_limited = True
        for _ in range(MAX_MESSAGES_PER_TICK):
            msg = client.receive()   # never waits; a socket error reads as nothing
            if msg is None:
                self.receive_limited = False
                break
            mtype = msg.get_type()
            if mtype == "TIMESYNC":
                self._on_timesync(client, msg)
                continue
            if mtype == "STATUSTEXT":
                text = self.statustexts.add(msg)
                if text is None:   # a chunk of a longer text
                    continue
                tel = replace(tel, last_statustext=text, statustext_t_s=t)
                if msg.severity <= mavlink.MAV_SEVERITY_WARNING:
                    log.warning("vehicle says: %s", text)
                continue
            tel = apply_message(tel, msg, t, ap, cfg.commands.companion_component)
            if mtype == "TELEOP_FEEDBACK" and tel.feedback is not None:
                self._on_feedback(tel.feedback, t)
            elif mtype == "COMMAND_ACK":
                self.station._ack(self.station.commands.on_command_ack(msg.command, msg.result, t))
            elif mtype == "PARAM_VALUE":
                pid = msg.param_id if isinstance(msg.param_id, str) else msg.param_id.decode(errors="ignore")
                self.station._ack(self.station.commands.on_param_value(pid.rstrip("\x00"), msg.param_value, t))
        return tel

    def _on_timesync(self, client: GroundClient, msg: Any) -> None:
        """TIMESYNC with the companion only (the autopilot's, routed through it, are not our peer's clock)."""
        if msg.get_srcComponent() != self.cfg.commands.companion_component:
            return
        # a request: the companion ages our commands with its estimate of our clock (the stamps' clock)
        if not client.answer_timesync(msg):
            self.sync.on_response(msg.tc1, msg.ts1, int(self.station.clock() * NS))

    def _on_feedback(self, fb: Feedback, t: float) -> None:
        st, cfg = self.station, self.cfg
        est = self.estimator.update(fb.gyro_yaw_rate_rad_s, fb.time_usec * 1e-6, fb.pan_scan_on,
                                    fb.yaw_rate_cmd_rad_s - fb.pan_scan_yaw_rate_rad_s)
        st._pan_scan_hz = est.frequency_hz
        ps = (est.yaw_rate_rad_s if cfg.force.pan_scan_source == "estimated"
              else fb.pan_scan_yaw_rate_rad_s if fb.pan_scan_on else 0.0)
        st._motion = MotionInput(t, VehicleMotion(fb.v_h_m_s, fb.alpha_rad, fb.gyro_yaw_rate_rad_s, ps),
                                 fb.mode in cfg.force.cue_modes)
        if st._force_proc is not None:
            st._force_proc.set_motion(st._motion, fb.time_usec * 1e-6)

    def _buttons(self, client: GroundClient, tel: Telemetry, t: float) -> None:
        st = self.station
        presses = st._force_proc.buttons() if st._force_proc is not None else []
        while True:
            try:
                presses.append(st._buttons.get_nowait())
            except queue.Empty:
                break
        for button in presses:
            if button == "quit":
                log.info("quit pressed")
                st.stop_event.set()
                continue
            out = st.commands.build(button, tel.feedback.pan_scan_on if tel.feedback else False)
            if out is not None:
                log.info("button %s -> %s", button, out.name)
                send_command(client, st.commands.submit(out, t))
        resend, failed = st.commands.poll(t)
        for out in resend:
            send_command(client, out)
        for result in failed:
            st._ack(result)


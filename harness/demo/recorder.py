"""Watch MAVLink UDP streams while the demo flies (the latest truth state, the vehicle's armed state, the truth's
senders); it records nothing.

One thread per endpoint (blocking reads with a timeout); :meth:`Recorder.stop` joins them. A listener's socket
drops datagrams when its thread is starved, so the flight's logs are written by their senders (the SITL's
``--truth-tlog``, the bridge's ``--tlog``); what this listener lost is counted from the MAVLink sequence numbers
(:attr:`Recorder.lost`) and logged.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass
from typing import Any

from quadlink.ids import GROUND_COMPONENT_ID, GROUND_SYSTEM_ID, TRUTH_SENSOR_ANY_SURFACE, TRUTH_SENSOR_NON_FLOOR
from quadlink.mavlink import mavlink
from quadlink.mavlink.connection import open_mavlink

log = logging.getLogger(__name__)


@dataclass
class TruthState:
    """Latest ground truth seen on the SITL's truth stream (for progress lines only)."""

    sim_time_s: float = float("nan")
    position_ned_m: tuple[float, float, float] = (float("nan"),) * 3
    velocity_ned_m_s: tuple[float, float, float] = (float("nan"),) * 3
    nearest_m: float = float("nan")
    nearest_obstacle_m: float = float("nan")
    messages: int = 0


class Recorder:
    def __init__(self) -> None:
        self._threads: list[threading.Thread] = []
        self._stop = threading.Event()
        self.truth = TruthState()
        self.vehicle_armed: bool | None = None   # from the autopilot's HEARTBEAT on a non-truth stream
        self.counts: dict[str, int] = {}
        self.lost: dict[str, int] = {}   # packets a stream's sequence numbers say this listener missed
        self.truth_senders: set[Any] = set()   # the addresses the truth came from: more than one voids the judgement

    def watch(self, name: str, url: str, is_truth: bool = False) -> None:
        """Listen on ``url`` until :meth:`stop`."""
        conn = open_mavlink(url, source_system=GROUND_SYSTEM_ID, source_component=GROUND_COMPONENT_ID)
        self.counts[name] = 0
        self.lost[name] = 0
        thread = threading.Thread(target=self._loop, args=(name, conn, is_truth), name=f"rec-{name}", daemon=True)
        thread.start()
        self._threads.append(thread)
        log.info("watching %s on %s", name, url)

    def _loop(self, name: str, conn: Any, is_truth: bool) -> None:
        try:
            while not self._stop.is_set():
                self._on_message(name, conn.recv_match(blocking=True, timeout=0.2), is_truth)
                if is_truth:
                    self._note_senders(conn)
            # what the senders sent before they stopped is still in the socket: read it, so the counts, the missed
            # packets and the truth senders' check cover the whole flight
            while (msg := conn.recv_match(blocking=False)) is not None:
                self._on_message(name, msg, is_truth)
            if is_truth:
                self._note_senders(conn)
            self.lost[name] = int(getattr(conn, "mav_loss", 0))
            if self.lost[name]:
                log.warning("%s: this listener missed at least %d of %d packets (a starved process; the sender's "
                            "own log has them)", name, self.lost[name], self.lost[name] + self.counts[name])
        finally:
            conn.close()

    def _note_senders(self, conn: Any) -> None:
        """Every address the truth came from (pymavlink's ``clients`` of a ``udpin``): a second SITL sending its
        truth to this port (a test's, on the default ports) would interleave another vehicle into the track."""
        senders = getattr(conn, "clients", None)
        if senders is not None and len(senders) > len(self.truth_senders):
            self.truth_senders |= set(senders)
            if len(self.truth_senders) > 1:
                log.error("ground truth from %d senders (%s): another SITL sends to this port; the judgement is "
                          "void", len(self.truth_senders), ", ".join(f"{h}:{p}" for h, p in sorted(self.truth_senders)))

    def _on_message(self, name: str, msg: Any, is_truth: bool) -> None:
        if msg is None or msg.get_type() == "BAD_DATA":
            return
        self.counts[name] += 1
        if is_truth:
            self._update_truth(msg)
        elif msg.get_type() == "HEARTBEAT" and msg.get_srcComponent() == mavlink.MAV_COMP_ID_AUTOPILOT1:
            self.vehicle_armed = bool(msg.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)

    def _update_truth(self, msg: Any) -> None:
        kind = msg.get_type()
        t = self.truth
        t.messages += 1
        if kind == "LOCAL_POSITION_NED":
            t.sim_time_s = msg.time_boot_ms / 1000.0
            t.position_ned_m = (msg.x, msg.y, msg.z)
            t.velocity_ned_m_s = (msg.vx, msg.vy, msg.vz)
        elif kind == "DISTANCE_SENSOR":
            if msg.id == TRUTH_SENSOR_ANY_SURFACE:
                t.nearest_m = msg.current_distance / 100.0
            elif msg.id == TRUTH_SENSOR_NON_FLOOR:
                t.nearest_obstacle_m = msg.current_distance / 100.0

    def stop(self) -> None:
        self._stop.set()
        for thread in self._threads:
            thread.join(timeout=2.0)

"""Ground truth for evaluation over MAVLink 2 (system id 250); the flight code never reads it.

Messages, stamped with simulated time (``time_boot_ms``), at ``truth_rate_hz``:
``LOCAL_POSITION_NED`` (true position and velocity, local NED with its origin at the start position),
``ATTITUDE_QUATERNION`` (true attitude [w, x, y, z] body FRD -> NED, true body rates),
``DISTANCE_SENSOR`` id 0 (centre of mass to the nearest surface of any kind) and id 1 (nearest
surface excluding floor and ceiling), in cm, plus a 1 Hz ``HEARTBEAT``.

:class:`TruthEncoder` is I/O-free (the dialect's codec); :class:`UdpTruthSink` sends its bytes.
"""

from __future__ import annotations

import logging
import math
import socket

import numpy as np
from numpy.typing import NDArray

from quadlink.errors import LinkError
from quadlink.frames import quat_wxyz_from_R
from quadlink.ids import TRUTH_COMPONENT_ID, TRUTH_SENSOR_ANY_SURFACE, TRUTH_SENSOR_NON_FLOOR, TRUTH_SYSTEM_ID
from quadlink.mavlink import mavlink

log = logging.getLogger(__name__)

TRUTH_SYSID = TRUTH_SYSTEM_ID
TRUTH_COMPID = TRUTH_COMPONENT_ID
DISTANCE_MAX_CM = 2000


class TruthEncoder:
    def __init__(self, system_id: int = TRUTH_SYSID, component_id: int = TRUTH_COMPID) -> None:
        self.mav = mavlink.MAVLink(None, srcSystem=system_id, srcComponent=component_id)
        self._last_heartbeat_ms: int | None = None

    def _pack(self, msg: object) -> bytes:
        """Pack one message with the next sequence number (a listener counts its losses by them)."""
        buf = bytes(msg.pack(self.mav))  # type: ignore[attr-defined]
        self.mav.seq = (self.mav.seq + 1) % 256
        return buf

    def encode(self, t_s: float, p_local_ned_m: NDArray[np.float64], v_ned_m_s: NDArray[np.float64],
               R_ned_q: NDArray[np.float64], omega_q_rad_s: NDArray[np.float64], nearest_any_m: float,
               nearest_obstacle_m: float) -> list[bytes]:
        ms = int(round(t_s * 1000.0)) & 0xFFFFFFFF
        out = []
        if self._last_heartbeat_ms is None or ms - self._last_heartbeat_ms >= 1000:
            self._last_heartbeat_ms = ms
            out.append(self._pack(mavlink.MAVLink_heartbeat_message(
                mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, mavlink.MAV_STATE_ACTIVE, 3)))
        p, v = np.asarray(p_local_ned_m, dtype=float), np.asarray(v_ned_m_s, dtype=float)
        out.append(self._pack(mavlink.MAVLink_local_position_ned_message(ms, *map(float, p), *map(float, v))))
        q = [float(x) for x in quat_wxyz_from_R(R_ned_q)]
        w = [float(x) for x in np.asarray(omega_q_rad_s, dtype=float)]
        out.append(self._pack(mavlink.MAVLink_attitude_quaternion_message(ms, q[0], q[1], q[2], q[3], w[0], w[1], w[2],
                                                                          [0.0, 0.0, 0.0, 0.0])))
        for sensor_id, d_m in ((TRUTH_SENSOR_ANY_SURFACE, nearest_any_m), (TRUTH_SENSOR_NON_FLOOR, nearest_obstacle_m)):
            d_cm = DISTANCE_MAX_CM + 1 if not math.isfinite(d_m) else min(int(round(d_m * 100.0)), DISTANCE_MAX_CM + 1)
            out.append(self._pack(mavlink.MAVLink_distance_sensor_message(
                ms, 0, DISTANCE_MAX_CM, d_cm, mavlink.MAV_DISTANCE_SENSOR_UNKNOWN, sensor_id,
                mavlink.MAV_SENSOR_ROTATION_NONE, 0, 0.0, 0.0, [0.0, 0.0, 0.0, 0.0], 100)))
        return out


class UdpTruthSink:
    """Sends datagrams to ``udpout:HOST:PORT`` (one MAVLink message per datagram, like mavutil)."""

    def __init__(self, url: str) -> None:
        if not url.startswith("udpout:"):
            raise LinkError(f"{url}: truth endpoint must be udpout:HOST:PORT")
        host, _, port = url[len("udpout:"):].rpartition(":")
        try:
            self.address = (host or "127.0.0.1", int(port))
        except ValueError as exc:
            raise LinkError(f"{url}: bad port in truth endpoint") from exc
        self.url = url
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setblocking(False)
        self.errors = 0

    def send(self, packets: list[bytes]) -> None:
        for pkt in packets:
            try:
                self.sock.sendto(pkt, self.address)
            except OSError:  # nobody listening (ICMP refused) or buffer full: truth is best-effort
                self.errors += 1

    def close(self) -> None:
        self.sock.close()

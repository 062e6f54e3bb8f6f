"""The ground client: one pymavlink link to the vehicle, its sends, what it heard, and bounded waits.

Two kinds of call, kept apart on purpose (a flight loop never waits on a peer):

* ``send_*``, :meth:`GroundClient.heartbeat_if_due`, :meth:`GroundClient.receive` and
  :meth:`GroundClient.drain` never block: the ground station's 50 Hz loop and the lock-step participants use
  only these.
* :meth:`GroundClient.command`, :meth:`GroundClient.arm` ..., :meth:`GroundClient.get_param`,
  :meth:`GroundClient.set_param`, :meth:`GroundClient.wait_heartbeat` and :meth:`GroundClient.wait_message` send
  and then wait for the answer, with a timeout on the client's injected clock; :class:`LinkTimeout` names what did
  not come. For scripts and tools, never for a loop that streams setpoints.

Every received message updates :class:`VehicleState` (the vehicle's heartbeat, its clock and the companion's mode
from TELEOP_FEEDBACK) and is handed to ``on_message`` if one is given, also those read during a wait.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from quadlink.client import commands
from quadlink.client.commands import CommandLong, command_name
from quadlink.client.setpoints import TIME_BOOT_MS_MASK, PositionTarget
from quadlink.errors import LinkTimeout, ProtocolError
from quadlink.ids import COMPANION_COMPONENT_ID, GROUND_COMPONENT_ID, GROUND_SYSTEM_ID, VEHICLE_SYSTEM_ID
from quadlink.mavlink import mavlink
from quadlink.mavlink.connection import open_mavlink
from quadlink.mavlink.param_service import decode_param_value, encode_param_value, param_name
from quadlink.mavlink.security import enable_signing
from quadlink.mavlink.timesync import NS, answer_fields, is_request, request_fields
from quadlink.px4_modes import Px4Mode

log = logging.getLogger(__name__)

HEARTBEAT_PERIOD_S = 1.0        # a ground station's HEARTBEAT, as QGroundControl and MAVSDK send it
DEFAULT_TIMEOUT_S = 3.0         # a blocking call's wait for its answer
POLL_S = 0.01                   # longest sleep of a wait between two reads (a real link wakes it on data)
US = 1_000_000                  # microseconds per second (COMMAND_STAMP.time_usec)
S_PER_US = 1e-6
MANUAL_CONTROL_MSG_ID = mavlink.MAVLINK_MSG_ID_MANUAL_CONTROL
RESULT_NAMES = {v: k.removeprefix("MAV_RESULT_") for k, v in vars(mavlink).items()
                if k.startswith("MAV_RESULT_") and isinstance(v, int) and k != "MAV_RESULT_ENUM_END"}


class CommandRejected(ProtocolError):
    """The vehicle answered a command with a COMMAND_ACK other than ACCEPTED."""

    def __init__(self, command: int, result: int, sender: tuple[int, int]) -> None:
        super().__init__(f"{command_name(command)} refused by {sender[0]}/{sender[1]}: "
                         f"{RESULT_NAMES.get(result, str(result))}")
        self.command = command
        self.result = result


@dataclass(frozen=True)
class Signing:
    """MAVLink 2 signing of everything the client sends (:func:`quadlink.mavlink.security.enable_signing`):
    the 32-byte key (``read_key(FILE)``), the stream's link id (distinct per ground station sharing a system
    id) and whether unsigned packets from the vehicle are refused."""

    key: bytes
    link_id: int = 0
    require: bool = False

    def enable(self, mav: Any) -> None:
        """Sign what ``mav`` (a link's pymavlink codec) sends from now on; check what it receives."""
        enable_signing(mav, self.key, require=self.require, link_id=self.link_id)


@dataclass
class VehicleState:
    """What the client has heard of the vehicle (``target_system``) so far; None: not yet."""

    heartbeat_s: float | None = None   # the client's clock when the last vehicle HEARTBEAT arrived
    time_s: float | None = None        # the vehicle's clock (TELEOP_FEEDBACK.time_usec), s
    teleop_mode: int | None = None     # QUADLINK_TELEOP_MODE of the companion (TELEOP_FEEDBACK)
    teleop_flags: int = 0              # QUADLINK_TELEOP_FLAGS (TELEOP_FEEDBACK)


class GroundClient:
    """A ground station's link to one vehicle: ``conn`` (a pymavlink ``mavfile``, :func:`connect` opens one),
    the default target of its messages (system ``target_system``, component ``target_component``: the companion,
    whose mode machine and safety layer every command and setpoint goes through) and ``clock``, the clock of its
    heartbeat, COMMAND_STAMP, TIMESYNC answers and waits (wall, or a lock-step's simulated time)."""

    def __init__(self, conn: Any, target_system: int = VEHICLE_SYSTEM_ID,
                 target_component: int = COMPANION_COMPONENT_ID, clock: Callable[[], float] = time.monotonic,
                 on_message: Callable[[Any], None] | None = None) -> None:
        self.conn = conn
        self.target_system = target_system
        self.target_component = target_component
        self.state = VehicleState()
        self.on_message = on_message
        self._clock = clock
        self._next_heartbeat_s = float("-inf")

    def close(self) -> None:
        self.conn.close()

    # ---- receiving (never blocks) ------------------------------------------------------------
    def receive(self) -> Any | None:
        """The next message readable now, or None (nothing, or a transient socket error: logged). BAD_DATA
        is skipped; the message updates :attr:`state` and goes to ``on_message``."""
        while True:
            try:
                msg = self.conn.recv_msg()
            except (OSError, ValueError) as exc:   # a bad datagram or a transient socket error
                log.debug("MAVLink receive: %s", exc)
                return None
            if msg is None or msg.get_type() != "BAD_DATA":
                break
        if msg is not None:
            self._update_state(msg)
            if self.on_message is not None:
                self.on_message(msg)
        return msg

    def drain(self, limit: int = 100_000) -> list[Any]:
        """Every message readable now (at most ``limit``: a flood cannot hold the caller)."""
        out: list[Any] = []
        while len(out) < limit and (msg := self.receive()) is not None:
            out.append(msg)
        return out

    def wait_readable(self, timeout_s: float) -> None:
        """Block up to ``timeout_s`` for data on the link (the link's own select)."""
        self.conn.select(timeout_s)

    def _update_state(self, msg: Any) -> None:
        if msg.get_srcSystem() != self.target_system:
            return
        kind = msg.get_type()
        if kind == "HEARTBEAT" and msg.type != mavlink.MAV_TYPE_GCS:
            self.state.heartbeat_s = self._clock()
        elif kind == "TELEOP_FEEDBACK":
            self.state.time_s = msg.time_usec * S_PER_US   # (not / US: the lock-step plans' times, to the ulp)
            self.state.teleop_mode, self.state.teleop_flags = msg.mode, msg.flags

    # ---- sending (never blocks) --------------------------------------------------------------
    def _target(self, system: int | None, component: int | None) -> tuple[int, int]:
        return (self.target_system if system is None else system,
                self.target_component if component is None else component)

    def send_heartbeat(self) -> None:
        self.conn.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0,
                                     mavlink.MAV_STATE_ACTIVE)

    def heartbeat_if_due(self, now_s: float | None = None) -> bool:
        """The 1 Hz GCS HEARTBEAT at ``now_s`` (default: the client's clock); the first call sends. Sent?"""
        now_s = self._clock() if now_s is None else now_s
        if now_s < self._next_heartbeat_s:
            return False
        self._next_heartbeat_s = now_s + HEARTBEAT_PERIOD_S
        self.send_heartbeat()
        return True

    def send_command_long(self, cmd: CommandLong, confirmation: int = 0, target_system: int | None = None,
                          target_component: int | None = None) -> None:
        """``cmd`` as a COMMAND_LONG (``confirmation``: the retry counter of MAVLink's command protocol)."""
        self.conn.mav.command_long_send(*self._target(target_system, target_component), cmd.command, confirmation,
                                        *cmd.params)

    def send_param_set(self, name: str, value: float, param_type: int = mavlink.MAV_PARAM_TYPE_REAL32,
                       target_system: int | None = None, target_component: int | None = None) -> None:
        """PARAM_SET of ``name`` (integers encoded bytewise, as PX4 and :mod:`quadlink.mavlink.param_service`)."""
        self.conn.mav.param_set_send(*self._target(target_system, target_component), name.encode("ascii"),
                                     encode_param_value(value, param_type), param_type)

    def send_param_request_read(self, name: str, target_system: int | None = None,
                                target_component: int | None = None) -> None:
        self.conn.mav.param_request_read_send(*self._target(target_system, target_component), name.encode("ascii"),
                                              -1)

    def send_position_target(self, sp: PositionTarget, time_boot_ms: int, target_system: int | None = None,
                             target_component: int | None = None) -> None:
        """``sp`` as SET_POSITION_TARGET_LOCAL_NED stamped ``time_boot_ms`` (wrapped to 32 bits)."""
        self.conn.mav.set_position_target_local_ned_send(
            int(time_boot_ms) & TIME_BOOT_MS_MASK, *self._target(target_system, target_component), sp.frame,
            sp.type_mask, sp.x_m, sp.y_m, sp.z_m, sp.vx_m_s, sp.vy_m_s, sp.vz_m_s, sp.ax_m_s2, sp.ay_m_s2, sp.az_m_s2,
            sp.yaw_rad, sp.yaw_rate_rad_s)

    def send_manual_control(self, x: int, y: int, z: int, r: int, buttons: int, stamped: bool = True) -> None:
        """MANUAL_CONTROL to ``target_system`` (axes in -1000..1000, z 0..1000 as MAVLink's), preceded by its
        COMMAND_STAMP (the send time on the client's clock, to ``target_component``: issue 18, the very next
        packet of this sender is the command it stamps) unless ``stamped`` is False."""
        if stamped:
            self.conn.mav.command_stamp_send(int(self._clock() * US), MANUAL_CONTROL_MSG_ID, self.target_system,
                                             self.target_component)
        self.conn.mav.manual_control_send(self.target_system, x, y, z, r, buttons)

    def send_timesync_request(self) -> None:
        """A TIMESYNC request stamped with the client's clock."""
        self.conn.mav.timesync_send(*request_fields(int(self._clock() * NS)))

    def answer_timesync(self, msg: Any) -> bool:
        """Answer ``msg`` if it is a TIMESYNC request (with the clock the COMMAND_STAMPs carry, so the peer can age
        our commands); False for a response (the caller's estimator wants it)."""
        if not is_request(msg.tc1):
            return False
        self.conn.mav.timesync_send(*answer_fields(msg.ts1, int(self._clock() * NS)))
        return True

    # ---- waiting (blocks, with a timeout on the client's clock) ------------------------------
    def wait_message(self, match: Callable[[Any], bool], timeout_s: float, what: str) -> Any:
        """The first message read from now on for which ``match`` is true; :class:`LinkTimeout` naming ``what``
        if none comes within ``timeout_s``."""
        deadline_s = self._clock() + timeout_s
        while (remaining_s := deadline_s - self._clock()) > 0.0:
            msg = self.receive()
            if msg is None:
                self.wait_readable(min(remaining_s, POLL_S))
            elif match(msg):
                return msg
        raise LinkTimeout(f"no {what} within {timeout_s:g} s")

    def wait_heartbeat(self, timeout_s: float = DEFAULT_TIMEOUT_S, component: int | None = None) -> Any:
        """The vehicle's next HEARTBEAT (from ``component`` if given; a ground station's never counts)."""
        def match(m: Any) -> bool:
            return (m.get_type() == "HEARTBEAT" and m.type != mavlink.MAV_TYPE_GCS
                    and m.get_srcSystem() == self.target_system
                    and (component is None or m.get_srcComponent() == component))

        who = self.target_system if component is None else f"{self.target_system}/{component}"
        return self.wait_message(match, timeout_s, f"HEARTBEAT from the vehicle {who}")

    def command(self, cmd: CommandLong, timeout_s: float = DEFAULT_TIMEOUT_S, target_system: int | None = None,
                target_component: int | None = None) -> None:
        """Send ``cmd`` and wait for its COMMAND_ACK (IN_PROGRESS: waits on); :class:`CommandRejected` unless
        ACCEPTED, :class:`LinkTimeout` if no final ack comes within ``timeout_s``. No retry: call again."""
        target = self._target(target_system, target_component)
        self.send_command_long(cmd, target_system=target[0], target_component=target[1])

        def match(m: Any) -> bool:
            return (m.get_type() == "COMMAND_ACK" and m.command == cmd.command
                    and m.result != mavlink.MAV_RESULT_IN_PROGRESS
                    and (m.get_srcSystem(), m.get_srcComponent()) == target)

        ack = self.wait_message(match, timeout_s, f"COMMAND_ACK for {cmd.name} from {target[0]}/{target[1]}")
        if ack.result != mavlink.MAV_RESULT_ACCEPTED:
            raise CommandRejected(cmd.command, ack.result, target)

    def arm(self, timeout_s: float = DEFAULT_TIMEOUT_S) -> None:
        self.command(commands.arm_command(), timeout_s)

    def disarm(self, timeout_s: float = DEFAULT_TIMEOUT_S) -> None:
        self.command(commands.disarm_command(), timeout_s)

    def takeoff(self, altitude_m: float, timeout_s: float = DEFAULT_TIMEOUT_S) -> None:
        self.command(commands.takeoff_command(altitude_m), timeout_s)

    def land(self, timeout_s: float = DEFAULT_TIMEOUT_S) -> None:
        self.command(commands.land_command(), timeout_s)

    def set_px4_mode(self, mode: Px4Mode, timeout_s: float = DEFAULT_TIMEOUT_S) -> None:
        self.command(commands.set_px4_mode_command(mode), timeout_s)

    def wait_teleop_mode(self, modes: tuple[int, ...], timeout_s: float) -> int:
        """Wait until the companion reports one of ``modes`` (QUADLINK_TELEOP_MODE, TELEOP_FEEDBACK); that mode."""
        if self.state.teleop_mode not in modes:
            names = "/".join(mavlink.enums["QUADLINK_TELEOP_MODE"][m].name for m in modes)
            self.wait_message(lambda m: self.state.teleop_mode in modes, timeout_s, f"TELEOP_FEEDBACK in {names}")
        assert self.state.teleop_mode is not None
        return self.state.teleop_mode

    def _wait_param_value(self, name: str, timeout_s: float, target: tuple[int, int]) -> float:
        def match(m: Any) -> bool:
            return (m.get_type() == "PARAM_VALUE" and param_name(m.param_id) == name
                    and (m.get_srcSystem(), m.get_srcComponent()) == target)

        msg = self.wait_message(match, timeout_s, f"PARAM_VALUE {name} from {target[0]}/{target[1]}")
        return decode_param_value(float(msg.param_value), int(msg.param_type))

    def get_param(self, name: str, timeout_s: float = DEFAULT_TIMEOUT_S, target_system: int | None = None,
                  target_component: int | None = None) -> float:
        """PARAM_REQUEST_READ of ``name``; its value from the PARAM_VALUE answer."""
        target = self._target(target_system, target_component)
        self.send_param_request_read(name, *target)
        return self._wait_param_value(name, timeout_s, target)

    def set_param(self, name: str, value: float, param_type: int = mavlink.MAV_PARAM_TYPE_REAL32,
                  timeout_s: float = DEFAULT_TIMEOUT_S, target_system: int | None = None,
                  target_component: int | None = None) -> float:
        """PARAM_SET of ``name``; the value the vehicle echoes (a refused set echoes the unchanged value)."""
        target = self._target(target_system, target_component)
        self.send_param_set(name, value, param_type, *target)
        return self._wait_param_value(name, timeout_s, target)


def connect(url: str, system_id: int = GROUND_SYSTEM_ID, component_id: int = GROUND_COMPONENT_ID,
            target_system: int = VEHICLE_SYSTEM_ID, target_component: int = COMPANION_COMPONENT_ID,
            signing: Signing | None = None, clock: Callable[[], float] = time.monotonic,
            on_message: Callable[[Any], None] | None = None) -> GroundClient:
    """Open ``url`` (pymavlink's: ``udpout:HOST:PORT``, ``udpin:HOST:PORT``, ``tcp:HOST:PORT``, ``/dev/ttyUSB0:57600``)
    as a ground station (``system_id``/``component_id``: 255/190, as QGroundControl and MAVProxy), signed when
    ``signing`` is given; :class:`quadlink.errors.LinkError` if it cannot be opened. Nothing is sent yet."""
    conn = open_mavlink(url, source_system=system_id, source_component=component_id)
    if signing is not None:
        signing.enable(conn.mav)
        log.info("%s signed (link id %d, unsigned packets %s)", url, signing.link_id,
                 "refused" if signing.require else "accepted")
    return GroundClient(conn, target_system, target_component, clock, on_message)

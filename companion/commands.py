"""Commands to the autopilot with acknowledgement, retries and timeouts (pure: time is an argument).

One command in flight at a time, in order (arm before takeoff): :meth:`CommandQueue.poll` returns the
COMMAND_LONG to (re)send, :meth:`CommandQueue.on_ack` consumes COMMAND_ACKs. A command with no ack after
``retries`` resends (``confirmation`` incremented, as MAVLink's command protocol asks) or with a
DENIED/FAILED result is dropped together with the commands queued behind it and reported as failed.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

from companion.modes import AutopilotRequest
from quadlink.mavlink import mavlink
from quadlink.px4_modes import Px4MainMode


@dataclass(frozen=True)
class CommandLong:
    """A COMMAND_LONG's command id and params 1..7."""

    command: int
    params: tuple[float, float, float, float, float, float, float]


def command_for(request: AutopilotRequest) -> CommandLong:
    """The standard MAVLink command for an :class:`AutopilotRequest` (PX4 semantics)."""
    nan = float("nan")
    if request.name == "arm":
        return CommandLong(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, (1.0, 0, 0, 0, 0, 0, 0))
    if request.name == "disarm":
        return CommandLong(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, (0.0, 0, 0, 0, 0, 0, 0))
    if request.name == "takeoff":  # param7: altitude; PX4 takes it as AMSL, the bridge as relative (documented)
        return CommandLong(mavlink.MAV_CMD_NAV_TAKEOFF, (0, 0, 0, nan, nan, nan, request.altitude_m))
    if request.name == "land":
        return CommandLong(mavlink.MAV_CMD_NAV_LAND, (0, 0, 0, nan, nan, nan, nan))
    if request.name == "offboard":
        return CommandLong(mavlink.MAV_CMD_DO_SET_MODE,
                           (float(mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED), float(Px4MainMode.OFFBOARD),
                            0, 0, 0, 0, 0))
    raise ValueError(f"unknown autopilot request {request.name!r}")


@dataclass
class _Pending:
    request: AutopilotRequest
    command: CommandLong
    sent_s: float | None = None
    attempts: int = 0
    in_progress: bool = False


@dataclass
class CommandQueue:
    ack_timeout_s: float = 0.5
    retries: int = 3
    in_progress_timeout_s: float = 5.0
    _queue: deque[_Pending] = field(default_factory=deque)

    def push(self, request: AutopilotRequest) -> None:
        self._queue.append(_Pending(request, command_for(request)))

    @property
    def pending(self) -> list[AutopilotRequest]:
        return [p.request for p in self._queue]

    def poll(self, now_s: float) -> tuple[list[tuple[CommandLong, int]], list[tuple[AutopilotRequest, str]]]:
        """(commands to send now as (command, confirmation)), (failed requests with a reason)."""
        failed: list[tuple[AutopilotRequest, str]] = []
        while self._queue:
            head = self._queue[0]
            timeout = self.in_progress_timeout_s if head.in_progress else self.ack_timeout_s
            if head.sent_s is not None and now_s - head.sent_s < timeout:
                return [], failed
            if head.attempts > self.retries or (head.in_progress and head.sent_s is not None):
                failed += self._fail_all("no acknowledgement")
                continue
            head.sent_s = now_s
            head.attempts += 1
            return [(head.command, head.attempts - 1)], failed
        return [], failed

    def _fail_all(self, reason: str) -> list[tuple[AutopilotRequest, str]]:
        out = [(p.request, reason) for p in self._queue]
        self._queue.clear()
        return out

    def on_ack(self, command: int, result: int, now_s: float) -> tuple[AutopilotRequest | None,
                                                                      list[tuple[AutopilotRequest, str]]]:
        """Consume a COMMAND_ACK: (the request it completed, failed requests)."""
        if not self._queue or self._queue[0].command.command != command:
            return None, []
        head = self._queue[0]
        if result == mavlink.MAV_RESULT_IN_PROGRESS:
            head.in_progress, head.sent_s = True, now_s
            return None, []
        if result == mavlink.MAV_RESULT_ACCEPTED:
            self._queue.popleft()
            head.sent_s = None
            return head.request, []
        name = mavlink.enums["MAV_RESULT"][result].name if result in mavlink.enums["MAV_RESULT"] else str(result)
        return None, self._fail_all(name)

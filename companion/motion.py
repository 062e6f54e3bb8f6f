"""The motion arbiter's command as the loop takes it (pure: the clock is injected; STATUSTEXT goes to ``tell``).

At camera rate (and at the fallback rate while the camera is silent) the daemon asks the arbiter
(:class:`companion.arbiter.Arbiter`) for its command. :class:`Motion` tells the arbiter's transitions (a source
engaged, lost, refused) to the ground stations as STATUSTEXT and logs a change of source; gives the operator's
handle to the reference only while the arbiter gives the operator control and the newest command is fresh
(:meth:`companion.command_age.CommandAgeFilter.fresh`: an older one zeroes the input); and says which mode
TELEOP_FEEDBACK reports (HOLD while the mode machine is in TELEOP but no source commands motion).
"""

from __future__ import annotations

import logging
from collections.abc import Callable

from companion.arbiter import Arbiter, MotionCommand, Pose, Source
from companion.command_age import CommandAgeFilter
from companion.modes import Mode, StatusText
from companion.operator_input import OperatorInput
from quadlink.mavlink import mavlink

log = logging.getLogger("companion.daemon")


class Motion:
    """``arbiter``: the motion arbiter; ``command_age``: the ground stations' command filter; ``clock``: monotonic
    seconds (the arbiter's and the commands' time); ``tell``: where the arbiter's STATUSTEXT go."""

    def __init__(self, arbiter: Arbiter, command_age: CommandAgeFilter, clock: Callable[[], float],
                 tell: Callable[[StatusText], None]) -> None:
        self.arbiter, self.command_age = arbiter, command_age
        self._clock, self._tell = clock, tell
        self.last: MotionCommand | None = None   # the last command the loop took

    def command(self, pose: Pose) -> MotionCommand:
        """The arbiter's command now, the vehicle at ``pose``; its transitions told as STATUSTEXT."""
        cmd = self.arbiter.command(self._clock(), pose)
        for text in self.arbiter.take_events():
            self._tell(StatusText(mavlink.MAV_SEVERITY_WARNING if "lost" in text else mavlink.MAV_SEVERITY_INFO,
                                  f"companion: {text}"))
        if self.last is None or cmd.source != self.last.source:
            log.info("motion source: %s (%s)", cmd.source.name, cmd.reason)
        self.last = cmd
        return cmd

    def operator_of(self, cmd: MotionCommand) -> OperatorInput:
        """The operator's input when the arbiter gives the operator control and its command is fresh."""
        if cmd.source != Source.OPERATOR or cmd.operator is None or not self.command_age.fresh(self._clock()):
            return OperatorInput()
        return cmd.operator

    def reported_mode(self, mode: Mode) -> Mode:
        """The mode machine's ``mode``, HOLD while it is TELEOP but no source commands motion (the arbiter holds)."""
        if mode == Mode.TELEOP and self.last is not None and self.last.hold:
            return Mode.HOLD
        return mode

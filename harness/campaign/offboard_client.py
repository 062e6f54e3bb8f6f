"""A scripted offboard operator (issue 15): what a MAVSDK script does, in plain pymavlink.

``python -m harness.campaign.offboard_client --vehicle udpout:127.0.0.1:14555 --plan PLAN.yaml``

Connects to the companion's ground-station endpoint, sends a 1 Hz GCS HEARTBEAT, arms and takes off
through the companion (COMMAND_LONG to component 191, as the ground station does), switches to PX4's
OFFBOARD mode (MAV_CMD_DO_SET_MODE, custom mode from :mod:`quadlink.px4_modes`) and then streams
SET_POSITION_TARGET_LOCAL_NED velocity setpoints at 20 Hz like MAVSDK's ``set_velocity_body``
(MAV_FRAME_BODY_NED, velocity + yaw rate) and ``set_velocity_ned`` (MAV_FRAME_LOCAL_NED, velocity + yaw);
at the end it commands LAND. The plan's timeline runs on the vehicle's clock (TELEOP_FEEDBACK
``time_usec``, simulated time in the SITL) from the first vehicle time it hears, as the ground station's
scripts do, so a lock-step flight sees the same setpoints at the same simulated time after the client
joined whatever the machine's load.

The plan (written by :func:`harness.campaign.sessions.generate_session`)::

    takeoff_s: 10.0        # offboard starts here (vehicle time)
    landing_s: 8.0
    duration_s: 40.0
    segments:              # one after the other from takeoff_s
      - {frame: body, forward_m_s: 0.3, right_m_s: 0.3, down_m_s: 0.0, yawspeed_deg_s: 0.0, duration_s: 3.0}
      - {frame: ned, north_m_s: 0.2, east_m_s: 0.0, down_m_s: 0.0, yaw_deg: 90.0, duration_s: 2.0}

Whether the companion shapes these setpoints with its safety layer is the companion's business (issue
14); this client only speaks the protocol, through :class:`quadlink.client.GroundClient`.

With ``--lockstep tcp://HOST:PORT`` the client is the ``operator`` participant of the SITL's deterministic
lock-step (:mod:`quadlink.lockstep`): it sends nothing until the coordinator's first STEP, then, per step,
handles exactly the companion datagrams the step announces (``companion>operator``), runs its heartbeat on the
step's simulated time and its plan on the vehicle time those messages carry, sends, and answers DONE with the
datagrams it has sent (``operator>companion``). Nothing it sends depends on the wall clock or on scheduling,
so two flights of the same draws see the same datagrams at the same steps. At the plan's end it answers the
step and leaves the lock-step (the flight goes on without it).
"""

from __future__ import annotations

import logging
import math
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import click
import yaml

from quadlink.client import (
    CommandLong,
    GroundClient,
    PositionTarget,
    arm_command,
    connect,
    land_command,
    takeoff_command,
    velocity_body,
    velocity_ned,
)
from quadlink.errors import ConfigError, QuadlinkError
from quadlink.lockstep import DEFAULT_INPUT_TIMEOUT_S, CountedMavlink, LockstepClient, LockstepError, wait_for_units
from quadlink.mavlink import mavlink
from quadlink.px4_modes import OFFBOARD

log = logging.getLogger("harness.campaign.offboard")

SETPOINT_PERIOD_S = 0.05  # MAVSDK streams offboard setpoints at 20 Hz
TAKEOFF_HEIGHT_M = 1.0
#: DO_SET_MODE OFFBOARD as this client has always sent it, to the companion (191): param2 carries the whole
#: custom_mode (6 << 16) where PX4 reads the main mode (6, :func:`quadlink.client.set_px4_mode_command`). The companion
#: refuses it (DENIED: param2 outside 0..255), so the stream's first setpoint is what engages offboard; kept as
#: flown so that the campaigns' figures stay comparable (docs/limits.md)
OFFBOARD_AS_FLOWN = CommandLong(mavlink.MAV_CMD_DO_SET_MODE, (float(mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED),
                                                              float(OFFBOARD.custom_mode), 0.0, 0.0, 0.0, 0.0, 0.0))
LOCKSTEP_NAME = "operator"
LINK_IN = "companion>operator"     # datagrams the companion sends us (lock-step input link)
LINK_OUT = "operator>companion"    # datagrams we send the companion (lock-step output link)
MAX_MESSAGES_PER_DRAIN = 100_000   # a runaway parse cannot hang a step


def setpoint_at(plan: dict[str, Any], t_s: float) -> PositionTarget | None:
    """The plan's setpoint at vehicle time ``t_s`` (pure); None before take-off-plus-offboard and after."""
    t = plan["takeoff_s"]
    if t_s < t:
        return None
    for seg in plan["segments"]:
        if t_s < t + seg["duration_s"]:
            if seg.get("frame", "body") == "body":
                return velocity_body(seg.get("forward_m_s", 0.0), seg.get("right_m_s", 0.0), seg.get("down_m_s", 0.0),
                                     math.radians(seg.get("yawspeed_deg_s", 0.0)))
            return velocity_ned(seg.get("north_m_s", 0.0), seg.get("east_m_s", 0.0), seg.get("down_m_s", 0.0),
                                math.radians(seg.get("yaw_deg", 0.0)))
        t += seg["duration_s"]
    return None


def plan_end_s(plan: dict[str, Any]) -> float:
    return float(plan["takeoff_s"] + sum(s["duration_s"] for s in plan["segments"]))


def load_plan(path: Path) -> dict[str, Any]:
    try:
        plan = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise ConfigError(f"{path}: cannot read offboard plan: {exc}") from exc
    if not isinstance(plan, dict) or "segments" not in plan or "takeoff_s" not in plan:
        raise ConfigError(f"{path}: an offboard plan needs takeoff_s and segments")
    return plan


class OffboardClient:
    """The I/O side: one ground client (commands and setpoints to the companion), driven by :meth:`run` (wall
    clock) or :meth:`run_lockstep`.

    The timers are split from the I/O so that both modes share them: :meth:`handle` takes one received
    message, :meth:`heartbeat` runs the 1 Hz GCS heartbeat on a given clock (wall or simulated) and
    :meth:`plan_tick` sends what the plan asks at the vehicle time received so far.
    """

    def __init__(self, client: GroundClient, plan: dict[str, Any]) -> None:
        self.client = client
        self.plan = plan
        self.origin_s: float | None = None  # vehicle time when the plan started
        self._done: set[str] = set()
        self._next_sp_s = 0.0                # plan time of the next setpoint
        self.end_s = plan_end_s(plan)
        self.total_s = float(plan.get("duration_s", self.end_s + plan.get("landing_s", 8.0)))

    @property
    def vehicle_t_s(self) -> float | None:
        """The plan's clock: the vehicle time of the latest TELEOP_FEEDBACK (the client's state), s."""
        return self.client.state.time_s

    def handle(self, msg: Any) -> None:
        """One received message (TELEOP_FEEDBACK already moved the client's vehicle time)."""
        if msg.get_type() == "STATUSTEXT":
            log.info("vehicle: %s", msg.text)

    def _pump(self, timeout_s: float) -> None:
        self.client.wait_readable(timeout_s)
        self.drain()

    def drain(self) -> int:
        """Handle every message readable now (in lock-step: up to the step's allowance); how many."""
        messages = self.client.drain(MAX_MESSAGES_PER_DRAIN)
        for msg in messages:
            self.handle(msg)
        return len(messages)

    def heartbeat(self, now_s: float) -> None:
        """The 1 Hz GCS heartbeat, on the caller's clock (the first call sends)."""
        self.client.heartbeat_if_due(now_s)

    def _once(self, name: str, due: bool) -> bool:
        if due and name not in self._done:
            self._done.add(name)
            return True
        return False

    def plan_time_s(self) -> float | None:
        """Seconds into the plan (vehicle time since the first TELEOP_FEEDBACK), None before any."""
        if self.vehicle_t_s is None:
            return None
        if self.origin_s is None:
            self.origin_s = self.vehicle_t_s
        return self.vehicle_t_s - self.origin_s

    def plan_tick(self) -> bool:
        """Send what the plan asks at the vehicle time received so far; True once the plan is over."""
        t = self.plan_time_s()
        if t is None:
            return False
        if self._once("arm", t >= 2.0):
            self.client.send_command_long(arm_command())
        if self._once("takeoff", t >= 3.0):
            self.client.send_command_long(takeoff_command(TAKEOFF_HEIGHT_M))
        sp = setpoint_at(self.plan, t)
        if sp is not None and t >= self._next_sp_s:
            self._next_sp_s = t + SETPOINT_PERIOD_S
            self.client.send_position_target(sp, int((self.vehicle_t_s or 0.0) * 1000))
            # PX4 wants setpoints streaming before the switch (MAVSDK offboard.start() sends one first)
            if self._once("offboard", True):
                self.client.send_command_long(OFFBOARD_AS_FLOWN)
        if self._once("land", t >= self.end_s):
            self.client.send_command_long(land_command())
        return t >= self.total_s

    def run(self, wall_timeout_s: float) -> int:
        """Without lock-step: heartbeat on the wall clock, plan on the vehicle time as it arrives."""
        deadline = time.monotonic() + wall_timeout_s
        while time.monotonic() < deadline:
            self.heartbeat(time.monotonic())
            self._pump(0.01)
            if self.plan_tick():
                return 0
        log.error("vehicle time did not reach %.1f s within %.0f s of wall time", self.total_s, wall_timeout_s)
        return 1

    def run_lockstep(self, client: LockstepClient, counted: CountedMavlink,
                     stop: Callable[[], bool] = lambda: False,
                     input_timeout_s: float = DEFAULT_INPUT_TIMEOUT_S) -> int:
        """The lock-step participant's loop (``hello`` already sent); 0 at the plan's end.

        Per STEP: read and handle the companion's datagrams up to the announced count (never one more: a
        datagram that came early waits for its step), heartbeat on the step's simulated time, the plan on
        the vehicle time received, then DONE with our datagrams sent so far. Raises :class:`LockstepError`
        when the coordinator is gone or an announced datagram does not come.
        """
        while not stop():
            step = client.next_step()
            if step is None:
                continue
            allow = step.count(LINK_IN)
            counted.allow = allow

            def pump(block_s: float) -> None:
                counted.wait_readable(block_s)
                self.drain()

            self.drain()
            wait_for_units(lambda: counted.received, allow, pump, f"{LINK_IN} at step {step.index}",
                           input_timeout_s)
            self.drain()   # the last datagram's further messages (pymavlink parses one per call)
            self.heartbeat(step.t_s)
            finished = self.plan_tick()
            client.done({LINK_OUT: counted.sent})
            if finished:
                log.info("plan finished at step %d (simulated %.2f s, vehicle %.2f s); leaving the lock-step",
                         step.index, step.t_s, self.vehicle_t_s or 0.0)
                return 0
        return 0


def open_lockstep(conn: Any, url: str) -> tuple[LockstepClient, CountedMavlink]:
    """Count the link's datagrams, join the coordinator as ``operator`` and say hello (nothing sent yet)."""
    counted = CountedMavlink(conn)
    client = LockstepClient(url, LOCKSTEP_NAME)
    client.hello({LINK_OUT: counted.sent})
    return client, counted


@click.command()
@click.option("--vehicle", required=True, help="companion ground-station endpoint, e.g. udpout:127.0.0.1:14555")
@click.option("--plan", "plan_path", required=True, type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("--wall-timeout", default=900.0, show_default=True,
              help="give up after this many wall seconds (not with --lockstep: the coordinator's timeouts apply)")
@click.option("--lockstep", "lockstep_url", default=None, metavar="tcp://HOST:PORT",
              help="join the SITL's deterministic lock-step as the 'operator' participant (quadlink.lockstep)")
def main(vehicle: str, plan_path: Path, wall_timeout: float, lockstep_url: str | None) -> None:
    """Fly an offboard velocity plan through the companion (pymavlink, MAVSDK-style setpoints)."""
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname).1s %(name)s: %(message)s")
    try:
        plan = load_plan(plan_path)
        ground = connect(vehicle)   # 255/190 to the companion, 1/191
    except QuadlinkError as exc:
        click.echo(f"offboard_client: error: {exc}", err=True)
        sys.exit(2)
    client: LockstepClient | None = None
    try:
        offboard = OffboardClient(ground, plan)
        if lockstep_url is None:
            code = offboard.run(wall_timeout)
        else:
            client, counted = open_lockstep(ground.conn, lockstep_url)
            code = offboard.run_lockstep(client, counted)
    except LockstepError as exc:   # the coordinator is gone (the SITL ended or died) or a datagram never came
        log.error("lock-step: %s", exc)
        click.echo(f"offboard_client: error: {exc}", err=True)
        code = 1
    except KeyboardInterrupt:  # the orchestrator stops its parts with SIGINT
        code = 0
    finally:
        if client is not None:
            client.close()
        ground.close()
    sys.exit(code)


if __name__ == "__main__":
    main()

"""Flight modes and safety of the companion: a pure state machine (no clock, no I/O).

Modes (the dialect's QUADLINK_TELEOP_MODE, TELEOP_FEEDBACK.mode): IDLE, TAKEOFF, TELEOP, HOLD, LAND.

* IDLE: on the ground or not in control. Ground-station ``takeoff`` -> arm + takeoff commands to the
  autopilot -> TAKEOFF. ``arm`` / ``disarm`` are passed on as commands. A takeoff commanded to the
  autopilot directly (a ground station talking to compid 1 through the routing) is followed too: the
  autopilot reporting its takeoff -> TAKEOFF.
* TAKEOFF: waits for the autopilot to finish its takeoff (in air and no longer in its takeoff mode; or,
  for an autopilot without EXTENDED_SYS_STATE, armed for ``takeoff_timeout_s``), then asks for offboard
  mode -> TELEOP. Disarmed (after having armed, or never armed within the timeout) or a refused
  command -> IDLE.
* TELEOP: operator command + pan-scan + repulsion.
* HOLD: zero operator command, repulsion still active (hover). Entered when the ground-station link is
  lost (no MANUAL_CONTROL for ``gcs_timeout_s``) or the odometry fails (bad for ``odometry_fail_s``:
  single bad frames are bridged by the estimator); left to TELEOP when both are
  good again (odometry good for ``odometry_recover_s``); -> LAND when the link stays lost for
  ``gcs_land_timeout_s`` or the odometry stays bad for ``odometry_land_timeout_s``.
* A live link is not a live operator: heartbeats keep the link, but when no fresh motion command (an
  operator's MANUAL_CONTROL or a script's setpoint, :meth:`ModeMachine.on_motion_command`) has arrived for
  ``gcs_land_timeout_s`` — a link so delayed that every command is dropped as stale, or a script that
  stopped — TELEOP and HOLD -> LAND, as PX4's RC-loss failsafe lands with a ground station still
  connected. Before the first command after take-off, or after the ground station switched to a hold
  mode (MAVSDK's ``offboard.stop()``), the vehicle holds as PX4 does.
* LAND: land command to the autopilot; -> IDLE when the autopilot reports landed or disarmed. The
  autopilot reporting that it lands (commanded by someone else, or its own failsafe) -> LAND.
* Where it lands (:mod:`companion.landing_spot`): a ground station's ``land`` over an object the map holds
  below the vehicle is refused. One over ground the camera has not seen (:mod:`companion.seen_ground`) is
  accepted and first moves to seen ground, as a failsafe landing moves clear (the same HOLD, ``clearing_spot``
  set); a ground station's mode change ends it. A failsafe landing (no fresh command, link lost) over an object
  first moves clear of it — HOLD with :attr:`ModeMachine.clearing_spot` set, the daemon flying away from the
  object through the same safety pipeline — and lands once the spot below is clear, or after
  ``land_clear_timeout_s`` wherever it is. With the odometry failed the vehicle cannot move safely: it lands
  where it is.

Every transition returns a :class:`StatusText` action (the daemon logs it and sends STATUSTEXT) and
the autopilot commands to send as :class:`AutopilotRequest` actions (the daemon sends them with acks
and reports failures back with :meth:`ModeMachine.on_request_failed`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from enum import IntEnum

from quadlink.mavlink import mavlink


class Mode(IntEnum):
    """The dialect's QUADLINK_TELEOP_MODE (TELEOP_FEEDBACK.mode and the companion's HEARTBEAT custom_mode)."""

    IDLE = mavlink.QUADLINK_TELEOP_MODE_IDLE
    TAKEOFF = mavlink.QUADLINK_TELEOP_MODE_TAKEOFF
    TELEOP = mavlink.QUADLINK_TELEOP_MODE_TELEOP
    HOLD = mavlink.QUADLINK_TELEOP_MODE_HOLD
    LAND = mavlink.QUADLINK_TELEOP_MODE_LAND


@dataclass(frozen=True)
class ModeParams:
    gcs_timeout_s: float = 0.5
    gcs_land_timeout_s: float = 10.0
    odometry_fail_s: float = 0.2  # failed this long (consecutive) before it counts: one bad frame is no failure
    odometry_recover_s: float = 0.5
    odometry_land_timeout_s: float = 5.0
    takeoff_altitude_m: float = 1.0
    takeoff_timeout_s: float = 8.0
    takeoff_min_s: float = 1.0
    land_clear_timeout_s: float = 30.0   # a failsafe landing moves clear of an object below this long at most
    land_clear_hold_s: float = 1.0       # ... and lands once the spot has stayed clear this long (the map
                                         # samples a desk's top sparsely: one clear look is not a clear spot)


@dataclass(frozen=True)
class VehicleStatus:
    """What the autopilot reports (HEARTBEAT, EXTENDED_SYS_STATE): armed, in air, in its takeoff mode."""

    armed: bool = False
    in_air: bool = False
    taking_off: bool = False
    landing: bool = False
    reports_landed_state: bool = False  # EXTENDED_SYS_STATE seen: no need to guess the end of the takeoff


@dataclass(frozen=True)
class AutopilotRequest:
    """A command for the autopilot: ``arm``, ``disarm``, ``takeoff`` (altitude_m), ``land``, ``offboard``."""

    name: str
    altitude_m: float = 0.0


@dataclass(frozen=True)
class StatusText:
    """A transition or event to log and send as STATUSTEXT (MAV_SEVERITY_* numbering)."""

    severity: int
    text: str


SEVERITY_CRITICAL = 2
SEVERITY_WARNING = 4
SEVERITY_NOTICE = 5
SEVERITY_INFO = 6

@dataclass(frozen=True)
class SpotRefusal:
    """Why the spot under the vehicle is no place to land: ``text``, the STATUSTEXT body; ``unseen``: only
    because the camera has not seen the ground there (no object seen below), so a commanded landing can move
    to seen ground first instead of being refused."""

    text: str
    unseen: bool = False


Action = AutopilotRequest | StatusText
LandRefusal = str | None | Callable[[], str | None]
GCS_REQUESTS = ("arm", "disarm", "takeoff", "land")


class ModeMachine:
    """The companion's modes; feed it time, link and vehicle state with :meth:`update`."""

    def __init__(self, params: ModeParams) -> None:
        self.params = params
        self.mode = Mode.IDLE
        self.reason = "start"
        self._entered_s = 0.0
        self._last_manual_s: float | None = None
        self._last_command_s: float | None = None
        self._takeoff_s = -float("inf")
        self._odometry_ok_since_s: float | None = None
        self._odometry_bad_since_s: float | None = None
        self.gcs_ok = False
        self.odometry_ok = False
        self._armed_in_takeoff = False
        self._clearing_since_s: float | None = None   # a failsafe landing moving clear of an object below
        self._commanded_clearing = False              # ... started by a ground station's land (unseen ground)
        self._clear_since_s: float | None = None      # ... and since when the spot below has looked clear

    # --- inputs -----------------------------------------------------------------------------
    def on_manual_control(self, now_s: float) -> None:
        self._last_manual_s = now_s

    def on_motion_command(self, stamp_s: float | None) -> None:
        """The newest fresh motion command (operator or script) arrived at ``stamp_s``; None: none is
        expected (none yet, or the ground station asked for a hold)."""
        self._last_command_s = stamp_s

    @property
    def operator_enabled(self) -> bool:
        return self.mode == Mode.TELEOP

    @property
    def in_control(self) -> bool:
        """The companion streams meaningful setpoints (the autopilot is meant to follow them)."""
        return self.mode in (Mode.TELEOP, Mode.HOLD)

    @property
    def clearing_spot(self) -> bool:
        """A landing is moving clear of an object below the vehicle, or to seen ground (HOLD; the daemon flies
        it away): a failsafe's, or a ground station's over unseen ground."""
        return self._clearing_since_s is not None and self.mode == Mode.HOLD

    @property
    def commanded_clearing(self) -> bool:
        """The landing moving to seen ground is a ground station's (not a failsafe's)."""
        return self._commanded_clearing and self.clearing_spot

    def end_commanded_clearing(self, now_s: float) -> list[Action]:
        """A ground station's mode change while its landing moves to seen ground: the landing is called off
        (as a mode change ends PX4's LAND) and the vehicle is the operator's or the script's again."""
        if not self.commanded_clearing:
            return []
        return self._go(Mode.TELEOP, now_s, "ground-station mode change: land called off", SEVERITY_NOTICE)

    def time_in_mode_s(self, now_s: float) -> float:
        return now_s - self._entered_s

    def _go(self, mode: Mode, now_s: float, reason: str, severity: int = SEVERITY_INFO) -> list[Action]:
        old = self.mode
        self._armed_in_takeoff = False
        self._clearing_since_s, self._commanded_clearing = None, False
        self.mode, self.reason, self._entered_s = mode, reason, now_s
        if mode == Mode.TAKEOFF:
            self._takeoff_s = now_s   # a flight's commands count from its take-off
        return [StatusText(severity, f"companion: {old.name} -> {mode.name} ({reason})")]

    def request(self, name: str, now_s: float, status: VehicleStatus,
                land_refusal: SpotRefusal | None = None) -> tuple[bool, list[Action]]:
        """A ground-station command (``arm``, ``disarm``, ``takeoff``, ``land``): accepted?, actions.
        ``land_refusal``: why the spot under the vehicle is no place to land (companion.landing_spot), if it is
        not: a commanded landing in flight is then refused, or, over ground only unseen, accepted and moved to
        seen ground first (the failsafe landings are not asked)."""
        if name not in GCS_REQUESTS:
            return False, []
        if name == "arm":
            if self.mode != Mode.IDLE:
                return False, []
            return True, [AutopilotRequest("arm")]
        if name == "disarm":
            if status.in_air and self.mode != Mode.IDLE:
                return False, [StatusText(SEVERITY_WARNING, "companion: disarm refused in flight (land first)")]
            return True, [AutopilotRequest("disarm")]
        if name == "takeoff":
            if self.mode != Mode.IDLE:
                return False, []
            actions: list[Action] = [] if status.armed else [AutopilotRequest("arm")]
            actions.append(AutopilotRequest("takeoff", self.params.takeoff_altitude_m))
            return True, actions + self._go(Mode.TAKEOFF, now_s, "ground-station takeoff")
        # land
        if self.mode in (Mode.IDLE, Mode.LAND):
            return self.mode == Mode.LAND, []
        if land_refusal is not None and self.mode in (Mode.TELEOP, Mode.HOLD):
            if not land_refusal.unseen:
                return False, [StatusText(SEVERITY_WARNING, f"companion: {land_refusal.text}")]
            if self._commanded_clearing:
                return True, []
            actions = self._land_clear_of_objects(now_s, "ground-station land", land_refusal.text,
                                                  self.odometry_ok, SEVERITY_NOTICE)
            self._commanded_clearing = self.clearing_spot
            return True, actions
        return True, [AutopilotRequest("land")] + self._go(Mode.LAND, now_s, "ground-station land")

    def on_request_failed(self, request: AutopilotRequest, now_s: float, detail: str) -> list[Action]:
        """The autopilot refused a command or never acknowledged it."""
        text = StatusText(SEVERITY_WARNING, f"companion: autopilot {request.name} failed ({detail})")
        if request.name in ("arm", "takeoff") and self.mode == Mode.TAKEOFF:
            return [text] + self._go(Mode.IDLE, now_s, f"{request.name} refused", SEVERITY_WARNING)
        if request.name == "offboard" and self.mode in (Mode.TELEOP, Mode.HOLD):
            # Without offboard the autopilot keeps its own hold; we cannot fly, so land.
            actions: list[Action] = [text, AutopilotRequest("land")]
            return actions + self._go(Mode.LAND, now_s, "offboard refused", SEVERITY_WARNING)
        return [text]

    # --- the periodic step ------------------------------------------------------------------
    def _land_clear_of_objects(self, now_s: float, reason: str, land_refusal: LandRefusal, can_move: bool,
                               severity: int = SEVERITY_WARNING) -> list[Action]:
        """A landing that must not come down on an object: a failsafe's, or a ground station's over unseen
        ground. At once, or first moving clear of an object below (``land_refusal``: why the spot is no place to
        land) while ``can_move`` and for at most ``land_clear_timeout_s``."""
        p = self.params
        if callable(land_refusal):
            land_refusal = land_refusal()
        if land_refusal is not None and can_move and self._clearing_since_s is None:
            actions = [] if self.mode == Mode.HOLD else self._go(Mode.HOLD, now_s, reason, severity)
            self._clearing_since_s, self._clear_since_s = now_s, None
            return actions + [StatusText(severity, f"companion: {reason}: {land_refusal}, moving clear")]
        if self._clearing_since_s is not None and can_move:
            if land_refusal is not None:
                self._clear_since_s = None
            elif self._clear_since_s is None:
                self._clear_since_s = now_s
            clear_long_enough = self._clear_since_s is not None and now_s - self._clear_since_s >= p.land_clear_hold_s
            if not clear_long_enough and now_s - self._clearing_since_s < p.land_clear_timeout_s:
                return []
            if not clear_long_enough:
                reason += ", could not clear the object below"
        return [AutopilotRequest("land")] + self._go(Mode.LAND, now_s, reason,
                                                     SEVERITY_CRITICAL if severity == SEVERITY_WARNING else severity)

    def update(self, now_s: float, status: VehicleStatus, odometry_ok: bool,
               land_refusal: LandRefusal = None) -> list[Action]:
        """The periodic step; ``land_refusal``: why the spot below the vehicle is no place to land, if it is not
        (a failsafe landing then moves clear first), or a function giving it, asked only when a failsafe landing
        is due (the daemon's looks at the whole map: not on every frame)."""
        p = self.params
        actions: list[Action] = []
        gcs_ok = self._last_manual_s is not None and now_s - self._last_manual_s <= p.gcs_timeout_s
        if gcs_ok != self.gcs_ok:
            actions.append(StatusText(SEVERITY_NOTICE if gcs_ok else SEVERITY_WARNING,
                                      "companion: ground-station link " + ("ok" if gcs_ok else "lost")))
        self.gcs_ok = gcs_ok
        if odometry_ok:
            self._odometry_bad_since_s = None
            if self._odometry_ok_since_s is None:
                self._odometry_ok_since_s = now_s
        else:
            self._odometry_ok_since_s = None
            if self._odometry_bad_since_s is None:
                self._odometry_bad_since_s = now_s
        failed = self._odometry_bad_since_s is not None and now_s - self._odometry_bad_since_s >= p.odometry_fail_s
        usable = not failed
        if usable != self.odometry_ok:
            actions.append(StatusText(SEVERITY_NOTICE if usable else SEVERITY_CRITICAL,
                                      "companion: odometry " + ("ok" if usable else "failed")))
        self.odometry_ok = usable
        odo_good = self._odometry_ok_since_s is not None and now_s - self._odometry_ok_since_s >= p.odometry_recover_s
        in_mode = now_s - self._entered_s

        if self.mode == Mode.IDLE and status.armed and status.taking_off:
            actions += self._go(Mode.TAKEOFF, now_s, "autopilot taking off")
        elif self.mode in (Mode.TAKEOFF, Mode.TELEOP, Mode.HOLD) and status.armed and status.landing:
            actions += self._go(Mode.LAND, now_s, "autopilot landing", SEVERITY_NOTICE)
        elif self.mode == Mode.TAKEOFF:
            self._armed_in_takeoff = self._armed_in_takeoff or status.armed
            if not status.armed and (self._armed_in_takeoff or in_mode > p.takeoff_timeout_s):
                actions += self._go(Mode.IDLE, now_s, "disarmed during takeoff", SEVERITY_WARNING)
            elif status.armed and ((status.in_air and not status.taking_off and in_mode >= p.takeoff_min_s)
                                   or (in_mode >= p.takeoff_timeout_s and not status.reports_landed_state)):
                actions.append(AutopilotRequest("offboard"))
                actions += self._go(Mode.TELEOP, now_s, "takeoff complete")
        elif self.mode in (Mode.TELEOP, Mode.HOLD):
            last = self._last_command_s
            silent_for = None if last is None or last < self._takeoff_s else now_s - last
            if not status.armed:
                actions += self._go(Mode.IDLE, now_s, "autopilot disarmed", SEVERITY_WARNING)
            elif self.commanded_clearing:   # a ground station's land, moving to seen ground first
                actions += self._land_clear_of_objects(now_s, "ground-station land", land_refusal, usable,
                                                       SEVERITY_NOTICE)
            elif silent_for is not None and silent_for >= p.gcs_land_timeout_s:
                actions += self._land_clear_of_objects(now_s, f"no fresh command for {p.gcs_land_timeout_s:g} s",
                                                       land_refusal, usable)
            elif self.mode == Mode.TELEOP and failed:
                actions += self._go(Mode.HOLD, now_s, "odometry failed", SEVERITY_CRITICAL)
            elif self.mode == Mode.TELEOP and not gcs_ok:
                actions += self._go(Mode.HOLD, now_s, "ground-station link lost", SEVERITY_WARNING)
            elif self.mode == Mode.HOLD:
                lost_for = now_s - self._last_manual_s if self._last_manual_s is not None else in_mode
                bad_for = now_s - self._odometry_bad_since_s if self._odometry_bad_since_s is not None else 0.0
                if not gcs_ok and lost_for >= p.gcs_land_timeout_s:
                    actions += self._land_clear_of_objects(now_s, "ground-station link lost too long",
                                                           land_refusal, usable)
                elif failed and bad_for >= p.odometry_land_timeout_s:
                    actions.append(AutopilotRequest("land"))
                    actions += self._go(Mode.LAND, now_s, "odometry failed too long", SEVERITY_CRITICAL)
                elif gcs_ok and odo_good:
                    actions += self._go(Mode.TELEOP, now_s, "link and odometry ok")
        elif self.mode == Mode.LAND:
            if not status.armed or (not status.in_air and in_mode > 1.0):
                actions += self._go(Mode.IDLE, now_s, "landed")
        return actions

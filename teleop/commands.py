"""Buttons -> vehicle commands with acknowledgements checked (pure: time passed in).

arm / disarm / takeoff / land are COMMAND_LONG to the vehicle (sysid 1; compid 191, the companion, whose
mode machine forwards them to the autopilot; ``commands.command_component``), acknowledged by COMMAND_ACK;
pan-scan on/off is a PARAM_SET of ``PANSCAN_EN`` on the companion (compid 191),
acknowledged by the PARAM_VALUE echo. Unacknowledged requests are re-sent (COMMAND_LONG with the
``confirmation`` counter incremented, as MAVLink's command protocol asks) and reported as timed out
after the last retry.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from quadlink.client import RESULT_NAMES as ACK_RESULT_NAMES
from quadlink.client import CommandLong, arm_command, disarm_command, land_command, takeoff_command
from quadlink.mavlink import mavlink
from teleop.config import CommandsConfig


@dataclass(frozen=True)
class OutgoingCommand:
    """A message to send: ``kind`` is 'command_long' or 'param_set'."""

    name: str
    kind: str
    target_system: int
    target_component: int
    command: int = 0
    params: tuple[float, float, float, float, float, float, float] = (0.0,) * 7
    param_id: str = ""
    param_value: float = 0.0
    confirmation: int = 0


@dataclass(frozen=True)
class CommandResult:
    name: str
    accepted: bool
    text: str          # shown on the page and in the terminal
    t_s: float


@dataclass(frozen=True)
class _Pending:
    out: OutgoingCommand
    sent_t_s: float
    attempts: int


class CommandTracker:
    def __init__(self, cfg: CommandsConfig) -> None:
        self.cfg = cfg
        self._pending: dict[str, _Pending] = {}

    def build(self, button: str, pan_scan_on: bool | None = None) -> OutgoingCommand | None:
        c = self.cfg
        commands: dict[str, CommandLong] = {"arm": arm_command(), "disarm": disarm_command(),
                                            "takeoff": takeoff_command(c.takeoff_altitude_m), "land": land_command()}
        if button in commands:
            cmd = commands[button]
            return OutgoingCommand(button, "command_long", c.autopilot_system, c.command_component, cmd.command,
                                   cmd.params)
        if button in ("pan_scan_on", "pan_scan_off", "pan_scan_toggle"):
            on = button == "pan_scan_on" or (button == "pan_scan_toggle" and not pan_scan_on)
            return OutgoingCommand("pan_scan_on" if on else "pan_scan_off", "param_set", c.autopilot_system,
                                   c.companion_component, param_id=c.pan_scan_param, param_value=1.0 if on else 0.0)
        return None

    def submit(self, out: OutgoingCommand, t_s: float) -> OutgoingCommand:
        key = self._key(out)
        self._pending[key] = _Pending(out, t_s, 1)
        return out

    @staticmethod
    def _key(out: OutgoingCommand) -> str:
        return f"cmd{out.command}" if out.kind == "command_long" else f"param:{out.param_id}"

    @property
    def pending(self) -> tuple[str, ...]:
        return tuple(p.out.name for p in self._pending.values())

    def on_command_ack(self, command: int, result: int, t_s: float) -> CommandResult | None:
        p = self._pending.get(f"cmd{command}")
        if p is None:
            return None
        if result == mavlink.MAV_RESULT_IN_PROGRESS:
            self._pending[f"cmd{command}"] = replace(p, sent_t_s=t_s)
            return CommandResult(p.out.name, True, f"{p.out.name}: in progress", t_s)
        del self._pending[f"cmd{command}"]
        name = ACK_RESULT_NAMES.get(result, str(result))
        return CommandResult(p.out.name, result == mavlink.MAV_RESULT_ACCEPTED, f"{p.out.name}: {name}", t_s)

    def on_param_value(self, param_id: str, value: float, t_s: float) -> CommandResult | None:
        p = self._pending.get(f"param:{param_id}")
        if p is None:
            return None
        del self._pending[f"param:{param_id}"]
        ok = abs(value - p.out.param_value) < 1e-6
        text = f"{p.out.name}: ACCEPTED" if ok else f"{p.out.name}: REJECTED ({param_id} is {value:g})"
        return CommandResult(p.out.name, ok, text, t_s)

    def poll(self, t_s: float) -> tuple[list[OutgoingCommand], list[CommandResult]]:
        """Re-sends due and timeouts given up at ``t_s``."""
        resend: list[OutgoingCommand] = []
        failed: list[CommandResult] = []
        for key, p in list(self._pending.items()):
            if t_s - p.sent_t_s < self.cfg.ack_timeout_s:
                continue
            if p.attempts > self.cfg.retries:
                del self._pending[key]
                failed.append(CommandResult(p.out.name, False, f"{p.out.name}: no ack after {p.attempts} tries", t_s))
                continue
            out = replace(p.out, confirmation=min(p.out.confirmation + 1, 255))
            self._pending[key] = _Pending(out, t_s, p.attempts + 1)
            resend.append(out)
        return resend, failed

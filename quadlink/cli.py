"""The ``quadlink`` console entry point: one click group, one subcommand per part of the stack.

Subcommands live with the package that owns them (``sim_sitl/cli.py`` and so on, each exposing a
click command named ``command``) and are imported only when run, so ``quadlink --help`` is fast
and a broken optional dependency of one part does not take the others down.
"""

from __future__ import annotations

import importlib
import logging
import sys

import click

from quadlink import __version__
from quadlink.errors import QuadlinkError

#: subcommand -> (module providing ``command``, one-line help)
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "sitl": ("sim_sitl.cli", "Start the simulated MK-Quadro (pybullet) on the MK serial protocol."),
    "bridge": ("firmware_bridge.cli", "Start the firmware bridge: MK board ports <-> MAVLink autopilot."),
    "companion": ("companion.cli", "Start the companion daemon (perception, reference velocity, routing)."),
    "teleop": ("teleop.cli", "Start the ground station: haptic device, force feedback, operator view."),
    "demo": ("harness.demo", "Fly the paper's experiment in the SITL and write a flight report."),
    "campaign": ("harness.campaign", "Fly N randomized flights of the stack on Ray; report the safety envelope."),
    "vo-eval": ("perception.cli", "Run the RGB-D odometry on a TUM-format sequence and print RPE/ATE."),
    "replay-companion": ("companion.replay_cli", "Re-run a companion from its input journal; check every byte."),
    "replay-bridge": ("firmware_bridge.replay_cli", "Re-run a bridge from its input journal; check every byte."),
    "replay-teleop": ("teleop.replay_cli", "Re-run a lock-stepped ground station from its journal; check every byte."),
    "identify-yaw": ("companion.identify_cli", "Identify the yaw response to the pan-scan (eq. 5) from a flight log."),
    "keygen": ("quadlink.keygen_cli", "Create a MAVLink 2 signing key file for signed ground-station links."),
    "netem": ("harness.netem.cli", "A UDP/TCP link with delay, jitter, loss, reordering and a rate limit."),
    "trajectory": ("harness.trajectory_cli", "Stream a minimum-snap trajectory (YAML) as MAVLink setpoints."),
    "paper003": ("harness.demo.paper003_cli", "Fly paper 003's hover or oval through the whole stack; its tables."),
    "falsify": ("harness.falsify.cli", "Search the flight space for the lowest clearance (Optuna on Ray); resumable."),
    "rerender": ("harness.rerender_cli", "Re-render a SITL flight's camera along its true path; flag phantom points."),
}


def _not_built(name: str, module: str) -> click.Command:
    @click.command(name=name, help=f"[not built yet] {SUBCOMMANDS[name][1]}",
                   context_settings={"ignore_unknown_options": True, "allow_extra_args": True})
    def placeholder() -> None:
        click.echo(f"quadlink {name}: not built yet (module {module} is missing)", err=True)
        sys.exit(2)

    return placeholder


class LazyGroup(click.Group):
    def list_commands(self, ctx: click.Context) -> list[str]:
        return list(SUBCOMMANDS)

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        if cmd_name not in SUBCOMMANDS:
            return None
        module_name, _ = SUBCOMMANDS[cmd_name]
        try:
            module = importlib.import_module(module_name)
        except ModuleNotFoundError as exc:
            if exc.name == module_name:
                return _not_built(cmd_name, module_name)
            raise
        command = getattr(module, "command", None)
        if not isinstance(command, click.Command):
            return _not_built(cmd_name, module_name)
        command.name = cmd_name
        return command

    def format_commands(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        # Help text from the table: listing the parts must not import them.
        with formatter.section("Commands"):
            formatter.write_dl([(name, help_text) for name, (_, help_text) in SUBCOMMANDS.items()])

    def invoke(self, ctx: click.Context) -> object:
        try:
            return super().invoke(ctx)
        except QuadlinkError as exc:
            # One line and a non-zero status for bad input (DESIGN.md "Command line").
            click.echo(f"quadlink: error: {exc}", err=True)
            sys.exit(2)


def setup_logging(verbose: int = 0, quiet: bool = False) -> None:
    level = logging.WARNING if quiet else logging.DEBUG if verbose else logging.INFO
    logging.basicConfig(level=level, format="%(asctime)s %(levelname).1s %(name)s: %(message)s",
                        datefmt="%H:%M:%S", stream=sys.stderr)


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="quadlink")
@click.option("-v", "--verbose", count=True, help="More log output (debug).")
@click.option("-q", "--quiet", is_flag=True, help="Only warnings and errors.")
def main(verbose: int, quiet: bool) -> None:
    """quadlink: MAVLink companion-computer flight stack for the MK-Quadro, with a pybullet SITL."""
    setup_logging(verbose, quiet)


if __name__ == "__main__":
    main()

"""What ``quadlink replay-companion`` and ``quadlink replay-bridge`` share: replay a journal, print the verdict."""

from __future__ import annotations

import logging
import sys
from collections.abc import Callable
from pathlib import Path

import click

from quadlink.errors import QuadlinkError
from quadlink.journal import ReplayReport


def replay_main(command: str, journal: Path, replay: Callable[..., ReplayReport]) -> None:
    """Replay ``journal`` with ``replay``, print the verdict, exit with status 0 (identical), 1 (the first
    divergence printed) or 2 (not a journal)."""
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname).1s %(name)s: %(message)s")
    click.echo(f"replaying {journal} ...", err=True)
    try:
        report = replay(journal, progress=lambda n: click.echo(f"  {n} events", err=True))
    except (QuadlinkError, KeyError, ValueError) as exc:
        click.echo(f"quadlink {command}: {exc}", err=True)
        sys.exit(2)
    click.echo(report.summary())
    sys.exit(0 if report.identical else 1)

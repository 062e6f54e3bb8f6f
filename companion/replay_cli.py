"""``quadlink replay-companion JOURNAL``: re-run a flight's companion open loop from its input journal
(``quadlink companion --journal FILE``) and check that it writes the same bytes, event by event."""

from __future__ import annotations

from pathlib import Path

import click

from quadlink.replay_cli import replay_main


@click.command(name="replay-companion")
@click.argument("journal", type=click.Path(exists=True, dir_okay=False, path_type=Path))
def command(journal: Path) -> None:
    """Re-run the companion of JOURNAL (written by `quadlink companion --journal FILE`) from its recorded inputs and
    clocks, and compare every byte it writes to the autopilot and the ground stations with the flight's. Exit
    status 0: identical, bit for bit; 1: the first event that differs is printed; 2: not a journal."""
    from companion.replay import replay_journal

    replay_main("replay-companion", journal, replay_journal)

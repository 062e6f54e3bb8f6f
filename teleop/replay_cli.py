"""``quadlink replay-teleop JOURNAL``: re-run a flight's lock-stepped ground station open loop from its journal
(``quadlink teleop --lockstep URL --journal FILE``) and check that it sends the same bytes, turn by turn."""

from __future__ import annotations

from pathlib import Path

import click

from quadlink.replay_cli import replay_main


@click.command(name="replay-teleop")
@click.argument("journal", type=click.Path(exists=True, dir_okay=False, path_type=Path))
def command(journal: Path) -> None:
    """Re-run the ground station of JOURNAL (written by `quadlink teleop --lockstep URL --journal FILE`) from its
    recorded turns, and compare every byte it sends to the companion with the flight's. Exit status 0: identical, bit
    for bit; 1: the first turn that differs is printed; 2: not a journal."""
    from teleop.replay import replay_teleop_journal

    replay_main("replay-teleop", journal, replay_teleop_journal)

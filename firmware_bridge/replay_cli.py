"""``quadlink replay-bridge JOURNAL``: re-run a flight's bridge open loop from its input journal
(``quadlink bridge --journal FILE``) and check that it writes the same bytes, event by event."""

from __future__ import annotations

from pathlib import Path

import click

from quadlink.replay_cli import replay_main


@click.command(name="replay-bridge")
@click.argument("journal", type=click.Path(exists=True, dir_okay=False, path_type=Path))
def command(journal: Path) -> None:
    """Re-run the bridge of JOURNAL (written by `quadlink bridge --journal FILE`) from its recorded inputs and clocks,
    and compare every byte it writes to the board (MK port 1) and to each MAVLink endpoint with the flight's. Exit
    status 0: identical, bit for bit; 1: the first event that differs is printed; 2: not a journal."""
    from firmware_bridge.replay import replay_bridge_journal

    replay_main("replay-bridge", journal, replay_bridge_journal)

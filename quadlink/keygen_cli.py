"""``quadlink keygen FILE``: create a MAVLink 2 signing key file (see :mod:`quadlink.mavlink.security`)."""

from __future__ import annotations

from pathlib import Path

import click

from quadlink.mavlink.security import write_key


@click.command(help="Create a MAVLink 2 signing key file (64 hex digits, mode 0600) for the vehicle and its "
                    "ground stations: pass it to bridge, companion and teleop with --signing-key.")
@click.argument("path", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--force", is_flag=True, help="Overwrite an existing key file.")
def command(path: Path, force: bool) -> None:
    write_key(path, overwrite=force)
    click.echo(f"wrote a new signing key to {path} (keep it secret; copy it to the vehicle and each ground "
               "station)")

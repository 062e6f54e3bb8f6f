"""``quadlink teleop``: the ground station (device, force feedback, commands, operator view)."""

from __future__ import annotations

import dataclasses
import logging
import signal
import sys
from pathlib import Path
from types import FrameType

import click

from quadlink.config import to_dict
from quadlink.errors import ConfigError
from quadlink.lockstep import LockstepEnded, LockstepError
from quadlink.mavlink.security import read_key
from quadlink.signals import STOP_SIGNALS
from teleop.config import load_teleop_config
from teleop.devices import DEVICE_NAMES, HapticDevice, open_device
from teleop.devices.script import load_script
from teleop.force_loop import DeviceSpec
from teleop.journal import open_journal
from teleop.station import Station

log = logging.getLogger(__name__)


@click.command(name="teleop")
@click.option("--device", "device_name", type=click.Choice(DEVICE_NAMES), default="virtual", show_default=True,
              help="Device backend.")
@click.option("--script", type=click.Path(dir_okay=False), default=None,
              help="Operator script for the virtual device (configs/teleop_scripts/*.yaml).")
@click.option("--vehicle", default=None, help="MAVLink URL of the companion [config: udpout:127.0.0.1:14555].")
@click.option("--image-stream", default=None, help="Operator image stream [config: tcp://127.0.0.1:5770]; "
                                                   "'none' to run without images.")
@click.option("--http-port", type=int, default=None, help="Web page port [config: 8080]; 0 = any free port, "
                                                          "-1 = no web page.")
@click.option("--record", type=click.Path(dir_okay=False), default=None, help="Record the view to a video (.avi/.mp4).")
@click.option("--config", "config_name", default="teleop", show_default=True, help="Config name or path.")
@click.option("--log-csv", type=click.Path(dir_okay=False), default=None, help="Force/q/command log (50 Hz CSV).")
@click.option("--duration", type=float, default=None, help="Stop after this many seconds.")
@click.option("--signing-key", type=click.Path(dir_okay=False, exists=True), default=None,
              help="Sign the vehicle link with this MAVLink 2 key (quadlink keygen FILE) "
                   "[config network.signing_key_file].")
@click.option("--exit-at-script-end/--keep-running", default=True, show_default=True,
              help="With --script: stop when the script has played.")
@click.option("--script-clock", type=click.Choice(["wall", "vehicle"]), default="wall", show_default=True,
              help="Time the script follows: wall clock, or the vehicle's (TELEOP_FEEDBACK; for a lock-stepped "
                   "SITL slower than real time; the script waits for the first feedback). With --lockstep, "
                   "'wall' is the simulated time of the steps.")
@click.option("--lockstep", "lockstep_url", default=None, metavar="tcp://HOST:PORT",
              help="Join the SITL's deterministic lock-step as the 'operator' participant: single-threaded, every "
                   "timer on simulated time, no operator view; --duration counts simulated seconds. Virtual "
                   "device only.")
@click.option("--journal", "journal_path", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="With --lockstep: journal every turn of the station (its time, the companion's datagrams, what "
                   "it sent; teleop.journal, ~25 kB/s): `quadlink replay-teleop FILE` re-runs it bit for bit.")
def command(device_name: str, script: str | None, vehicle: str | None, image_stream: str | None,
            http_port: int | None, record: str | None, config_name: str, log_csv: str | None,
            duration: float | None, exit_at_script_end: bool, script_clock: str, signing_key: str | None,
            lockstep_url: str | None, journal_path: Path | None) -> None:
    """Start the ground station: haptic device, force feedback, commands, operator view (issue 7)."""
    cfg = load_teleop_config(config_name)
    if signing_key is not None:
        cfg = dataclasses.replace(cfg, network=dataclasses.replace(cfg.network, signing_key_file=signing_key))
    if cfg.network.signing_key_file is not None:
        read_key(cfg.network.signing_key_file)   # a bad key file: one clear error before anything starts
    if script is not None and device_name != "virtual":
        raise ConfigError(f"--script drives the virtual device only (got --device {device_name})")
    vehicle_url = vehicle or cfg.network.vehicle_url
    image_url = image_stream or cfg.network.image_stream_url
    port = cfg.network.http_port if http_port is None else http_port
    if lockstep_url is not None:
        if device_name != "virtual":   # a person's hand (or keys) cannot be replayed step for step
            raise ConfigError(f"--lockstep drives the virtual device only (got --device {device_name})")
        view = [name for name, on in (("--image-stream", image_url != "none"), ("--http-port", port >= 0),
                                      ("--record", bool(record))) if on]
        if view:   # the view reads wall-clock image streams and serves a page: off in a lock-stepped station
            log.warning("--lockstep: no operator view; ignoring %s", ", ".join(view))
        image_url, port, record = "none", -1, None
    stations: list[Station] = []

    def vehicle_clock() -> float | None:
        return stations[0].vehicle_time_s() if stations else None

    device: HapticDevice | DeviceSpec
    if lockstep_url is not None:    # single-threaded: the device runs in the step loop of this process
        device = open_device(device_name, cfg.device, script, vehicle_clock if script_clock == "vehicle" else None)
    elif device_name == "keyboard":   # reads this terminal: the force loop runs in a thread of this process
        device = open_device(device_name, cfg.device, script, vehicle_clock if script_clock == "vehicle" else None)
    else:                           # the force loop runs in its own process (force_loop.py: why)
        if script is not None:
            load_script(script)     # bad scripts fail here, with one line, before anything starts
        device = DeviceSpec(device_name, script, script_clock)
    journal = None
    if journal_path is not None:
        if lockstep_url is None:   # free-running, the force loop and the view interleave with the link: not journaled
            raise ConfigError("--journal journals a lock-stepped station only (give --lockstep URL)")
        if cfg.network.signing_key_file is not None:
            raise ConfigError("--journal: a signed vehicle link cannot be replayed (the journal holds no key)")
        header = {"teleop": to_dict(cfg), "script": Path(script).read_text() if script else "",
                  "script_clock": script_clock, "exit_at_script_end": exit_at_script_end, "duration_s": duration}
        try:
            journal = open_journal(journal_path, header)
        except OSError as exc:
            raise ConfigError(f"journal {journal_path}: {exc}") from exc
        log.info("journaling every turn to %s (quadlink replay-teleop %s)", journal_path, journal_path)
    station = Station(cfg, device, vehicle_url, None if image_url == "none" else image_url,
                      None if port < 0 else port, record, log_csv, exit_at_script_end=exit_at_script_end,
                      journal=journal)
    stations.append(station)
    log.info("device %s%s", device_name, f", script {script} on the {script_clock} clock" if script else "")

    def on_sigterm(signum: int, frame: FrameType | None) -> None:
        raise KeyboardInterrupt   # SIGTERM stops as cleanly as Ctrl-C (force off, CSV and video closed)

    previous = {sig: signal.signal(sig, on_sigterm) for sig in STOP_SIGNALS}   # Ctrl-C too (quadlink.signals)
    lockstep_error: LockstepError | None = None
    try:
        if lockstep_url is not None:
            station.start_lockstep(lockstep_url)
            station.run_lockstep(duration)
        else:
            station.start()   # opens the device (its own process) first: a missing backend is a one-line error
            if station.server is not None:
                log.info("open %s in a browser", station.server.url)
            station.run(duration)
    except KeyboardInterrupt:
        log.info("interrupted; stopping")
    except LockstepEnded as exc:   # the SITL ended the flight (its duration, the flight's end): a normal stop
        log.info("lock-step: %s", exc)
    except LockstepError as exc:   # the coordinator is gone (the SITL ended or died) or a datagram never came
        log.error("lock-step: %s", exc)
        lockstep_error = exc
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        station.close()
        if journal is not None:
            journal.close()
        log.info("ground station stopped (%d MANUAL_CONTROL sent, %d view frames)", station.manual_control_sent,
                 station.view_frames)
    if lockstep_error is not None:
        click.echo(f"quadlink: error: lock-step: {str(lockstep_error).removeprefix('lock-step: ')}", err=True)
        sys.exit(1)

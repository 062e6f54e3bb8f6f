"""``quadlink bridge``: the MK board's two serial ports as a MAVLink autopilot."""

from __future__ import annotations

import dataclasses
import logging
import signal
import sys
from pathlib import Path

import click

from quadlink.config import find_config, load_config
from quadlink.errors import ConfigError
from quadlink.lockstep import LockstepError
from quadlink.realtime import MAX_PRIORITY, set_realtime_priority
from quadlink.signals import STOP_SIGNALS
from quadlink.vehicle import load_vehicle

log = logging.getLogger(__name__)

SWITCH_INTERVAL_S = 0.0005


@click.command(help="Start the firmware bridge: MK board ports <-> MAVLink autopilot (PX4-style offboard).")
@click.option("--mk-cmd", "mk_cmd", default=None, help="MK port 1 URL (commands/telemetry) "
              "[default socket://127.0.0.1:5760; /dev/ttyUSB0:115200, pty also work]")
@click.option("--mk-imu", "mk_imu", default=None, help="MK port 2 URL (IMU 500 Hz) [default socket://127.0.0.1:5761]")
@click.option("--mavlink", "mavlink_urls", multiple=True, help="MAVLink endpoint, pymavlink syntax; repeatable "
              "[default udpout:127.0.0.1:14540 and udpout:127.0.0.1:14550]")
@click.option("--sysid", type=click.IntRange(1, 255), default=None, help="MAVLink system id [default 1]")
@click.option("--config", "config_name", default="bridge", show_default=True,
              help="bridge config (a path or a name under configs/)")
@click.option("--params", "params_path", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="parameter file [default ~/.local/state/quadlink/bridge_params.yaml]")
@click.option("--rt-priority", "rt_priority", type=click.IntRange(0, MAX_PRIORITY), default=None,
              help="SCHED_FIFO priority 1-99 for the IMU path (needs CAP_SYS_NICE), 0 = normal "
              "[config realtime_priority: 0]")
@click.option("--duration", type=float, default=None, help="stop after this many seconds (tests, benchmarks; "
              "with --lockstep, simulated seconds)")
@click.option("--signing-key", "signing_key", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="MAVLink 2 signing key for the ground-station links (quadlink keygen FILE) "
              "[config security.signing_key_file]")
@click.option("--require-signing/--allow-unsigned", "require_signing", default=None,
              help="refuse unsigned packets on the ground-station links [config security.require_signing: false]")
@click.option("--gcs-link", "gcs_links", type=int, multiple=True,
              help="index of a --mavlink endpoint that faces ground stations (signed); repeatable "
              "[config ground_station_links: 1; link 0 is the companion's, internal]")
@click.option("--lockstep", "lockstep_url", default=None, metavar="tcp://HOST:PORT",
              help="deterministic lock-step (quadlink/lockstep.py): join the SITL's coordinator as participant "
              "'bridge'; the bridge then runs on the simulated time, handles exactly what each step announces "
              "(companion datagrams on --mavlink endpoint 0, MK bytes); exits with status 0 when the "
              "simulation ends, 1 when the coordinator is lost [config lockstep_url: off]")
@click.option("--journal", "journal_path", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="journal every input the bridge handles, with its clocks and what it wrote "
                   "(firmware_bridge.journal; ~0.1 MB/s): `quadlink replay-bridge FILE` re-runs it bit for bit")
@click.option("--tlog", "tlog_path", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="record every MAVLink packet sent on the ground-station links (--gcs-link) to this .tlog, as sent")
def command(mk_cmd: str | None, mk_imu: str | None, mavlink_urls: tuple[str, ...], sysid: int | None,
            config_name: str, params_path: Path | None, rt_priority: int | None, duration: float | None,
            signing_key: Path | None, require_signing: bool | None, gcs_links: tuple[int, ...],
            lockstep_url: str | None, journal_path: Path | None, tlog_path: Path | None) -> None:
    from firmware_bridge.daemon import BridgeConfig, BridgeDaemon
    from firmware_bridge.journal import JournalWriter
    from firmware_bridge.params import load_param_file
    from quadlink.config import to_dict
    from quadlink.errors import LinkError
    from quadlink.mavlink.tlog import TlogWriter

    try:
        config = load_config(find_config(config_name), BridgeConfig)
    except ConfigError:
        if config_name != "bridge":
            raise
        config = BridgeConfig()
    overrides: dict[str, object] = {}
    if mk_cmd:
        overrides["mk_cmd_url"] = mk_cmd
    if mk_imu:
        overrides["mk_imu_url"] = mk_imu
    if mavlink_urls:
        overrides["mavlink_urls"] = tuple(mavlink_urls)
    if sysid is not None:
        overrides["sysid"] = sysid
    if rt_priority is not None:
        overrides["realtime_priority"] = rt_priority
    if gcs_links:
        overrides["ground_station_links"] = tuple(gcs_links)
    if lockstep_url:
        overrides["lockstep_url"] = lockstep_url
    sec = config.security
    overrides["security"] = dataclasses.replace(
        sec, signing_key_file=str(signing_key) if signing_key else sec.signing_key_file,
        require_signing=sec.require_signing if require_signing is None else require_signing)
    config = dataclasses.replace(config, **overrides)  # type: ignore[arg-type]
    config.security.key()   # a missing or bad key file: one clear error before any link opens
    vehicle = load_vehicle(config.vehicle)
    # The readers hand bytes to the main thread; with CPython's default 5 ms GIL switch interval a reader
    # that wakes while the main thread computes waits up to 5 ms, which is the whole IMU latency budget.
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    set_realtime_priority(config.realtime_priority)   # before open() starts the reader threads: they inherit it
    journal = None
    if journal_path is not None:
        stored = load_param_file((params_path or Path(config.params_file)).expanduser())
        try:
            journal = JournalWriter(journal_path, {"bridge": to_dict(config), "vehicle": to_dict(vehicle),
                                                   "params": stored})
        except OSError as exc:
            raise LinkError(f"journal {journal_path}: {exc}") from exc
        log.info("journaling every input to %s (quadlink replay-bridge %s)", journal_path, journal_path)
    try:
        tlog = TlogWriter(tlog_path) if tlog_path is not None else None
    except OSError as exc:
        if journal is not None:
            journal.close()
        raise LinkError(f"tlog {tlog_path}: {exc}") from exc
    daemon = BridgeDaemon(config, vehicle, params_path, journal=journal, tlog=tlog)
    try:
        daemon.open()
    except BaseException:
        if journal is not None:
            journal.close()
        if tlog is not None:
            tlog.close()
        raise  # LinkError (a lock-step coordinator that never answers too) -> one-line error, exit 2
    previous = {sig: signal.signal(sig, lambda *_: daemon.stop()) for sig in STOP_SIGNALS}   # quadlink.signals
    log.info("bridge running (Ctrl-C to stop)")
    lockstep_end: LockstepError | None = None
    try:
        daemon.run(duration)
    except KeyboardInterrupt:
        log.info("Ctrl-C: stopping")
    except LockstepError as exc:  # the coordinator was lost or an input never came (a normal end returns)
        lockstep_end = exc
    finally:
        daemon.close()
        if journal is not None:
            journal.close()
        if tlog is not None:
            tlog.close()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        s = daemon.stats
        log.info("bridge stopped: %d IMU samples, %d setpoints, %d MAVLink in / %d out", s.imu_samples,
                 s.setpoints_sent, s.mavlink_in, s.mavlink_out)
    if lockstep_end is not None:
        # not a bad invocation (exit 2): the simulation the bridge was stepped by went away without ending
        click.echo(f"quadlink bridge: {lockstep_end}", err=True)
        raise SystemExit(1) from lockstep_end

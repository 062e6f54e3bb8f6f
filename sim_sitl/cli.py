"""``quadlink sitl``: run the simulated MK-Quadro until Ctrl-C or ``--duration``."""

from __future__ import annotations

import dataclasses
import logging
import signal
from pathlib import Path

import click

from quadlink.errors import ConfigError, LinkError
from quadlink.lockstep import PARTICIPANTS
from sim_sitl.config import RendererName, known_scenarios, load_sitl_config

log = logging.getLogger(__name__)


@click.command(help="Start the simulated MK-Quadro (pybullet) on the MK serial protocol.")
@click.option("--scenario", default=None, help=f"scenario name ({', '.join(known_scenarios())}) or YAML path")
@click.option("--config", "config_path", default=None, help="SITL config YAML (default configs/sitl.yaml)")
@click.option("--lockstep", is_flag=True, help="advance in 10 ms chunks gated by setpoints and camera acks")
@click.option("--lockstep-port", type=int, default=None,
              help="deterministic lock-step (quadlink/lockstep.py): serve its coordinator on this TCP port and step "
                   "only with every participant (no simulated time passes before they all registered)")
@click.option("--lockstep-participants", default=",".join(PARTICIPANTS), show_default=True,
              help="with --lockstep-port: the participants' names, comma-separated")
@click.option("--end-after-operator", "end_after_operator_s", type=float, default=None,
              help="with --lockstep-port: once the operator has left, end after 2 s disarmed on the ground, or this "
                   "many simulated seconds after it left (default: run to --duration)")
@click.option("--speed", type=float, default=None,
              help="sim speed factor vs wall clock (default 1.0; 0 = as fast as possible)")
@click.option("--camera-res", default=None, help="320x240 (default) or 640x480")
@click.option("--no-camera", is_flag=True, help="do not render or serve the RGB-D camera")
@click.option("--renderer", type=click.Choice(["raster", "pybullet"]), default=None,
              help="camera renderer (default: camera.renderer of the config, raster)")
@click.option("--pty", is_flag=True, help="also expose both MK ports as pseudo-terminals (paths are logged)")
@click.option("--port1", type=int, default=5760, show_default=True, help="MK port 1 TCP port (commands)")
@click.option("--port2", type=int, default=5761, show_default=True, help="MK port 2 TCP port (IMU)")
@click.option("--camera-port", type=int, default=5762, show_default=True, help="camera stream TCP port")
@click.option("--truth", default="udpout:127.0.0.1:14560", show_default=True,
              help="ground-truth MAVLink endpoint (udpout:HOST:PORT, 'none' to disable)")
@click.option("--truth-tlog", "truth_tlog", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="also write every ground-truth packet to this .tlog as it is sent (lossless, unlike a UDP "
                   "listener on a starved machine; with --truth none, only here)")
@click.option("--duration", type=float, default=None, help="stop after this many simulated seconds")
@click.option("--board", type=click.Choice(["model", "avr"]), default=None,
              help="what flies: the Python board model or the firmware binary in simavr (default: the config's, model)")
@click.option("--firmware-elf", default=None,
              help="with --board avr: the firmware ELF (default firmware/build/quadlink-fc.elf)")
def command(scenario: str | None, config_path: str | None, lockstep: bool, lockstep_port: int | None,
            lockstep_participants: str, end_after_operator_s: float | None, speed: float | None,
            camera_res: str | None, no_camera: bool, renderer: RendererName | None, pty: bool, port1: int, port2: int,
            camera_port: int, truth: str, truth_tlog: Path | None, duration: float | None, board: str | None,
            firmware_elf: str | None) -> None:
    from sim_sitl.runner import Sitl, SitlOptions, parse_resolution

    cfg = load_sitl_config(config_path)
    if renderer is not None:
        cfg = dataclasses.replace(cfg, camera=dataclasses.replace(cfg.camera, renderer=renderer))
    if board is not None:
        cfg = dataclasses.replace(cfg, board=board)  # type: ignore[arg-type]
    if firmware_elf is not None:
        cfg = dataclasses.replace(cfg, firmware_elf=firmware_elf)
    if cfg.board == "avr":
        from sim_sitl.avr_board import elf_path

        elf_path(cfg.firmware_elf)  # a missing ELF is a one-line error before any port opens
    if speed is not None and speed < 0:
        raise ConfigError(f"--speed must be positive (or 0 for as fast as possible), got {speed}")
    res = None
    if camera_res:
        try:
            res = parse_resolution(camera_res)
        except ValueError as exc:
            raise ConfigError(f"--camera-res: {exc}") from exc
    opts = SitlOptions(config=cfg, scenario=scenario, port1=port1, port2=port2, camera_port=camera_port,
                       camera=not no_camera, camera_res=res, truth_url=None if truth == "none" else truth,
                       truth_tlog=truth_tlog, pty=pty,
                       lockstep=lockstep or lockstep_port is not None, speed=speed, duration_s=duration,
                       lockstep_port=lockstep_port, end_after_operator_s=end_after_operator_s,
                       lockstep_participants=tuple(p.strip() for p in lockstep_participants.split(",") if p.strip()))
    try:
        sitl = Sitl(opts)
    except OSError as exc:
        raise LinkError(str(exc)) from exc
    sitl.log_endpoints()
    def _request_stop(signum: int, _frame: object) -> None:
        log.info("%s: stopping", signal.Signals(signum).name)
        sitl.request_stop()

    # explicit handlers: a SITL started in the background by a script has SIGINT ignored by default
    previous = {sig: signal.signal(sig, _request_stop) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        sitl.run()
    except KeyboardInterrupt:
        log.info("Ctrl-C: stopping")
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        sitl.stop()
        s = sitl.stats
        log.info("ran %.1f s sim in %.1f s wall (rtf %.2f); IMU frames %d (dropped %d), camera frames %d, "
                 "port-1 frames dropped %d", s.sim_time_s, s.wall_time_s, s.real_time_factor, s.imu_frames_offered,
                 s.imu_frames_dropped, s.camera_frames, sitl.line1.stats.frames_dropped)


__all__ = ["command"]

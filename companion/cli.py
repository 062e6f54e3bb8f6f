"""``quadlink companion``: the companion daemon (see companion/README.md)."""

from __future__ import annotations

import logging
import signal
import sys
import threading
from pathlib import Path

import click

from quadlink.signals import STOP_SIGNALS

log = logging.getLogger("companion")


def _math_threads() -> int:
    """OpenCV and BLAS on ``QUADLINK_THREADS`` threads (default 1), set before numpy loads its BLAS.

    At QVGA their worker threads cost more CPU than they save time (OpenCV's Sobel on 320x240: 136 µs of
    CPU on 2 threads for 85 µs of wall time, 84 µs on one), and the flight loop is one thread by design."""
    import os

    n = os.environ.get("QUADLINK_THREADS", "1")
    n = n if n.isdigit() and int(n) > 0 else "1"
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, n)
    import cv2

    cv2.setNumThreads(int(n))
    return int(cv2.getNumThreads())


@click.command(name="companion")
@click.option("--config", "config_path", default="companion", show_default=True,
              help="Companion YAML (path, or a name under configs/).")
@click.option("--autopilot", default=None, help="Autopilot MAVLink URL [config links.autopilot: udpin:0.0.0.0:14540].")
@click.option("--gcs", default=None, help="Ground-station MAVLink URL [config links.gcs: udpin:0.0.0.0:14555].")
@click.option("--camera", default=None,
              help="Camera: tcp://HOST:PORT (SITL stream), a TUM folder, realsense[:SERIAL], openni[:URI] or "
                   "realsense://software?source=URL (companion/cameras) [config links.camera: tcp://127.0.0.1:5762].")
@click.option("--image-port", type=int, default=None, help="Operator image stream TCP port [config: 5770]; 0 = off.")
@click.option("--image-host", default=None,
              help="Address the operator image stream listens on [config links.image_host: 127.0.0.1, local only].")
@click.option("--signing-key", "signing_key", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="MAVLink 2 signing key for the ground-station endpoint (quadlink keygen FILE) "
                   "[config security.signing_key_file].")
@click.option("--require-signing/--allow-unsigned", "require_signing", default=None,
              help="Refuse unsigned ground-station packets [config security.require_signing: false].")
@click.option("--tlog", "tlog_path", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Record every MAVLink packet of both links to this .tlog.")
@click.option("--record-frames", "frames_path", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Record every camera frame received to this file (camera-stream records, ~380 kB per QVGA "
                   "frame; replay with quadlink.camera.read_frame_recording).")
@click.option("--journal", "journal_path", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Journal every input the daemon handles, with the clocks it reads and the bytes it writes "
                   "(companion.journal; ~400 kB per frame): `quadlink replay-companion FILE` re-runs it bit for bit.")
@click.option("--duration", type=float, default=None,
              help="Stop after this many seconds (wall; simulated seconds with --lockstep).")
@click.option("--lockstep", "lockstep_url", default=None, metavar="tcp://HOST:PORT",
              help="Join the SITL's deterministic lock-step (quadlink.lockstep) as \"companion\": every input read "
                   "up to the counts of each simulation step, the step's simulated time as the clock. Needs the "
                   "SITL camera stream (--camera tcp://...). Exit status 1 when the coordinator goes away.")
def command(config_path: str, autopilot: str | None, gcs: str | None, camera: str | None, image_port: int | None,
            image_host: str | None, signing_key: Path | None, require_signing: bool | None,
            tlog_path: Path | None, frames_path: Path | None, journal_path: Path | None, duration: float | None,
            lockstep_url: str | None) -> None:
    """Start the companion daemon: perception, reference velocity, MAVLink to autopilot and ground station."""
    if journal_path is not None and frames_path is not None:
        raise click.UsageError("--journal holds the frames already: give one of --journal and --record-frames")
    stop = threading.Event()

    def on_stop_signal(*_: object) -> None:
        # is_set() first: Event.set() takes a lock, and a second signal inside it would deadlock the handler
        if not stop.is_set():
            stop.set()

    # installed before the start-up (imports, links, perception: seconds on a loaded board), so that a Ctrl-C
    # during it stops the command as well (quadlink.signals; a SIGINT 3 s in was lost at load 6)
    previous = {sig: signal.signal(sig, on_stop_signal) for sig in STOP_SIGNALS}
    try:
        failure = _start_and_run(stop, config_path, autopilot, gcs, camera, image_port, image_host, signing_key,
                                 require_signing, tlog_path, frames_path, duration, lockstep_url, journal_path)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    if failure is not None:
        # the flight ended under us (the SITL is gone): not bad input (status 2), a failed run
        click.echo(f"quadlink companion: {failure}", err=True)
        sys.exit(1)


def _start_and_run(stop: threading.Event, config_path: str, autopilot: str | None, gcs: str | None,
                   camera: str | None, image_port: int | None, image_host: str | None, signing_key: Path | None,
                   require_signing: bool | None, tlog_path: Path | None, frames_path: Path | None,
                   duration: float | None, lockstep_url: str | None,
                   journal_path: Path | None = None) -> Exception | None:
    """Open everything, run until stopped; the lock-step's end (:class:`~quadlink.lockstep.LockstepError`)
    is returned, for the command's exit status."""
    threads = _math_threads()
    import dataclasses

    from companion.cameras import camera_url, is_device_url, open_camera
    from companion.config import load_companion_config
    from companion.daemon import Companion
    from companion.image_publisher import OperatorImagePublisher
    from companion.interfaces import for_camera, perception_config, pipeline_factory
    from companion.journal import JournalWriter
    from companion.lockstep_links import join_lockstep
    from quadlink.camera import FrameRecordWriter
    from quadlink.config import to_dict
    from quadlink.errors import LinkError
    from quadlink.lockstep import LockstepError
    from quadlink.mavlink.connection import open_mavlink
    from quadlink.mavlink.tlog import TlogWriter
    from quadlink.realtime import set_nice
    from quadlink.vehicle import load_vehicle

    cfg = load_companion_config(config_path)
    links = dataclasses.replace(cfg.links, autopilot=autopilot or cfg.links.autopilot, gcs=gcs or cfg.links.gcs,
                                camera=camera_url(camera or cfg.links.camera),
                                image_port=cfg.links.image_port if image_port is None else image_port,
                                image_host=image_host or cfg.links.image_host)
    sec = cfg.security
    sec = dataclasses.replace(sec, signing_key_file=str(signing_key) if signing_key else sec.signing_key_file,
                              require_signing=sec.require_signing if require_signing is None else require_signing)
    sec.key()   # a missing or bad key file: one clear error before any link opens
    cfg = dataclasses.replace(cfg, links=links, security=sec)
    if lockstep_url is not None and not links.camera.startswith("tcp://"):
        # a replayed folder or a live sensor has its own pace: no step counts its frames
        raise LinkError(f"--lockstep needs the SITL camera stream (--camera tcp://HOST:PORT), not {links.camera}")
    if is_device_url(links.camera) and cfg.timing.camera_stamps != "local":
        # a live sensor's stamps are its own clock, never the autopilot's: map them to ours (TIMESYNC does the rest)
        log.warning("camera %s: timing.camera_stamps 'local' (the config says %r)", links.camera,
                    cfg.timing.camera_stamps)
        cfg = dataclasses.replace(cfg, timing=dataclasses.replace(cfg.timing, camera_stamps="local"))
    set_nice(cfg.timing.nice)   # before the threads start: they inherit it
    vehicle = load_vehicle(cfg.vehicle)
    configured = perception_config(cfg)
    pcfg = for_camera(configured, links.camera)
    factory = pipeline_factory(pcfg, cfg.seed)
    if configured.hidden_floor.enabled and not pcfg.hidden_floor.enabled:
        log.info("hidden floor off for camera %s: a stereo camera's depth holes are not a dark object's",
                 links.camera)
    ident = cfg.identity
    opened: list = []
    try:
        ap = open_mavlink(links.autopilot, ident.system_id, ident.component_id)
        opened.append(ap)
        ground = open_mavlink(links.gcs, ident.system_id, ident.component_id,
                              udp_timeout=links.gcs_client_timeout_s) if links.gcs.startswith("udpin:") else \
            open_mavlink(links.gcs, ident.system_id, ident.component_id)
        opened.append(ground)
        cam = open_camera(links.camera, R_qc=vehicle.camera.R_qc_matrix, p_qc_m=vehicle.camera.p_qc,
                          stamps="local" if cfg.timing.camera_stamps == "local" else "device")
        opened.append(cam)
        try:
            images = OperatorImagePublisher(links.image_host, links.image_port) if links.image_port else None
        except OSError as exc:
            raise LinkError(f"operator image stream tcp://{links.image_host}:{links.image_port}: {exc}") from exc
        if images is not None:
            opened.append(images)
        tlog = TlogWriter(tlog_path) if tlog_path else None
        if tlog is not None:
            opened.append(tlog)
        try:
            frames = FrameRecordWriter(frames_path) if frames_path else None
        except OSError as exc:
            raise LinkError(f"frame recording {frames_path}: {exc}") from exc
        if frames is not None:
            opened.append(frames)
        try:
            header = {"companion": to_dict(cfg), "perception": to_dict(pcfg),
                      "seed": cfg.seed}
            journal = JournalWriter(journal_path, header) if journal_path else None
        except OSError as exc:
            raise LinkError(f"journal {journal_path}: {exc}") from exc
        if journal is not None:
            opened.append(journal)
        # the last: from the hello on, the coordinator waits for our steps
        lockstep = join_lockstep(lockstep_url, ap, ground, cam, stop) if lockstep_url is not None else None
    except BaseException:
        for link in opened:
            link.close()
        raise
    log.info("autopilot %s, ground station %s (signing %s, state changes from sysids %s), camera %s, "
             "operator images %s, tlog %s, math threads %d, %s", links.autopilot, links.gcs,
             "required" if sec.require_signing else ("optional" if sec.signing_key_file else "off"),
             "any" if sec.allowed_sender_sysids is None else f"{list(sec.allowed_sender_sysids)} + own",
             links.camera, f"tcp://{links.image_host}:{links.image_port}" if images else "off", tlog_path or "off",
             threads, f"deterministic lock-step at {lockstep_url}" if lockstep else "wall clock")
    if frames is not None:
        log.info("recording camera frames to %s", frames_path)
    if journal is not None:
        log.info("journaling every input to %s (quadlink replay-companion %s)", journal_path, journal_path)
    if lockstep is None:
        daemon = Companion(cfg, ap, ground, cam, factory, image_server=images, tlog=tlog, frame_recorder=frames,
                           journal=journal)
    else:
        daemon = Companion(cfg, ap, ground, cam, factory, image_server=images, tlog=tlog, frame_recorder=frames,
                           clock=lockstep.client.clock, lockstep=lockstep, journal=journal)
    failure: Exception | None = None
    try:
        daemon.run(stop, duration)
    except KeyboardInterrupt:
        log.info("interrupted")
    except LockstepError as exc:   # logged by the daemon
        failure = exc
    finally:
        stop.set()
        daemon.close()
        s = daemon.stats
        log.info("stopped: %d frames, %d setpoints, %d feedback, routed %d to GCS / %d to autopilot",
                 s.frames, s.setpoints, s.feedback, s.routed_to_gcs, s.routed_to_autopilot)
    return failure


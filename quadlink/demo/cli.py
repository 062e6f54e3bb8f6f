"""``quadlink demo``: the paper's experiment (paper 000 section VII) flown by the whole stack in the SITL."""

from __future__ import annotations

import logging
import math
import signal
import time
from dataclasses import dataclass
from pathlib import Path

import click

from quadlink import CONFIG_DIR
from quadlink.demo.link import LinkImpairment, LinkProxies, teleop_config_with_passivity, write_link_stats
from quadlink.demo.orchestrator import ProcessDied, ProcessSpec, Stack
from quadlink.demo.recorder import Recorder
from quadlink.demo.report import summary_table, write_report
from quadlink.errors import ConfigError

log = logging.getLogger("quadlink.demo")

DEFAULT_SCRIPT = CONFIG_DIR / "teleop_scripts" / "paper_experiment.yaml"


@dataclass(frozen=True)
class Ports:
    """Every port of a demo flight, shifted by one offset so several stacks can share a machine."""

    offset: int = 0

    def __getattr__(self, name: str) -> int:
        base = {"mk1": 5760, "mk2": 5761, "camera": 5762, "image": 5770, "autopilot": 14540, "gcs_bridge": 14551,
                "vehicle": 14555, "truth": 14560, "http": 8080,
                "vehicle_netem": 14557, "image_netem": 5771}   # the impaired link's ends (quadlink.demo.link)
        if name not in base:
            raise AttributeError(name)
        return base[name] + self.offset


def build_specs(scenario: str, script: Path, out_dir: Path, ports: Ports, lockstep: bool, speed: float,
                duration_s: float, record_frames: bool = False, via_netem: bool = False,
                teleop_config: Path | None = None) -> list[ProcessSpec]:
    """``via_netem``: the ground station talks to the netem proxies' ports (quadlink.demo.link)."""
    vehicle_port, image_port = (ports.vehicle_netem, ports.image_netem) if via_netem else (ports.vehicle, ports.image)
    sitl = ["sitl", "--scenario", scenario, "--port1", str(ports.mk1), "--port2", str(ports.mk2),
            "--camera-port", str(ports.camera), "--truth", f"udpout:127.0.0.1:{ports.truth}",
            "--duration", f"{duration_s + 30:.0f}"]
    if lockstep:
        sitl.append("--lockstep")
    if speed != 1.0:
        sitl += ["--speed", str(speed)]
    return [
        ProcessSpec("sitl", tuple(sitl), ready_after_s=4.0),
        ProcessSpec("bridge", ("bridge", "--mk-cmd", f"socket://127.0.0.1:{ports.mk1}",
                               "--mk-imu", f"socket://127.0.0.1:{ports.mk2}",
                               "--mavlink", f"udpout:127.0.0.1:{ports.autopilot}",
                               "--mavlink", f"udpout:127.0.0.1:{ports.gcs_bridge}",
                               "--params", str(out_dir / "bridge_params.yaml")), ready_after_s=2.0),
        ProcessSpec("companion", ("companion", "--config", str(CONFIG_DIR / "companion.yaml"),
                                  "--autopilot", f"udpin:127.0.0.1:{ports.autopilot}",
                                  "--gcs", f"udpin:127.0.0.1:{ports.vehicle}",
                                  "--camera", f"tcp://127.0.0.1:{ports.camera}",
                                  "--image-port", str(ports.image),
                                  "--tlog", str(out_dir / "companion.tlog"),
                                  *(("--record-frames", str(out_dir / "frames.qlcf")) if record_frames else ())),
                    ready_after_s=3.0),
        ProcessSpec("teleop", ("teleop", "--device", "virtual", "--script", str(script),
                               "--vehicle", f"udpout:127.0.0.1:{vehicle_port}",
                               "--image-stream", f"tcp://127.0.0.1:{image_port}",
                               *(("--config", str(teleop_config)) if teleop_config else ()),
                               "--http-port", str(ports.http), "--log-csv", str(out_dir / "teleop.csv"),
                               "--exit-at-script-end", "--script-clock", "vehicle" if lockstep else "wall"),
                    ready_after_s=0.5),
    ]


def run_demo(scenario: str, duration_s: float, out_dir: Path, script: Path, lockstep: bool = True,
             speed: float = 1.0, port_offset: int = 0, progress_every_s: float = 3.0,
             record_frames: bool = False, link: LinkImpairment | None = None,
             passivity: bool | None = None) -> dict[str, object]:
    """Fly the demo; returns the report. Raises :class:`ProcessDied` if a part dies.

    ``link``: the ground link goes through the netem proxies with this impairment (issue 18);
    ``passivity``: the force loop's passivity controller (default: on when ``link`` is given)."""
    if not script.is_file():
        raise ConfigError(f"{script}: operator script not found")
    out_dir.mkdir(parents=True, exist_ok=True)
    ports = Ports(port_offset)
    stack = Stack(out_dir / "logs")
    recorder = Recorder()
    recorder.record("truth", f"udpin:127.0.0.1:{ports.truth}", out_dir / "truth.tlog", is_truth=True)
    recorder.record("bridge", f"udpin:127.0.0.1:{ports.gcs_bridge}", out_dir / "bridge.tlog")
    interrupted = False
    failure: ProcessDied | None = None
    proxies: LinkProxies | None = None
    passivity_on = (link is not None) if passivity is None else passivity
    teleop_config = teleop_config_with_passivity(out_dir, passivity_on) if passivity_on or link else None

    def on_sigint(signum: int, frame: object) -> None:
        nonlocal interrupted
        interrupted = True

    previous = signal.signal(signal.SIGINT, on_sigint)
    t_wall0 = time.monotonic()
    try:
        for spec in build_specs(scenario, script, out_dir, ports, lockstep, speed, duration_s, record_frames,
                                via_netem=link is not None, teleop_config=teleop_config):
            if interrupted:
                break
            if spec.name == "teleop" and link is not None:
                proxies = LinkProxies(link, ports.vehicle_netem, ports.vehicle, ports.image_netem, ports.image)
                log.info("ground link through netem: %.0f ms one way, %.0f ms jitter, %.1f %% loss", link.delay_ms,
                         link.jitter_ms, 100 * link.loss)
            stack.start(spec)
        log.info("all parts running; operator view at http://127.0.0.1:%d ; logs in %s", ports.http, stack.log_dir)
        next_progress = 0.0
        while not interrupted:
            time.sleep(0.2)
            if "teleop" in stack.check(may_finish=frozenset({"teleop"})):
                log.info("operator script finished")
                break
            t = recorder.truth
            if math.isfinite(t.sim_time_s) and t.sim_time_s >= duration_s:
                log.info("duration of %.0f s simulated time reached", duration_s)
                break
            if time.monotonic() >= next_progress:
                next_progress = time.monotonic() + progress_every_s
                speed_m_s = math.hypot(*t.velocity_ned_m_s[:2]) if math.isfinite(t.velocity_ned_m_s[0]) else math.nan
                log.info("t_sim %6.1f s  (wall %5.0f s)  altitude %5.2f m  speed %4.2f m/s  nearest obstacle "
                         "%5.2f m  [truth %d msgs, bridge %d msgs]", t.sim_time_s, time.monotonic() - t_wall0,
                         -t.position_ned_m[2], speed_m_s, t.nearest_obstacle_m, recorder.counts.get("truth", 0),
                         recorder.counts.get("bridge", 0))
    except ProcessDied as exc:
        failure = exc
        log.error("stopping: %s", exc)
    finally:
        signal.signal(signal.SIGINT, previous)
        cpu = stack.cpu_seconds()
        codes = stack.stop()
        recorder.stop()
        if proxies is not None:
            write_link_stats(out_dir, proxies)
            proxies.close()
        log.info("stopped (exit statuses: %s)", ", ".join(f"{k}={v}" for k, v in codes.items()))
    report = write_report(out_dir, cpu, scenario)
    report["interrupted"] = interrupted
    report["failure"] = str(failure) if failure else None
    if failure:
        raise failure
    return report


@click.command(name="demo")
@click.option("--scenario", default="paper-arena", show_default=True, help="SITL scenario (configs/scenarios/).")
@click.option("--duration", "duration_s", default=90.0, show_default=True, help="Simulated seconds at most.")
@click.option("--out", "out_dir", default="flight-report", show_default=True, type=click.Path(path_type=Path),
              help="Folder for tlogs, report.json and plots.")
@click.option("--script", default=str(DEFAULT_SCRIPT), show_default=True, type=click.Path(path_type=Path),
              help="Scripted operator for the virtual haptic device.")
@click.option("--lockstep/--realtime", default=True, show_default=True,
              help="Lock-step keeps every part in step with simulated time on a loaded machine.")
@click.option("--speed", default=1.0, show_default=True, help="Real-time factor in --realtime mode.")
@click.option("--port-offset", default=0, show_default=True, help="Shift every port (run beside another stack).")
@click.option("--record-frames", is_flag=True,
              help="Also record the companion's camera frames to OUT/frames.qlcf (~11 MB per second of flight).")
@click.option("--link-delay-ms", type=float, default=None,
              help="Ground link through netem: one-way delay (ms, each direction) [issue 18].")
@click.option("--link-jitter-ms", type=float, default=None, help="Ground link jitter (ms, std dev).")
@click.option("--link-loss", type=float, default=None, help="Ground link packet loss (0-1, MAVLink; TCP images: none).")
@click.option("--link-seed", type=int, default=0, show_default=True, help="Seed of the link's impairment.")
@click.option("--passivity/--no-passivity", default=None,
              help="Force loop passivity controller [default: on with --link-*, else the teleop config's].")
def command(scenario: str, duration_s: float, out_dir: Path, script: Path, lockstep: bool, speed: float,
            port_offset: int, record_frames: bool, link_delay_ms: float | None, link_jitter_ms: float | None,
            link_loss: float | None, link_seed: int, passivity: bool | None) -> None:
    """Fly the paper's experiment in the SITL (take off, drive, rotate, approach and push the obstacle, land)."""
    try:
        impaired = any(v is not None for v in (link_delay_ms, link_jitter_ms, link_loss))
        link = LinkImpairment(link_delay_ms or 0.0, link_jitter_ms or 0.0, link_loss or 0.0, link_seed) \
            if impaired else None
        if link is not None:
            link.impairment()   # validates (ConfigError names the bad value)
        report = run_demo(scenario, duration_s, out_dir, script, lockstep, speed, port_offset,
                          record_frames=record_frames, link=link, passivity=passivity)
    except ProcessDied as exc:
        click.echo(f"quadlink demo: {exc}", err=True)
        raise SystemExit(1) from exc
    plots = ", ".join(str(p) for p in report.get("plots", []))  # type: ignore[attr-defined]
    click.echo(f"\nFlight report ({out_dir}/report.json, plots: {plots}):")
    click.echo(summary_table(report))

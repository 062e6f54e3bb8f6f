"""``quadlink demo``: the paper's experiment (paper 000 section VII) flown by the whole stack in the SITL."""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import click

from harness.cpu_share import CpuShare
from harness.demo.link import LinkImpairment, LinkProxies, teleop_config_with_passivity, write_link_stats
from harness.demo.orchestrator import JudgementVoid, ProcessDied, ProcessSpec, Stack
from harness.demo.parts import BridgePart, CompanionPart, SitlPart
from harness.demo.recorder import Recorder
from harness.demo.report import (
    FlightLog,
    avoidance_distances,
    compute_report,
    load_flight,
    summary_table,
    write_report,
)
from harness.ports import PORT_BLOCK_SIZE, PORT_NAMES, Ports
from quadlink import CONFIG_DIR
from quadlink.errors import ConfigError

log = logging.getLogger("harness.demo")

DEFAULT_SCRIPT = CONFIG_DIR / "teleop_scripts" / "paper_experiment.yaml"
# The flight's duration counts from the operator's start: a lock-step SITL on an idle machine runs several times
# faster than the wall while the parts start one after the other (seconds of wall time, tens of simulated
# seconds before the operator is there). The SITL's own bound only stops a SITL left behind.
SITL_DURATION_MARGIN_S = 300.0
STARVED_PARTS = ("bridge", "companion")  # the parts a CPU share holds: what runs on the companion board
JOURNAL_NAME = "companion.qljn"   # the companion's input journal (--journal): quadlink replay-companion re-runs it
BRIDGE_JOURNAL_NAME = "bridge.qlbj"   # the bridge's (--journal too): quadlink replay-bridge re-runs it
TELEOP_JOURNAL_NAME = "teleop.qltj"   # the lock-stepped ground station's (--journal, deterministic): replay-teleop


#: the demo operator's entry of the room's height is this much above the truth: the unsafe side of the +-10 cm a
#: tape measure and a rough guess give (issue 29: no operator knows the ceiling to the millimetre); campaigns draw it
ROOM_HEIGHT_ENTRY_ERROR_M = 0.10


@dataclass(frozen=True)
class FlightSpec:
    """Everything a flight is made of besides ports: what ``flight.json`` holds and ``--replay`` re-flies.

    ``operator`` is ``haptic`` (the ground station with the virtual device running ``script``, a teleop
    script) or ``offboard`` (:mod:`harness.campaign.offboard_client` flying ``script``, an offboard plan).
    Paths are absolute or relative to the flight's folder.
    """

    scenario: str
    script: str
    duration_s: float
    operator: str = "haptic"
    sitl_config: str | None = None
    lockstep: bool = True
    speed: float = 1.0
    view: bool = True  # the operator's image view (no effect on the flight; headless saves CPU)
    deterministic: bool = False  # the deterministic lock-step (quadlink.lockstep): the same spec flies the same bytes
    settle_s: float = 0.0  # run_demo's settle_s: how long the vehicle may fly on after the operator's session
    room_height_error_m: float | None = ROOM_HEIGHT_ENTRY_ERROR_M  # the operator's entry - the truth; None: not entered
    companion_config: str | None = None  # the companion's YAML (None: the nominal one with the room's height entry)
    board: str | None = None  # the SITL's board: model (Python) or avr (the firmware binary in simavr); None: config

    def resolve(self, folder: Path) -> FlightSpec:
        def r(p: str | None) -> str | None:
            """Relative to the folder; an absolute path that is gone (a moved or copied flight) by its name."""
            if p is None:
                return None
            q = Path(p)
            if not q.is_absolute():
                return str(folder / q) if (folder / q).exists() else p
            return str(q) if q.exists() or not (folder / q.name).exists() else str(folder / q.name)

        return FlightSpec(r(self.scenario) or self.scenario, r(self.script) or self.script, self.duration_s,
                          self.operator, r(self.sitl_config), self.lockstep, self.speed, self.view,
                          self.deterministic, self.settle_s, self.room_height_error_m, r(self.companion_config),
                          self.board)


def write_companion_config(out_dir: Path, **sections: object) -> Path:
    """configs/companion.yaml with some keys replaced (a section's dict is merged into it,
    ``reference={"room_height_m": 3.0}``; any other value replaces the key), written to
    ``out_dir/companion.yaml``."""
    import yaml

    data = yaml.safe_load((CONFIG_DIR / "companion.yaml").read_text())
    for key, value in sections.items():
        data[key] = {**data.get(key, {}), **value} if isinstance(value, dict) else value
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / "companion.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def companion_config_for_room(out_dir: Path, scenario: str, room_height_error_m: float | None) -> Path:
    """The companion's configuration for a flight in ``scenario``'s room: the height the operator enters as the
    ceiling (``reference.room_height_m``), as for an indoor flight (the camera never sees the ceiling; PX4's
    GF_MAX_VER_DIST and ArduPilot's FENCE_ALT_MAX are set the same way). The entry is the room's true height plus
    ``room_height_error_m``; ``None``: the operator entered nothing (only the altitude fence holds). The height
    entered is the lowest overhead (:func:`sim_sitl.scenario_gen.lowest_overhead_m`), as the user's guide asks of
    the operator: the camera never sees above the vehicle's level, so a soffit lower than the ceiling is kept from
    only by the entry (campaign 24, flight 27: 0.106 m under a soffit 0.36 m below the ceiling entered)."""
    from sim_sitl.config import load_scenario
    from sim_sitl.scenario_gen import lowest_overhead_m

    if room_height_error_m is None:
        return write_companion_config(out_dir, reference={"room_height_m": None})
    entered_m = lowest_overhead_m(load_scenario(scenario)) + room_height_error_m
    return write_companion_config(out_dir, reference={"room_height_m": round(entered_m, 2)})




LOCKSTEP_ODOM_LOSS_T_S = 1.0   # the bridge's odometry-loss timeout in lock-step flights (sim seconds)


def build_specs(scenario: str, script: Path, out_dir: Path, ports: Ports, lockstep: bool, speed: float,
                duration_s: float, record_frames: bool = False, sitl_config: str | None = None,
                operator: str = "haptic", view: bool = True, via_netem: bool = False,
                teleop_config: Path | None = None, signing_key: Path | None = None,
                companion_config: Path | None = None, deterministic: bool = False,
                settle_s: float = 0.0, room_height_error_m: float | None = ROOM_HEIGHT_ENTRY_ERROR_M,
                board: str | None = None, journal: bool = False) -> list[ProcessSpec]:
    """The parts of a flight in start order. ``view=False`` runs headless: no operator image stream from the
    companion, no view or web page in the ground station (neither feeds back into the flight: the haptic
    cue's pan-scan estimate comes from TELEOP_FEEDBACK, not from the images), which saves their CPU.
    ``via_netem``: the ground station talks to the netem proxies' ports (harness.demo.link). ``signing_key``:
    the ground link is MAVLink 2 signed with this key (quadlink keygen), and the companion refuses unsigned
    ground-station packets (issue 16). ``companion_config``: the companion's YAML (default: configs/companion.yaml
    with the operator's entry of the room's height, the truth plus ``room_height_error_m``,
    :func:`companion_config_for_room`). ``deterministic``: the SITL serves the
    deterministic lock-step (:mod:`quadlink.lockstep`) and ends the flight itself on simulated time
    (``duration_s`` from the operator's start, or, once the operator has left, at the disarm or ``settle_s``
    later); the bridge, the companion and the operator step with it."""
    if deterministic and (not lockstep or via_netem or view):
        raise ConfigError("a deterministic flight is in lock-step, headless (--no-view) and without netem")
    signed = ("--signing-key", str(signing_key)) if signing_key is not None else ()
    if companion_config is None:
        companion_config = companion_config_for_room(out_dir, scenario, room_height_error_m)
    params = out_dir / "bridge_params.yaml"
    if lockstep and not deterministic and not params.exists():
        # Lock-step runs the SITL up to ~2x real time and the bridge counts its timeouts in sim time, while the
        # companion's ODOMETRY reaches it over UDP with wall-clock jitter: on a loaded 2-core machine 0.3 s of
        # wall time (0.5 s of sim) passed without one and the bridge landed in flight (campaign 7, flight 8
        # re-flown). Plain lock-step flights give it the wall-clock margin of a real-time flight; real time and the
        # deterministic lock-step (every part on simulated time: no wall-clock jitter) fly the shipped 0.5 s.
        params.write_text(f"BRG_ODOM_LOSS_T: {LOCKSTEP_ODOM_LOSS_T_S}\n")
    vehicle_port, image_port = (ports.vehicle_netem, ports.image_netem) if via_netem else (ports.vehicle, ports.image)
    sitl = SitlPart(scenario, lockstep=lockstep, deterministic=deterministic, end_after_operator_s=settle_s,
                    duration_s=duration_s if deterministic else float(f"{duration_s + SITL_DURATION_MARGIN_S:.0f}"),
                    config=sitl_config, board=board, speed=None if speed == 1.0 else speed,
                    truth_tlog=out_dir / "truth.tlog")
    stepped: tuple[str, ...] = ()
    if deterministic:
        stepped = ("--lockstep", f"tcp://127.0.0.1:{ports.lockstep}")
    if operator == "offboard":
        operator_spec = ProcessSpec("operator", ("--vehicle", f"udpout:127.0.0.1:{ports.vehicle}",
                                                 "--plan", str(script), *stepped),
                                    ready_after_s=0.5, module="harness.campaign.offboard_client")
    elif operator == "haptic":
        operator_spec = ProcessSpec(
            "teleop", ("teleop", "--device", "virtual", "--script", str(script),
                       "--vehicle", f"udpout:127.0.0.1:{vehicle_port}",
                       "--image-stream", f"tcp://127.0.0.1:{image_port}" if view else "none",
                       *(("--config", str(teleop_config)) if teleop_config else ()),
                       "--http-port", str(ports.http) if view else "-1", "--log-csv", str(out_dir / "teleop.csv"),
                       "--exit-at-script-end", "--script-clock", "vehicle" if lockstep else "wall", *signed,
                       *(("--journal", str(out_dir / TELEOP_JOURNAL_NAME)) if journal and deterministic else ()),
                       *stepped),
            ready_after_s=0.5)
    else:
        raise ConfigError(f"unknown operator {operator!r} (haptic or offboard)")
    return [
        sitl.spec(ports),
        BridgePart(params, journal=out_dir / BRIDGE_JOURNAL_NAME if journal else None, tlog=out_dir / "bridge.tlog",
                   deterministic=deterministic).spec(ports),
        CompanionPart(companion_config, image_stream=view, tlog=out_dir / "companion.tlog", signing_key=signing_key,
                      record_frames=out_dir / "frames.qlcf" if record_frames else None,
                      journal=out_dir / JOURNAL_NAME if journal else None, deterministic=deterministic).spec(ports),
        operator_spec,
    ]


def run_demo(scenario: str, duration_s: float, out_dir: Path, script: Path, lockstep: bool = True,
             speed: float = 1.0, port_offset: int = 0, progress_every_s: float = 3.0,
             record_frames: bool = False, port_base: int | None = None, sitl_config: str | None = None,
             operator: str = "haptic", should_stop: Callable[[], bool] | None = None,
             view: bool = True, plots: bool = True,
             on_flight: Callable[[FlightLog], None] | None = None, link: LinkImpairment | None = None,
             passivity: bool | None = None, signing_key: Path | None = None,
             settle_s: float = 0.0, deterministic: bool = False,
             room_height_error_m: float | None = ROOM_HEIGHT_ENTRY_ERROR_M,
             companion_config: Path | None = None, board: str | None = None,
             cpu_share: CpuShare | None = None, journal: bool = False) -> dict[str, object]:
    """Fly the demo; returns the report. Raises :class:`ProcessDied` if a part dies.

    Writes ``out_dir/flight.json`` (the :class:`FlightSpec`, what ``--replay`` re-flies) and
    ``out_dir/logs/pids`` (the parts' process ids, so a supervisor can kill them if this process dies).
    ``should_stop`` is polled five times a second: True ends the flight early as Ctrl-C does. With
    ``plots=False`` only ``report.json`` is written, and ``on_flight`` gets the logs' time series (parsed once).
    ``link``: the ground link goes through the netem proxies with this impairment (issue 18);
    ``passivity``: the force loop's passivity controller (default: on when ``link`` is given);
    ``signing_key``: sign the ground link with this key file and refuse unsigned packets at the companion.
    ``settle_s``: when the operator's session or the duration ends with the vehicle still armed, the stack flies
    on without the operator for up to this many simulated seconds, until the autopilot disarms: the companion's
    failsafe lands it (a campaign's flight ends on the ground, not torn down in the air).
    ``deterministic``: the deterministic lock-step (:func:`build_specs`): the SITL ends the flight on simulated
    time, and the same arguments fly the same flight, bit for bit.
    ``companion_config``: the companion's YAML (default: configs/companion.yaml with the room's height; a
    falsification flight gives one with a room-height error or the pan-scan off).
    ``cpu_share``: the bridge and the companion run in this CPU share (:class:`harness.cpu_share.CpuShare`, entered
    by the caller): a starved companion board (issue 30). ``journal``: the companion journals its inputs to
    ``out_dir/companion.qljn`` (``quadlink replay-companion`` re-runs it bit for bit).
    """
    if signing_key is not None and not Path(signing_key).is_file():
        raise ConfigError(f"{signing_key}: signing key not found (create one with: quadlink keygen FILE)")
    if not Path(script).is_file():
        raise ConfigError(f"{script}: operator script not found")
    out_dir.mkdir(parents=True, exist_ok=True)
    spec = FlightSpec(str(scenario), str(script), float(duration_s), operator, sitl_config, lockstep, speed, view,
                      deterministic, settle_s, room_height_error_m,
                      str(companion_config) if companion_config is not None else None, board)
    (out_dir / "flight.json").write_text(json.dumps(dataclasses.asdict(spec), indent=2) + "\n")
    ports = Ports(port_offset, port_base)
    stack = Stack(out_dir / "logs")
    recorder = Recorder()
    # the live state (progress, the senders' check, armed for the settle); the logs are the senders' own (the
    # SITL's --truth-tlog, the bridge's --tlog): a UDP listener in this process drops packets when it is starved
    recorder.watch("truth", f"udpin:127.0.0.1:{ports.truth}", is_truth=True)
    recorder.watch("bridge", f"udpin:127.0.0.1:{ports.gcs_bridge}")
    interrupted = False
    failure: ProcessDied | None = None
    proxies: LinkProxies | None = None
    passivity_on = (link is not None) if passivity is None else passivity
    teleop_config = teleop_config_with_passivity(out_dir, passivity_on) if passivity_on or link else None

    def on_sigint(signum: int, frame: object) -> None:
        nonlocal interrupted
        interrupted = True

    # signal handlers can only be set from the main thread (a Ray task or a test thread may run us elsewhere)
    main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGINT, on_sigint) if main_thread else None
    t_wall0 = time.monotonic()
    specs = build_specs(scenario, Path(script), out_dir, ports, lockstep, speed, duration_s, record_frames,
                        sitl_config, operator, view, via_netem=link is not None, teleop_config=teleop_config,
                        signing_key=signing_key, deterministic=deterministic, settle_s=settle_s,
                        room_height_error_m=room_height_error_m, companion_config=companion_config, board=board,
                        journal=journal)
    operator_name = specs[-1].name
    try:
        for part in specs:
            if interrupted or (should_stop is not None and should_stop()):
                interrupted = True
                break
            if part.name == "teleop" and link is not None:
                proxies = LinkProxies(link, ports.vehicle_netem, ports.vehicle, ports.image_netem, ports.image)
                log.info("ground link through netem: %.0f ms one way, %.0f ms jitter, %.1f %% loss", link.delay_ms,
                         link.jitter_ms, 100 * link.loss)
            stack.start(part)
            if cpu_share is not None and part.name in STARVED_PARTS:
                cpu_share.add(stack.running[-1].popen.pid)
        # the flight's clock starts with the operator (the SITL ran on while the parts started)
        t_sim0 = recorder.truth.sim_time_s if math.isfinite(recorder.truth.sim_time_s) else 0.0
        log.info("all parts running at %.1f s simulated; operator view at http://127.0.0.1:%d ; logs in %s",
                 t_sim0, ports.http, stack.log_dir)
        next_progress = 0.0
        operator_done = False
        if deterministic:
            interrupted = interrupted or _await_sitl_end(recorder, stack, should_stop, t_wall0, progress_every_s)
        while not interrupted and not deterministic:
            time.sleep(0.2)
            if should_stop is not None and should_stop():
                interrupted = True
                break
            if operator_name in stack.check(may_finish=frozenset({operator_name})):
                log.info("operator script finished")
                operator_done = True
                break
            t = recorder.truth
            if math.isfinite(t.sim_time_s) and t.sim_time_s >= t_sim0 + duration_s:
                log.info("duration of %.0f s simulated time reached", duration_s)
                break
            if time.monotonic() >= next_progress:
                next_progress = time.monotonic() + progress_every_s
                _log_progress(recorder, t_wall0)
        if settle_s > 0.0 and operator_done and not interrupted and recorder.vehicle_armed:
            interrupted = _settle(recorder, stack, operator_name, settle_s, should_stop, t_wall0, progress_every_s)
    except ProcessDied as exc:
        failure = exc
        log.error("stopping: %s", exc)
    finally:
        if previous is not None:
            signal.signal(signal.SIGINT, previous)
        cpu = stack.cpu_seconds()
        codes = stack.stop()
        recorder.stop()
        if proxies is not None:
            write_link_stats(out_dir, proxies)
            proxies.close()
        log.info("stopped (exit statuses: %s)", ", ".join(f"{k}={v}" for k, v in codes.items()))
    if plots:
        report = write_report(out_dir, cpu, str(scenario))
    else:  # the metrics alone (a campaign draws its own figures; the plots cost seconds on a loaded machine)
        flight = load_flight(out_dir)
        if on_flight is not None:
            on_flight(flight)
        report = compute_report(flight, cpu, str(scenario), *avoidance_distances(out_dir))
        report["plots"] = []
        (out_dir / "report.json").write_text(json.dumps(report, indent=2, default=float) + "\n")
    if len(recorder.truth_senders) > 1 and failure is None:   # another vehicle's truth in the track: no judgement
        failure = JudgementVoid(f"ground truth came from {len(recorder.truth_senders)} senders on port {ports.truth}: "
                                "another SITL sends its truth there; this flight's judgement is void (fly it on free "
                                "ports)")
    report["interrupted"] = interrupted
    report["failure"] = str(failure) if failure else None
    report["wall_time_s"] = time.monotonic() - t_wall0
    if failure:
        raise failure
    return report


def _log_progress(recorder: Recorder, t_wall0: float) -> None:
    t = recorder.truth
    speed_m_s = math.hypot(*t.velocity_ned_m_s[:2]) if math.isfinite(t.velocity_ned_m_s[0]) else math.nan
    log.info("t_sim %6.1f s  (wall %5.0f s)  altitude %5.2f m  speed %4.2f m/s  nearest obstacle "
             "%5.2f m  [truth %d msgs, bridge %d msgs]", t.sim_time_s, time.monotonic() - t_wall0,
             -t.position_ned_m[2], speed_m_s, t.nearest_obstacle_m, recorder.counts.get("truth", 0),
             recorder.counts.get("bridge", 0))


def _await_sitl_end(recorder: Recorder, stack: Stack, should_stop: Callable[[], bool] | None, t_wall0: float,
                    progress_every_s: float) -> bool:
    """A deterministic flight: the SITL ends it (on simulated time); wait for that. Interrupted? Any part that
    exits with a non-zero status raises :class:`ProcessDied`; parts that end cleanly (the operator at the end of
    its session, the others when the simulation has ended) are fine."""
    names = frozenset(r.spec.name for r in stack.running)
    next_progress = time.monotonic() + progress_every_s
    while True:
        time.sleep(0.2)
        if should_stop is not None and should_stop():
            return True
        if "sitl" in stack.check(may_finish=names):
            log.info("the simulation ended the flight at %.1f s simulated", recorder.truth.sim_time_s)
            return False
        if time.monotonic() >= next_progress:
            next_progress = time.monotonic() + progress_every_s
            _log_progress(recorder, t_wall0)


def _settle(recorder: Recorder, stack: Stack, operator_name: str, settle_s: float,
            should_stop: Callable[[], bool] | None, t_wall0: float, progress_every_s: float) -> bool:
    """With the operator gone, fly on until the autopilot disarms or ``settle_s`` simulated seconds pass;
    interrupted? (A part that dies meanwhile raises :class:`ProcessDied`, as in the flight.)"""
    t_end = recorder.truth.sim_time_s + settle_s
    log.info("the vehicle is still armed: flying on for up to %.0f s simulated until it lands", settle_s)
    next_progress = time.monotonic() + progress_every_s
    while recorder.vehicle_armed:
        time.sleep(0.2)
        if should_stop is not None and should_stop():
            return True
        stack.check(may_finish=frozenset({operator_name}))
        if not recorder.truth.sim_time_s < t_end:   # reached (or the truth stream went silent: NaN)
            log.warning("still armed %.0f s after the session's end", settle_s)
            return False
        if time.monotonic() >= next_progress:
            next_progress = time.monotonic() + progress_every_s
            _log_progress(recorder, t_wall0)
    log.info("disarmed at %.1f s simulated", recorder.truth.sim_time_s)
    return False


def replay_flight(flight_dir: Path, out_dir: Path | None = None, port_offset: int = 0,
                  port_base: int | None = None, progress_every_s: float = 3.0,
                  journal: bool = False) -> tuple[dict[str, object], Path]:
    """Fly ``flight_dir/flight.json`` again (into ``flight_dir/replay`` by default; ``journal``: with the
    companion's and the bridge's input journals); returns (report, folder)."""
    path = flight_dir / "flight.json"
    if not path.is_file():
        raise ConfigError(f"{path}: no flight.json (fly it with quadlink demo or quadlink campaign first)")
    try:
        spec = FlightSpec(**json.loads(path.read_text())).resolve(flight_dir)
    except (TypeError, json.JSONDecodeError) as exc:
        raise ConfigError(f"{path}: not a flight spec: {exc}") from exc
    out = out_dir or flight_dir / "replay"
    report = run_demo(spec.scenario, spec.duration_s, out, Path(spec.script), spec.lockstep, spec.speed, port_offset,
                      progress_every_s, port_base=port_base, sitl_config=spec.sitl_config, operator=spec.operator,
                      view=spec.view, settle_s=spec.settle_s, deterministic=spec.deterministic,
                      room_height_error_m=spec.room_height_error_m,
                      companion_config=Path(spec.companion_config) if spec.companion_config else None,
                      board=spec.board, journal=journal)
    return report, out


def compare_reports(original: dict[str, Any], replay: dict[str, Any]) -> list[tuple[str, Any, Any]]:
    """The metrics (numbers, flattened ``a.b`` keys) that differ between two reports: (key, original, replay)."""
    def flat(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
        out: dict[str, Any] = {}
        for k, v in d.items():
            if k in ("cpu_core_s_per_sim_s", "plots", "wall_time_s", "targets"):
                continue
            if isinstance(v, dict):
                out.update(flat(v, f"{prefix}{k}."))
            elif isinstance(v, (int, float)) and not isinstance(v, bool):
                out[prefix + k] = v
        return out

    a, b = flat(original), flat(replay)
    return [(k, a.get(k), b.get(k)) for k in sorted(set(a) | set(b))
            if not (a.get(k) == b.get(k) or (isinstance(a.get(k), float) and isinstance(b.get(k), float)
                                             and math.isnan(a[k]) and math.isnan(b[k])))]


@click.command(name="demo")
@click.option("--scenario", default="paper-arena", show_default=True,
              help="SITL scenario (configs/scenarios/) or YAML path.")
@click.option("--duration", "duration_s", default=90.0, show_default=True, help="Simulated seconds at most.")
@click.option("--out", "out_dir", default=None, type=click.Path(path_type=Path),
              help="Folder for tlogs, report.json and plots [flight-report; with --replay: DIR/replay].")
@click.option("--script", default=str(DEFAULT_SCRIPT), show_default=True, type=click.Path(path_type=Path),
              help="Scripted operator for the virtual haptic device.")
@click.option("--lockstep/--realtime", default=True, show_default=True,
              help="Lock-step keeps every part in step with simulated time on a loaded machine.")
@click.option("--speed", default=1.0, show_default=True, help="Real-time factor in --realtime mode.")
@click.option("--port-offset", default=0, show_default=True, help="Shift every port (run beside another stack).")
@click.option("--port-base", type=int, default=None,
              help=f"Use the {PORT_BLOCK_SIZE} ports BASE.. ({', '.join(PORT_NAMES)}) instead of the defaults.")
@click.option("--replay", "replay_dir", type=click.Path(file_okay=False, exists=True, path_type=Path), default=None,
              help="Re-fly the flight recorded in DIR (its flight.json: arena, operator, configs) and compare "
                   "its metrics with DIR/report.json.")
@click.option("--view/--no-view", default=True, show_default=True,
              help="The operator's image view (companion image stream, ground-station page); --no-view saves CPU.")
@click.option("--record-frames", is_flag=True,
              help="Also record the companion's camera frames to OUT/frames.qlcf (~11 MB per second of flight).")
@click.option("--journal", is_flag=True,
              help=f"Journal every input the companion handles to OUT/{JOURNAL_NAME} (~12 MB per second of flight), "
                   f"the bridge's to OUT/{BRIDGE_JOURNAL_NAME} (~0.1 MB/s) and, in a --deterministic flight, the "
                   f"ground station's turns to OUT/{TELEOP_JOURNAL_NAME}: `quadlink replay-companion`, "
                   "`replay-bridge` and `replay-teleop` re-run each bit for bit.")
@click.option("--link-delay-ms", type=float, default=None,
              help="Ground link through netem: one-way delay (ms, each direction) [issue 18].")
@click.option("--link-jitter-ms", type=float, default=None, help="Ground link jitter (ms, std dev).")
@click.option("--link-loss", type=float, default=None, help="Ground link packet loss (0-1, MAVLink; TCP images: none).")
@click.option("--link-seed", type=int, default=0, show_default=True, help="Seed of the link's impairment.")
@click.option("--passivity/--no-passivity", default=None,
              help="Force loop passivity controller [default: on with --link-*, else the teleop config's].")
@click.option("--signing-key", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Sign the ground link with this MAVLink 2 key (quadlink keygen FILE); the companion then "
                   "refuses unsigned ground-station packets.")
@click.option("--deterministic", is_flag=True,
              help="The deterministic lock-step (quadlink/lockstep.py; needs --no-view, no --link-*): every part steps "
                   "with the SITL and the SITL ends the flight, so the same flight re-flies bit for bit (--replay).")
@click.option("--board", type=click.Choice(["model", "avr"]), default=None,
              help="The SITL's flight controller: model (the Python board) or avr (the firmware binary, "
                   "firmware/build/quadlink-fc.elf, in simavr); default: configs/sitl.yaml.")
def command(scenario: str, duration_s: float, out_dir: Path | None, script: Path, lockstep: bool, speed: float,
            port_offset: int, port_base: int | None, replay_dir: Path | None, view: bool, record_frames: bool,
            link_delay_ms: float | None, link_jitter_ms: float | None, link_loss: float | None, link_seed: int,
            passivity: bool | None, signing_key: Path | None, deterministic: bool, board: str | None,
            journal: bool) -> None:
    """Fly the paper's experiment in the SITL (take off, drive, rotate, approach and push the obstacle, land)."""
    try:
        impaired = any(v is not None for v in (link_delay_ms, link_jitter_ms, link_loss))
        link = LinkImpairment(link_delay_ms or 0.0, link_jitter_ms or 0.0, link_loss or 0.0, link_seed) \
            if impaired else None
        if link is not None:
            link.impairment()   # validates (ConfigError names the bad value)
        if replay_dir is not None:
            report, out_dir = replay_flight(replay_dir, out_dir, port_offset, port_base, journal=journal)
        else:
            out_dir = out_dir or Path("flight-report")
            if journal and record_frames:
                raise ConfigError("--journal holds the frames already: give one of --journal and --record-frames")
            report = run_demo(scenario, duration_s, out_dir, script, lockstep, speed, port_offset,
                              record_frames=record_frames, journal=journal, port_base=port_base, view=view, link=link,
                              passivity=passivity, signing_key=signing_key, deterministic=deterministic, board=board)
    except ProcessDied as exc:
        click.echo(f"quadlink demo: {exc}", err=True)
        raise SystemExit(1) from exc
    plots = ", ".join(str(p) for p in report.get("plots", []))  # type: ignore[attr-defined]
    click.echo(f"\nFlight report ({out_dir}/report.json, plots: {plots}):")
    click.echo(summary_table(report))
    if replay_dir is not None and (replay_dir / "report.json").is_file():
        diffs = compare_reports(json.loads((replay_dir / "report.json").read_text()), report)
        if not diffs:
            click.echo(f"replay: every metric equals the original flight's ({replay_dir}/report.json)")
        else:
            click.echo(f"replay: {len(diffs)} metrics differ from {replay_dir}/report.json:")
            for key, a, b in diffs:
                click.echo(f"  {key:<44} {a!s:>14} -> {b!s:<14}")

"""``quadlink paper003 oval|hover --out DIR``: paper 003's two experiments through the whole stack (issue 19).

One command each: the SITL (lock-step), the bridge with the geometric tracker (``BRG_TRACKER`` 1), the companion
and a ground-station client in this process. The client takes off through the companion (MAV_CMD_NAV_TAKEOFF to
compid 191) and streams PX4-style position + velocity + acceleration SET_POSITION_TARGET_LOCAL_NED at 50 Hz of
the *vehicle's* clock (TELEOP_FEEDBACK stamps: in lock-step the simulation runs slower than the wall), as
``quadlink trajectory`` does (:func:`harness.trajectory_cli.setpoint_fields`). The companion closes the position
loop on its odometry and sends the bridge velocity + acceleration after its safety layer (companion.arbiter).

* ``oval``: ``configs/trajectories/oval.yaml`` (paper 003's P1..P4 in 9 s). The client first holds the first
  waypoint (``--lead-in`` s: the vehicle flies there and settles), then streams the trajectory and holds its
  end. Tables 3-5 of paper 003 from the companion's estimate (its LOCAL_POSITION_NED), the desired trajectory
  and the SITL truth, over the trajectory's 9 s.
* ``hover``: ``configs/scenarios/paper003-hover.yaml`` (three ~0.7 m pushes, z, y, x); the client holds a point
  with the same setpoints (p, v = 0, a = 0). Per push: peak displacement and the time back within 5 cm.

Writes ``DIR/paper003.json`` (tables, recoveries), ``DIR/series.csv`` and the plots (``--no-plots`` skips them),
the stack's logs in ``DIR/logs`` and the companion's tlog. Frames: the odometry's local NED starts at the take-off
pose with x along the start heading (perception.velocity: the first frame levelled, yaw 0); the SITL's truth
starts at the start position with the arena's axes. The figures turn the truth by the scenario's start yaw into
the odometry's axes, so the experiments are the same at any start pose (``--scenario``; the campaign's draws).
"""

from __future__ import annotations

import csv
import dataclasses
import json
import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import click
import numpy as np

from harness.demo.cli import Ports, build_specs, write_companion_config
from harness.demo.orchestrator import ProcessDied, Stack
from harness.demo.paper003 import (
    HOVER_SCENARIO,
    OVAL,
    Paper003Series,
    format_tables,
    hover_pass,
    make_plots,
    push_recoveries,
    resample,
    tables,
)
from harness.trajectory_cli import load_trajectory_file, trajectory_target
from quadlink.client import connect, land_command, takeoff_command
from quadlink.errors import ConfigError
from quadlink.frames import Rz
from quadlink.ids import AUTOPILOT_COMPONENT_ID, COMPANION_COMPONENT_ID
from quadlink.mavlink import mavlink
from quadlink.trajectory.minsnap import MinSnapTrajectory

log = logging.getLogger("quadlink.paper003")

SETPOINT_RATE_HZ = 50.0
FEEDBACK_CAMERA_FRESH = mavlink.QUADLINK_TELEOP_FLAGS_OBSTACLES_FRESH   # camera frames flow at the companion
MODE_TELEOP = mavlink.QUADLINK_TELEOP_MODE_TELEOP
MODE_HOLD = mavlink.QUADLINK_TELEOP_MODE_HOLD                  # TELEOP with no live source of motion (no script yet)
TAKEOFF_HEIGHT_M = 1.0
#: the take-off has handed over once the companion is in TELEOP/HOLD with the vehicle off the ground; the setpoints
#: then fly it to the experiment's height. Not the take-off's 1 m: a take-off that ends short (campaign hover
#: flight 2 of seed 19: the bridge's integrated climb said 0.95 m at 0.69 m true) would leave the client waiting
#: until the first push lifts the vehicle
AIRBORNE_M = 0.3
#: the companion as paper 003 flew: no pan-scan (a fixed heading), scripts may go where the camera has not looked
#: (the oval goes round the vehicle, the camera looks one way); the script and ground-station timeouts as the SITL
#: tests use them on a loaded machine (a starved client reads as a lost stream on wall time)
COMPANION_OVERRIDES: dict[str, dict[str, object]] = {
    "pan_scan": {"enabled": False},
    "obstacles": {"scripts_into_unknown": True},
    "modes": {"gcs_timeout_s": 2.0},
    "arbiter": {"operator_timeout_s": 2.0, "script_timeout_s": 2.0},
}
#: the bridge: paper 003's geometric tracker with the drag feed-forward at the SITL's drag per unit mass (airframe
#: 0.25 N s/m + rotor drag 0.02 N s/m per N at hover, 1 kg: 0.45 1/s; a real vehicle's is identified from a flight);
#: board/odometry loss timeouts for a loaded machine's lock-step stalls
BRIDGE_PARAMS = {"BRG_TRACKER": 1.0, "BRG_GEO_DRAG": 0.45, "BRG_BOARD_LOSS_T": 3.0, "BRG_ODOM_LOSS_T": 2.0}


def write_configs(out_dir: Path, companion_overrides: dict[str, dict[str, object]] | None = None,
                  estimator: str = "filters") -> Path:
    """The companion's YAML (configs/companion.yaml with :data:`COMPANION_OVERRIDES`; perception's velocity
    estimator ``filters``, eqs. 9-13 of paper 000, or ``ukf``, paper 003's) and the bridge's parameter file
    (``bridge_params.yaml``, which build_specs passes) in ``out_dir``; returns the companion's path."""
    overrides: dict[str, object] = {**COMPANION_OVERRIDES, **(companion_overrides or {})}
    out_dir.mkdir(parents=True, exist_ok=True)
    if estimator != "filters":
        (out_dir / "perception.yaml").write_text(f"estimator: {estimator}\n")
        overrides["perception_config"] = str(out_dir / "perception.yaml")
    path = write_companion_config(out_dir, **overrides)
    (out_dir / "bridge_params.yaml").write_text("".join(f"{k}: {v}\n" for k, v in BRIDGE_PARAMS.items()))
    return path


@dataclass
class Recording:
    """Time series as received (vehicle time, s; local NED)."""

    truth: list[tuple[float, float, float, float, float, float, float]] = field(default_factory=list)
    estimate: list[tuple[float, float, float, float, float, float, float]] = field(default_factory=list)
    statustexts: list[str] = field(default_factory=list)

    @staticmethod
    def arrays(rows: Sequence[tuple[float, ...]]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        a = np.asarray(rows, dtype=float).reshape(-1, 7)
        a = a[np.argsort(a[:, 0], kind="stable")]
        _, first = np.unique(a[:, 0], return_index=True)
        a = a[first]
        return a[:, 0], a[:, 1:4], a[:, 4:7]


class Client:
    """The ground station on the companion's endpoint (a :class:`quadlink.client.GroundClient`: commands to the
    companion, setpoints to the autopilot through it, a 1 Hz heartbeat on the wall clock), the truth listener, and
    the vehicle's clock."""

    def __init__(self, ports: Ports, stack: Stack) -> None:
        from quadlink.mavlink.connection import open_mavlink

        self.stack = stack
        self.gcs = connect(f"udpout:127.0.0.1:{ports.vehicle}", target_component=COMPANION_COMPONENT_ID)
        self.truth = open_mavlink(f"udpin:127.0.0.1:{ports.truth}", 255, 0)
        self.rec = Recording()
        self.truth_t_s = math.nan
        self.height_m = 0.0

    @property
    def t_s(self) -> float:
        """The vehicle's clock as the companion reports it (TELEOP_FEEDBACK), s; NaN before the first."""
        t = self.gcs.state.time_s
        return math.nan if t is None else t

    @property
    def mode(self) -> int:
        return self.gcs.state.teleop_mode or 0

    @property
    def flags(self) -> int:
        return self.gcs.state.teleop_flags

    def close(self) -> None:
        self.gcs.close()
        self.truth.close()

    def pump(self) -> None:
        while (m := self.truth.recv_msg()) is not None:
            if m.get_type() == "LOCAL_POSITION_NED":
                self.truth_t_s = m.time_boot_ms / 1e3
                self.rec.truth.append((self.truth_t_s, m.x, m.y, m.z, m.vx, m.vy, m.vz))
        while (m := self.gcs.receive()) is not None:   # TELEOP_FEEDBACK: the client's state (t_s, mode, flags)
            kind = m.get_type()
            if kind == "LOCAL_POSITION_NED" and m.get_srcComponent() == COMPANION_COMPONENT_ID:
                self.rec.estimate.append((m.time_boot_ms / 1e3, m.x, m.y, m.z, m.vx, m.vy, m.vz))
                self.height_m = -m.z
            elif kind == "STATUSTEXT":
                text = f"{self.t_s:.1f} {m.text}"
                self.rec.statustexts.append(text)
                log.info("vehicle: %s", m.text)
        self.gcs.heartbeat_if_due()

    def wait(self, until: Callable[[], bool], wall_timeout_s: float, what: str,
             each: Callable[[], None] | None = None) -> None:
        deadline = time.monotonic() + wall_timeout_s
        while not until():
            if time.monotonic() > deadline:
                raise TimeoutError(f"{what}: not within {wall_timeout_s:.0f} s (wall); "
                                   f"status: {self.rec.statustexts[-5:]}")
            self.stack.check()
            self.pump()
            if each is not None:
                each()
            time.sleep(0.005)

    def take_off(self) -> None:
        self.wait(lambda: bool(self.flags & FEEDBACK_CAMERA_FRESH), 180.0, "camera frames at the companion")
        self.gcs.send_command_long(takeoff_command(TAKEOFF_HEIGHT_M))
        self.wait(lambda: self.mode in (MODE_TELEOP, MODE_HOLD) and self.height_m > AIRBORNE_M, 240.0,
                  "take-off to teleop")
        log.info("airborne at vehicle time %.1f s, height %.2f m", self.t_s, self.height_m)
        if self.height_m < TAKEOFF_HEIGHT_M - 0.25:
            log.warning("the take-off ended at %.2f m (companion's height), short of %.1f m", self.height_m,
                        TAKEOFF_HEIGHT_M)

    def stream(self, traj: MinSnapTrajectory, t0_s: float, until_s: float, yaw_rad: float,
               wall_timeout_s: float) -> None:
        """Setpoints of ``traj`` at vehicle time t (sample t - t0, the first point before t0, the last after its
        end) at :data:`SETPOINT_RATE_HZ` of the vehicle's clock, until vehicle time ``until_s``."""
        period = 1.0 / SETPOINT_RATE_HZ
        next_s = self.t_s
        zero = np.zeros(3)

        def send() -> None:
            nonlocal next_s
            if not math.isfinite(self.t_s) or self.t_s < next_s:
                return
            next_s = self.t_s + period
            s = traj.sample(min(max(self.t_s - t0_s, 0.0), traj.duration_s))
            if self.t_s < t0_s or self.t_s > t0_s + traj.duration_s:     # lead-in and hold: rest at the point
                s = type(s)(s.t_s, s.p_m, zero, zero, zero)
            self.gcs.send_position_target(trajectory_target(s, zero, yaw_rad), int(self.t_s * 1e3),
                                          target_component=AUTOPILOT_COMPONENT_ID)

        self.wait(lambda: self.t_s >= until_s, wall_timeout_s, f"vehicle time {until_s:.0f} s", each=send)

    def land(self) -> None:
        self.gcs.send_command_long(land_command())


def _series(rec: Recording, traj: MinSnapTrajectory, t0_s: float, start_yaw_rad: float = 0.0, align_s: float = 1.0
            ) -> tuple[Paper003Series, np.ndarray]:
    """The trajectory's window on the estimate's time base (camera frames), truth interpolated onto it and moved
    into the odometry's frame: turned from the arena's axes by the start yaw (the odometry's x is the start
    heading); the truth's origin is the start position, the odometry's the take-off pose, and the odometry has
    drifted by the time the trajectory starts, so the truth is shifted by its mean difference from the estimate
    over the ``align_s`` before the start (the vehicle resting at the first waypoint); the drift during the
    trajectory stays in the figures. Returns the series and that shift (local NED, m)."""
    t_e, p_e, v_e = rec.arrays(rec.estimate)
    t_t, p_arena, v_arena = rec.arrays(rec.truth)
    R_arena_odo = Rz(start_yaw_rad)   # odometry axes -> arena axes; rows: p_odo = p_arena R_arena_odo
    p_t, v_t = p_arena @ R_arena_odo, v_arena @ R_arena_odo
    before = (t_e >= t0_s - align_s) & (t_e < t0_s)
    shift = np.nanmean(resample(t_e[before], t_t, p_t) - p_e[before], axis=0) if np.any(before) else np.zeros(3)
    w = (t_e >= t0_s) & (t_e <= t0_s + traj.duration_s)
    t = t_e[w]
    samples = [traj.sample(x - t0_s) for x in t]
    p_d = np.array([s.p_m for s in samples]).reshape(-1, 3)
    v_d = np.array([s.v_m_s for s in samples]).reshape(-1, 3)
    return Paper003Series(t, p_d, v_d, resample(t, t_t, p_t) - shift, resample(t, t_t, v_t), p_e[w], v_e[w]), shift


def _write_csv(path: Path, s: Paper003Series) -> None:
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["t_s", *(f"{q}_{a}" for q in ("pd", "vd", "ptrue", "vtrue", "pest", "vest") for a in "xyz")])
        assert s.p_est_m is not None and s.v_est_m_s is not None
        for row in np.column_stack([s.t_s, s.p_d_m, s.v_d_m_s, s.p_true_m, s.v_true_m_s, s.p_est_m, s.v_est_m_s]):
            w.writerow([f"{x:.5f}" for x in row])


def run_paper003(experiment: str, out_dir: Path, port_offset: int = 0, port_base: int | None = None,
                 lockstep: bool = True, lead_in_s: float = 6.0, hold_s: float = 1.0, plots: bool = True,
                 scenario: str | None = None, trajectory: Path | None = None,
                 companion_overrides: dict[str, dict[str, object]] | None = None,
                 wall_timeout_s: float = 900.0, estimator: str = "filters",
                 sitl_config: str | None = None, journal: bool = False) -> dict[str, Any]:
    """Fly one experiment; returns (and writes to ``out_dir/paper003.json``) its figures. ``scenario``: the arena
    and start pose (name or path; default :data:`HOVER_SCENARIO` or ``empty``); ``sitl_config``: the SITL's YAML
    (``quadlink sitl --config``: vehicle, noise, seed), e.g. a campaign flight's ``sitl.yaml``; ``journal``: the
    companion journals its inputs to ``out_dir/companion.qljn`` (``quadlink replay-companion``)."""
    from sim_sitl.config import load_scenario

    if experiment not in ("oval", "hover"):
        raise ConfigError(f"unknown experiment {experiment!r} (oval or hover)")
    out_dir.mkdir(parents=True, exist_ok=True)
    ports = Ports(port_offset, port_base)
    scenario = scenario or (str(HOVER_SCENARIO) if experiment == "hover" else "empty")
    sc = load_scenario(scenario)
    start_yaw_rad = math.radians(sc.start.yaw_deg)
    if experiment == "oval":
        cfg, traj = load_trajectory_file(trajectory or OVAL)
        yaw = math.radians(cfg.yaw_deg)
        sim_s = 150.0
    else:
        pushes = [(d.start_s, d.start_s + d.duration_s) for d in sc.disturbances]
        hold_point = np.array([0.0, 0.0, -1.2])
        traj = _rest_at(hold_point)
        yaw = 0.0
        sim_s = max((e for _, e in pushes), default=0.0) + 60.0
    companion_yaml = write_configs(out_dir, companion_overrides, estimator)
    specs = build_specs(scenario, Path("unused"), out_dir, ports, lockstep, 1.0, sim_s, view=False,
                        companion_config=companion_yaml, sitl_config=sitl_config,
                        journal=journal)[:3]   # the client is us
    # at most real time: lock-step alone lets the SITL run unpaced while only the bridge gates it (before the
    # companion's camera client connects), which would spend the scenario's push times before the take-off
    specs[0] = dataclasses.replace(specs[0], args=(*specs[0].args, "--speed", "1.0"))
    stack = Stack(out_dir / "logs")
    client: Client | None = None
    t_wall0 = time.monotonic()
    report: dict[str, Any] = {"experiment": experiment, "scenario": scenario, "sitl_config": sitl_config,
                              "start_position_m": list(sc.start.position_m), "start_yaw_deg": sc.start.yaw_deg,
                              "lockstep": lockstep, "estimator": estimator, "bridge_params": BRIDGE_PARAMS}
    try:
        for part in specs:
            stack.start(part)
        client = Client(ports, stack)
        client.take_off()
        report["airborne"] = {"t_s": client.t_s, "height_m": client.height_m}   # the companion's height, m up
        if experiment == "oval":
            t0 = client.t_s + lead_in_s
            end = t0 + traj.duration_s + hold_s
            log.info("lead-in to %s, trajectory from vehicle time %.1f s to %.1f s", traj.sample(0.0).p_m, t0, end)
            client.stream(traj, t0, end, yaw, wall_timeout_s)
            client.land()
            series, shift = _series(client.rec, traj, t0, start_yaw_rad)
            report["trajectory"] = {"file": str(trajectory or OVAL), "start_s": t0, "duration_s": traj.duration_s,
                                    "peak_speed_m_s": traj.peak_speed_m_s(), "samples": int(series.t_s.size),
                                    "truth_to_odometry_shift_m": shift.tolist()}
            report["tables"] = tables(series)
            _write_csv(out_dir / "series.csv", series)
            if plots:
                report["plots"] = [str(p) for p in make_plots(series, out_dir)]
        else:
            last = max(e for _, e in pushes) + 8.0
            if client.t_s > pushes[0][0] - 3.0:
                raise RuntimeError(f"airborne only at vehicle time {client.t_s:.1f} s: the first push is at "
                                   f"{pushes[0][0]:.1f} s (move the scenario's pushes later)")
            client.stream(traj, 0.0, last, yaw, wall_timeout_s)
            client.land()
            report.update(_hover_figures(client.rec, pushes, hold_point))
    except ProcessDied as exc:
        report["failure"] = str(exc)
        raise
    finally:
        codes = stack.stop()
        if client is not None:
            report["statustexts"] = client.rec.statustexts[-40:]
            client.close()
            t_t, p_t, v_t = client.rec.arrays(client.rec.truth)
            np.savetxt(out_dir / "truth.csv", np.column_stack([t_t, p_t, v_t]), delimiter=",", fmt="%.5f",
                       header="t_s,x_m,y_m,z_m,vx_m_s,vy_m_s,vz_m_s (SITL truth, local NED from the start position)")
        report["exit_codes"] = codes
        report["wall_time_s"] = time.monotonic() - t_wall0
        (out_dir / "paper003.json").write_text(json.dumps(report, indent=2, default=_json) + "\n")
    return report


def _json(x: Any) -> Any:
    return float(x) if isinstance(x, (np.floating, np.integer)) else str(x)


def _rest_at(p_ned_m: np.ndarray) -> MinSnapTrajectory:
    """A "trajectory" that rests at a point (the hover's setpoints: p, v = 0, a = 0)."""
    from quadlink.trajectory.minsnap import minimum_snap

    return minimum_snap(np.array([p_ned_m, p_ned_m]), [1.0])


def _hover_figures(rec: Recording, pushes: list[tuple[float, float]], hold_point: np.ndarray) -> dict[str, Any]:
    t, p, v = rec.arrays(rec.truth)
    before = (t >= pushes[0][0] - 3.0) & (t < pushes[0][0])
    p_hold_true = p[before].mean(axis=0) if np.any(before) else hold_point
    rec_true = push_recoveries(t, p, v, p_hold_true, pushes)
    t_e, p_e, v_e = rec.arrays(rec.estimate)
    rec_est = push_recoveries(t_e, p_e, v_e, hold_point, pushes)
    return {"hold_point_ned_m": hold_point.tolist(), "hold_truth_ned_m": p_hold_true.tolist(),
            "recoveries_truth": [r.__dict__ for r in rec_true], "recoveries_estimate": [r.__dict__ for r in rec_est],
            "pass": hover_pass(rec_true)}


def format_hover(report: dict[str, Any]) -> str:
    lines = [f"{'push':<6} {'released s':>10} {'peak m':>8} {'peak m/s':>9} {'back (5 cm) s':>14}   (truth; paper 003: "
             "~0.7 m, back within 3 s)"]
    for name, r in zip("zyx", report.get("recoveries_truth", []), strict=False):
        lines.append(f"{name:<6} {r['release_s']:>10.1f} {r['peak_displacement_m']:>8.3f} {r['peak_speed_m_s']:>9.2f} "
                     f"{r['back_after_s']:>14.2f}")
    return "\n".join(lines)


@click.command(name="paper003")
@click.argument("experiment", type=click.Choice(["oval", "hover"]))
@click.option("--out", "out_dir", default=None, type=click.Path(path_type=Path),
              help="Folder for paper003.json, series and plots, the stack's logs [paper003-EXPERIMENT].")
@click.option("--port-offset", default=0, show_default=True, help="Shift every port (run beside another stack).")
@click.option("--port-base", type=int, default=None, help="Use the demo's port block from BASE.")
@click.option("--lockstep/--realtime", default=True, show_default=True)
@click.option("--lead-in", "lead_in_s", default=6.0, show_default=True,
              help="oval: seconds (vehicle time) holding the first waypoint before the trajectory starts.")
@click.option("--plots/--no-plots", default=True, show_default=True)
@click.option("--estimator", type=click.Choice(["filters", "ukf"]), default="filters", show_default=True,
              help="The companion's velocity estimator: paper 000's filters or paper 003's UKF.")
@click.option("--scenario", default=None,
              help="Arena and start pose (name or YAML path) [hover: paper003-hover.yaml, oval: empty].")
@click.option("--sitl-config", default=None, type=click.Path(exists=True, dir_okay=False),
              help="The SITL's YAML (vehicle, noise, seed), e.g. a campaign flight's sitl.yaml.")
def command(experiment: str, out_dir: Path | None, port_offset: int, port_base: int | None, lockstep: bool,
            lead_in_s: float, plots: bool, estimator: str, scenario: str | None, sitl_config: str | None) -> None:
    """Fly paper 003's hover (three pushes) or oval (9 s trajectory) through SITL, bridge, companion and a
    ground-station client; print the figures beside the paper's."""
    out_dir = out_dir or Path(f"paper003-{experiment}")
    try:
        report = run_paper003(experiment, out_dir, port_offset, port_base, lockstep, lead_in_s, plots=plots,
                              scenario=scenario, estimator=estimator, sitl_config=sitl_config)
    except ProcessDied as exc:
        click.echo(f"quadlink paper003: {exc}", err=True)
        raise SystemExit(1) from exc
    click.echo(f"\npaper 003 {experiment} ({out_dir}/paper003.json, {report['wall_time_s']:.0f} s wall):")
    click.echo(format_tables(report["tables"]) if experiment == "oval" else format_hover(report))

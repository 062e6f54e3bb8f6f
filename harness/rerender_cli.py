"""``quadlink rerender FLIGHT_DIR``: re-render a SITL flight's camera along its true path and look for phantoms.

A judge's tool, run after a flight: it reads the flight's truth (``truth.tlog``: the SITL's true position and
attitude on simulated time) and its ``flight.json`` (scenario, SITL configuration), rebuilds the scene, renders
the SITL's own camera (the same renderer and Xtion model, a noise draw of ``--seed``) at the true pose every
``--every-ms`` of simulated time, and runs the companion's obstacle extraction and hidden floor on each image
with the true attitude and height. Every point it finds within ``--near`` metres horizontally and inside the
avoidance's height band is looked up in the scene: a point farther than ``--phantom-m`` from every surface (the
floor included) is a **phantom**, something the image shows that is not there.

This is how the renderer's edge-on phantom was found (the demo's misses of round 3, `acac873`): the vehicle
stopped at a map point with nothing real near it; re-rendered along its path, the camera showed it. What it
cannot see: the flight's own noise draws (``--seed`` draws anew; try several), and anything after the camera
(the odometry's pose, the map's memory). Nothing of it reaches a flight: it reads a finished flight's files.

Exit status: 0 without phantoms, 1 with at least one (so a script can sweep flights), 2 on bad input.
"""

from __future__ import annotations

import json
import logging
import math
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import click
import numpy as np
from numpy.typing import NDArray

from companion.reference_params import ReferenceParams
from perception.hidden_floor import HiddenFloorConfig, hidden_floor_points_h
from perception.obstacles import ObstacleConfig, extract_obstacles
from quadlink.errors import ConfigError
from quadlink.frames import R_from_quat_wxyz, euler_from_R
from quadlink.mavlink.tlog import read_tlog

log = logging.getLogger(__name__)

BAND_M = ReferenceParams().vertical_band_m   # the avoidance's height band


@dataclass(frozen=True)
class TruePose:
    """The SITL's truth at one instant: simulated seconds, position (local NED from the start), velocity,
    attitude (body FRD -> NED) and body rates."""

    t_s: float
    p_ned_m: NDArray[np.float64]
    v_ned_m_s: NDArray[np.float64]
    R_ned_q: NDArray[np.float64]
    w_q_rad_s: NDArray[np.float64]


@dataclass(frozen=True)
class FrameFinding:
    """What one re-rendered frame shows inside the band and ``near``: its points' horizontal distances, the
    distance of each to the nearest surface, and the hidden floor's points (objects that return nothing)."""

    t_s: float
    height_m: float
    seen_m: NDArray[np.float64]          # (N,) horizontal distance of each seen point
    seen_surface_m: NDArray[np.float64]  # (N,) its distance to the nearest surface in the scene
    hidden_m: NDArray[np.float64]        # (M,) horizontal distance of each hidden-floor point
    hidden_surface_m: NDArray[np.float64]
    zero_depth_share: float

    def phantoms(self, phantom_m: float) -> int:
        return int((self.seen_surface_m > phantom_m).sum() + (self.hidden_surface_m > phantom_m).sum())


def read_truth(path: Path) -> list[TruePose]:
    """The truth log's poses, in time order (LOCAL_POSITION_NED and ATTITUDE_QUATERNION paired by their stamp)."""
    if not path.is_file():
        raise ConfigError(f"{path}: no truth log (a SITL flight's folder holds truth.tlog)")
    positions: dict[int, tuple[NDArray[np.float64], NDArray[np.float64]]] = {}
    attitudes: dict[int, tuple[NDArray[np.float64], NDArray[np.float64]]] = {}
    for _, m in read_tlog(path):
        if m.get_type() == "LOCAL_POSITION_NED":
            positions[m.time_boot_ms] = (np.array([m.x, m.y, m.z]), np.array([m.vx, m.vy, m.vz]))
        elif m.get_type() == "ATTITUDE_QUATERNION":
            attitudes[m.time_boot_ms] = (np.array([m.q1, m.q2, m.q3, m.q4]),
                                         np.array([m.rollspeed, m.pitchspeed, m.yawspeed]))
    poses = []
    for ms in sorted(set(positions) & set(attitudes)):
        (p, v), (q, w) = positions[ms], attitudes[ms]
        if np.all(np.isfinite(p)) and np.all(np.isfinite(q)) and float(np.linalg.norm(q)) > 0.5:
            poses.append(TruePose(ms / 1e3, p, v, R_from_quat_wxyz(q / np.linalg.norm(q)), w))
    if not poses:
        raise ConfigError(f"{path}: no true pose (LOCAL_POSITION_NED with ATTITUDE_QUATERNION) in it")
    return poses


def every(poses: list[TruePose], t_from_s: float, t_to_s: float, step_s: float) -> Iterator[TruePose]:
    """The poses in [t_from_s, t_to_s], at least ``step_s`` apart."""
    last = -math.inf
    for pose in poses:
        if t_from_s <= pose.t_s <= t_to_s and pose.t_s - last >= step_s - 1e-9:
            last = pose.t_s
            yield pose


class Rerenderer:
    """The flight's scene and camera, rebuilt from its ``flight.json``; :meth:`frame` re-renders one true pose."""

    def __init__(self, flight_dir: Path, seed: int) -> None:
        from quadlink.vehicle import load_vehicle
        from sim_sitl.camera_sim import RgbdCamera
        from sim_sitl.config import load_scenario, load_sitl_config
        from sim_sitl.vehicle_sim import SimVehicle

        meta_file = flight_dir / "flight.json"
        if not meta_file.is_file():
            raise ConfigError(f"{meta_file}: not found (a SITL flight's folder from quadlink demo, campaign or "
                              "falsify holds it)")
        try:
            meta = json.loads(meta_file.read_text(encoding="utf-8"))
        except json.JSONDecodeError as exc:
            raise ConfigError(f"{meta_file}: not JSON: {exc}") from exc
        if not isinstance(meta, dict) or not meta.get("scenario"):
            raise ConfigError(f"{meta_file}: no scenario")
        scenario = str(meta["scenario"])
        if not Path(scenario).is_file() and (flight_dir / Path(scenario).name).is_file():
            scenario = str(flight_dir / Path(scenario).name)
        sitl_config = meta.get("sitl_config") or None
        if sitl_config and not Path(sitl_config).is_file() and (flight_dir / Path(sitl_config).name).is_file():
            sitl_config = str(flight_dir / Path(sitl_config).name)       # a flight folder moved since
        self.cfg = load_sitl_config(sitl_config)
        vehicle = load_vehicle(self.cfg.vehicle)
        self.sim = SimVehicle(vehicle, self.cfg, load_scenario(scenario), np.random.default_rng(self.cfg.seed))
        self.camera = RgbdCamera(self.sim.world, vehicle.camera, self.cfg.camera_noise, np.random.default_rng(seed),
                                 vehicle.camera.width_px, vehicle.camera.height_px, self.cfg.camera.renderer)
        self.start_ned_m = np.asarray(self.sim.world.start_p_ned_m, dtype=float)
        self.obstacles = ObstacleConfig()
        self.hidden = HiddenFloorConfig()

    def frame(self, pose: TruePose, near_m: float) -> FrameFinding:
        from sim_sitl.world import RigidState

        p_ned = pose.p_ned_m + self.start_ned_m
        state = RigidState(pose.t_s, p_ned, pose.v_ned_m_s, pose.R_ned_q, pose.w_q_rad_s, np.zeros(3), np.zeros(4))
        rendered = self.camera.render(state, 0, pose.t_s)
        roll, pitch, yaw = euler_from_R(pose.R_ned_q)
        height_m = -float(p_ned[2])                      # the floor is z = 0 in the scene's NED
        depth = rendered.depth_m
        if depth is None:
            raise ConfigError("the SITL camera rendered no depth image")
        obs = extract_obstacles(depth, rendered.intrinsics, self.camera.R_qc, self.camera.p_qc_m, roll,
                                pitch, self.obstacles)
        hidden = hidden_floor_points_h(depth, rendered.intrinsics, self.camera.R_qc, self.camera.p_qc_m,
                                       roll, pitch, height_m, self.obstacles.min_range_m, self.obstacles.max_range_m,
                                       self.hidden)
        zero_share = float(np.mean(~np.isfinite(depth) | (depth <= 0)))
        seen, seen_surface = self._in_band(obs.points_h_m, p_ned, yaw, near_m)
        hid, hid_surface = self._in_band(hidden, p_ned, yaw, near_m)
        return FrameFinding(pose.t_s, height_m, seen, seen_surface, hid, hid_surface, zero_share)

    def _in_band(self, points_h_m: NDArray[np.float64], p_ned_m: NDArray[np.float64], yaw_rad: float,
                 near_m: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Horizontal distances of the points in the band within ``near_m``, and each one's distance to the
        nearest surface (H is yaw-aligned NED centred on the vehicle)."""
        ph = np.asarray(points_h_m, dtype=float).reshape(-1, 3)
        ph = ph[np.all(np.isfinite(ph), axis=1)]
        horiz = np.hypot(ph[:, 0], ph[:, 1])
        keep = (horiz < near_m) & (np.abs(ph[:, 2]) <= BAND_M)
        ph, horiz = ph[keep], horiz[keep]
        c, s = math.cos(yaw_rad), math.sin(yaw_rad)
        world = np.column_stack((c * ph[:, 0] - s * ph[:, 1], s * ph[:, 0] + c * ph[:, 1], ph[:, 2])) + p_ned_m
        surface = np.array([self.sim.world.nearest_distances(q, max_distance_m=5.0)[0] for q in world])
        return horiz, surface.reshape(-1)

    def close(self) -> None:
        self.sim.world.close()


def describe(f: FrameFinding, phantom_m: float) -> str:
    def nearest(d: NDArray[np.float64]) -> str:
        return f"{float(d.min()):.2f} m" if d.size else "-"

    ph = f.phantoms(phantom_m)
    worst = np.concatenate((f.seen_surface_m, f.hidden_surface_m))
    flag = f"  PHANTOM x{ph} (up to {float(worst.max()):.2f} m from any surface)" if ph else ""
    return (f"t {f.t_s:8.2f} s  height {f.height_m:4.2f} m  no depth {f.zero_depth_share:4.0%}  "
            f"in band: seen {f.seen_m.size:3d} (nearest {nearest(f.seen_m)})  hidden floor {f.hidden_m.size:3d} "
            f"(nearest {nearest(f.hidden_m)}){flag}")


HELP = """Re-render the SITL camera of FLIGHT_DIR (a demo, campaign or falsify flight: its flight.json and
truth.tlog) at its true poses, run the companion's obstacle extraction and hidden floor on each image, and print
the frames with points within --near m and the avoidance's height band; a point farther than --phantom-m from every
surface of the scene is a PHANTOM. Times are the flight's simulated seconds. Exit status 0: no phantom; 1: at least
one; 2: bad input."""


@click.command(help=HELP)
@click.argument("flight_dir", type=click.Path(path_type=Path, file_okay=False))
@click.option("--from", "t_from_s", type=float, default=0.0, show_default=True, help="simulated seconds")
@click.option("--to", "t_to_s", type=float, default=math.inf, help="simulated seconds [the flight's end]")
@click.option("--every-ms", type=click.FloatRange(min=1.0), default=33.0, show_default=True,
              help="simulated milliseconds between re-rendered frames (the camera's 30 Hz: 33)")
@click.option("--near", "near_m", type=click.FloatRange(min=0.1), default=1.2, show_default=True,
              help="report points within this horizontal distance (m)")
@click.option("--phantom-m", type=click.FloatRange(min=0.01), default=0.2, show_default=True,
              help="a point farther than this from every surface is a phantom (m)")
@click.option("--seed", type=int, default=1, show_default=True, help="the camera noise's draw")
@click.option("--all-frames", is_flag=True, help="print every frame, not only those with points in the band")
def command(flight_dir: Path, t_from_s: float, t_to_s: float, every_ms: float, near_m: float, phantom_m: float,
            seed: int, all_frames: bool) -> None:
    from quadlink.cli import setup_logging

    setup_logging()
    if t_to_s < t_from_s:
        raise ConfigError(f"--to {t_to_s} is before --from {t_from_s}")
    poses = list(every(read_truth(flight_dir / "truth.tlog"), t_from_s, t_to_s, every_ms / 1e3))
    if not poses:
        raise ConfigError(f"{flight_dir}: no true pose between {t_from_s} and {t_to_s} s")
    click.echo(f"{flight_dir}: {len(poses)} frames from {poses[0].t_s:.2f} to {poses[-1].t_s:.2f} s "
               f"(simulated), noise draw {seed}; points within {near_m} m and {BAND_M} m of the vehicle's height")
    rr = Rerenderer(flight_dir, seed)
    frames = phantom_frames = 0
    try:
        with click.progressbar(poses, label="re-rendering", file=sys.stderr, show_eta=True) as bar:
            for pose in bar:
                f = rr.frame(pose, near_m)
                frames += 1
                if f.phantoms(phantom_m):
                    phantom_frames += 1
                if all_frames or f.seen_m.size or f.hidden_m.size:
                    click.echo(describe(f, phantom_m))
    except KeyboardInterrupt:
        click.echo(f"\ninterrupted after {frames} frames", err=True)
    finally:
        rr.close()
    click.echo(f"{frames} frames re-rendered; {phantom_frames} with a phantom (a point farther than {phantom_m} m "
               "from every surface)")
    if phantom_frames:
        sys.exit(1)


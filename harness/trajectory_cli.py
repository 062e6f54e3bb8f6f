"""``quadlink trajectory FILE.yaml``: build a minimum-snap trajectory and stream it as MAVLink setpoints.

It streams SET_POSITION_TARGET_LOCAL_NED with position, velocity and acceleration (``type_mask`` 2048: yaw
used, yaw rate ignored; ``MAV_FRAME_LOCAL_NED``) at ``rate_hz`` (50 Hz) to a MAVLink URL, as a MAVSDK offboard
script would (PX4 accepts exactly these), then holds the last point for ``--hold`` seconds. Who consumes it:

* the companion's ground-station endpoint (default ``udpout:127.0.0.1:14555``): issue 19 wants the companion to
  stay the one arbiter of motion — it closes the position loop on its odometry
  (``companion.trajectory_follow``) and sends velocity + acceleration through its safety layer to the bridge;
* or any PX4-style autopilot endpoint directly.

The stream carries the trajectory's *position* in the odometry's local NED frame; ``relative: true`` in the
file (or ``--relative``) shifts it so it starts at the vehicle's current position, read from the link's
LOCAL_POSITION_NED or ODOMETRY. ``--dry-run`` prints the trajectory (peak speed, a CSV with ``--csv``) and
sends nothing. ``--offboard`` asks for OFFBOARD (PX4 custom mode) once the stream runs, as MAVSDK's
``offboard.start()`` does; arming and take-off stay the operator's. The link is a :class:`quadlink.client.GroundClient`.
"""

from __future__ import annotations

import logging
import math
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import click
import numpy as np

from quadlink.client import GroundClient, PositionTarget, position_velocity_accel_ned, set_px4_mode_command
from quadlink.config import load_config
from quadlink.errors import ConfigError
from quadlink.ids import GROUND_COMPONENT_ID
from quadlink.px4_modes import OFFBOARD
from quadlink.trajectory.minsnap import MinSnapTrajectory, TrajectoryError, TrajectorySample, minimum_snap

log = logging.getLogger(__name__)

OFFBOARD_AFTER_S = 0.5  # PX4 wants a setpoint stream before OFFBOARD


@dataclass(frozen=True)
class TrajectoryFile:
    """``configs/trajectories/*.yaml``: waypoints in local NED (m), times (s), optional waypoint velocities."""

    name: str = ""
    waypoints_ned_m: tuple[tuple[float, float, float], ...] = ()
    durations_s: tuple[float, ...] | None = None  # one per segment; or total_duration_s shared by length
    total_duration_s: float | None = None
    velocities_ned_m_s: tuple[tuple[float, float, float] | None, ...] | None = None  # one per waypoint (None: free)
    yaw_deg: float = 0.0  # heading held along the trajectory (b1d)
    relative: bool = False  # shift to start at the vehicle's current position
    rate_hz: float = 50.0
    max_speed_m_s: float = 2.0  # refuse a trajectory whose peak speed exceeds this


def load_trajectory_file(path: str | Path) -> tuple[TrajectoryFile, MinSnapTrajectory]:
    """Read and validate the file, build the trajectory (ConfigError naming the file on any problem)."""
    cfg = load_config(path, TrajectoryFile)
    if len(cfg.waypoints_ned_m) < 2:
        raise ConfigError(f"{path}: waypoints_ned_m needs at least two waypoints")
    if (cfg.durations_s is None) == (cfg.total_duration_s is None):
        raise ConfigError(f"{path}: give exactly one of durations_s and total_duration_s")
    if not (0.0 < cfg.rate_hz <= 200.0):
        raise ConfigError(f"{path}: rate_hz must be in (0, 200], got {cfg.rate_hz}")
    try:
        traj = minimum_snap(np.array(cfg.waypoints_ned_m, dtype=float), cfg.durations_s,
                            total_duration_s=cfg.total_duration_s,
                            velocities_m_s=None if cfg.velocities_ned_m_s is None else list(cfg.velocities_ned_m_s))
    except TrajectoryError as exc:
        raise ConfigError(f"{path}: {exc}") from exc
    peak = traj.peak_speed_m_s()
    if peak > cfg.max_speed_m_s:
        raise ConfigError(f"{path}: peak speed {peak:.2f} m/s exceeds max_speed_m_s {cfg.max_speed_m_s} "
                          "(lengthen the durations)")
    return cfg, traj


def trajectory_target(sample: TrajectorySample, offset_ned_m: np.ndarray, yaw_rad: float) -> PositionTarget:
    """The setpoint for one sample (position shifted by ``offset_ned_m``; type_mask 2048, MAV_FRAME_LOCAL_NED)."""
    return position_velocity_accel_ned(sample.p_m + offset_ned_m, sample.v_m_s, sample.a_m_s2, yaw_rad)


def schedule(traj: MinSnapTrajectory, rate_hz: float, hold_s: float) -> Iterator[tuple[float, TrajectorySample]]:
    """(send time from the start, sample) at ``rate_hz`` over the trajectory and the hold after it."""
    n = int(math.floor((traj.duration_s + hold_s) * rate_hz + 1e-9)) + 1
    for k in range(n):
        t = k / rate_hz
        yield t, traj.sample(t)


def _position(msg: Any) -> np.ndarray | None:
    """A finite position from LOCAL_POSITION_NED or ODOMETRY, else None."""
    if msg.get_type() not in ("LOCAL_POSITION_NED", "ODOMETRY"):
        return None
    p = np.array([msg.x, msg.y, msg.z], dtype=float)
    return p if np.all(np.isfinite(p)) else None


def _wait_position(client: GroundClient, timeout_s: float) -> np.ndarray:
    msg = client.wait_message(lambda m: _position(m) is not None, timeout_s,
                              "LOCAL_POSITION_NED or ODOMETRY (needed for a relative start)")
    p = _position(msg)
    assert p is not None
    return p


def stream(client: GroundClient, traj: MinSnapTrajectory, rate_hz: float, hold_s: float, offset_ned_m: np.ndarray,
           yaw_rad: float, offboard: bool, clock: Callable[[], float] = time.monotonic,
           sleep: Callable[[float], None] = time.sleep, progress: Callable[[float], None] | None = None) -> int:
    """Send the setpoints on time (absolute deadlines: no drift) to the client's target; returns how many were sent.

    ``time_boot_ms`` carries the sample's trajectory time (ms since the stream started)."""
    start = clock()
    sent = 0
    asked_offboard = False
    for t, sample in schedule(traj, rate_hz, hold_s):
        delay = start + t - clock()
        if delay > 0:
            sleep(delay)
        client.send_position_target(trajectory_target(sample, offset_ned_m, yaw_rad), round(t * 1000))
        sent += 1
        if offboard and not asked_offboard and t >= OFFBOARD_AFTER_S:
            client.send_command_long(set_px4_mode_command(OFFBOARD))
            asked_offboard = True
        if progress is not None and sent % max(1, int(rate_hz)) == 0:
            progress(t)
    return sent


@click.command(name="trajectory")
@click.argument("file", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--url", default="udpout:127.0.0.1:14555", show_default=True,
              help="MAVLink URL to stream to (the companion's ground-station endpoint by default).")
@click.option("--target-system", default=1, show_default=True, type=click.IntRange(1, 255))
@click.option("--target-component", default=1, show_default=True, type=click.IntRange(0, 255))
@click.option("--sysid", default=255, show_default=True, type=click.IntRange(1, 255), help="Our system id.")
@click.option("--hold", "hold_s", default=2.0, show_default=True, type=click.FloatRange(0.0, 60.0),
              help="Keep sending the last point this long after the end, s.")
@click.option("--relative/--absolute", default=None,
              help="Start at the vehicle's current position (overrides the file's 'relative').")
@click.option("--offboard", is_flag=True, help="Request OFFBOARD (PX4 custom mode) once the stream runs.")
@click.option("--dry-run", is_flag=True, help="Build and print the trajectory; send nothing.")
@click.option("--csv", "csv_path", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="With --dry-run: write t, p, v, a at the stream rate to this CSV.")
def command(file: Path, url: str, target_system: int, target_component: int, sysid: int, hold_s: float,
            relative: bool | None, offboard: bool, dry_run: bool, csv_path: Path | None) -> None:
    """Stream a minimum-snap trajectory (FILE.yaml: waypoints, times) as position+velocity+acceleration setpoints."""
    cfg, traj = load_trajectory_file(file)
    yaw = math.radians(cfg.yaw_deg)
    click.echo(f"trajectory {cfg.name or file.stem}: {traj.segments} segments, {traj.duration_s:.2f} s, "
               f"peak speed {traj.peak_speed_m_s():.3f} m/s, snap cost {traj.snap_cost():.3g} m^2/s^7")
    if dry_run:
        if csv_path is not None:
            with csv_path.open("w", encoding="utf-8") as out:
                out.write("t_s,x_m,y_m,z_m,vx_m_s,vy_m_s,vz_m_s,ax_m_s2,ay_m_s2,az_m_s2\n")
                for t, s in schedule(traj, cfg.rate_hz, 0.0):
                    out.write(",".join(f"{v:.6f}" for v in (t, *s.p_m, *s.v_m_s, *s.a_m_s2)) + "\n")
            click.echo(f"wrote {csv_path}")
        return
    from quadlink.client import connect

    client = connect(url, system_id=sysid, component_id=GROUND_COMPONENT_ID, target_system=target_system,
                     target_component=target_component)
    try:
        offset = np.zeros(3)
        if cfg.relative if relative is None else relative:
            p0 = _wait_position(client, 5.0)
            offset = p0 - traj.sample(0.0).p_m
            click.echo(f"relative start at {np.round(p0, 3).tolist()} (offset {np.round(offset, 3).tolist()})")
        click.echo(f"streaming to {url} at {cfg.rate_hz:g} Hz (Ctrl-C stops)")
        try:
            sent = stream(client, traj, cfg.rate_hz, hold_s, offset, yaw, offboard,
                          progress=lambda t: log.info("t = %.1f / %.1f s", t, traj.duration_s + hold_s))
        except KeyboardInterrupt:
            click.echo("stopped", err=True)
            sys.exit(130)
        click.echo(f"done: {sent} setpoints sent")
    finally:
        client.close()

"""``quadlink identify-yaw``: the closed-loop yaw response to the pan-scan (A'_omega, phi_omega of eq. 5) from a
flight's telemetry log, compared with the first-order model the companion uses by default, printed with the
``pan_scan`` YAML that makes the companion use it."""

from __future__ import annotations

import math
from pathlib import Path

import click
import numpy as np

from companion.config import load_companion_config, pan_scan_params
from quadlink.analysis.yaw_identification import FeedbackSeries, IdentificationError, fit_yaw_loop
from quadlink.errors import QuadlinkError
from quadlink.mavlink import mavlink


def feedback_from_tlog(path: Path) -> FeedbackSeries:
    """TELEOP_FEEDBACK of a .tlog (the companion's own ``--tlog``, or any that recorded its GCS link) while the
    companion was in TELEOP with the pan-scan on, in the order of their stamps."""
    from quadlink.mavlink.tlog import read_tlog

    try:
        records = read_tlog(path)
    except OSError as exc:
        raise QuadlinkError(f"{path}: cannot read the log ({exc.strerror or exc})") from exc
    rows = sorted((m.time_usec * 1e-6, m.pan_scan_yaw_rate, m.yaw_rate_cmd, m.gyro_yaw_rate)
                  for _, m in records
                  if m.get_type() == "TELEOP_FEEDBACK" and m.mode == mavlink.QUADLINK_TELEOP_MODE_TELEOP
                  and m.flags & mavlink.QUADLINK_TELEOP_FLAGS_PAN_SCAN_ON)
    if not rows:
        raise IdentificationError(f"{path}: no TELEOP_FEEDBACK in teleop with the pan-scan on "
                                  f"({len(records)} messages read)")
    a = np.array(rows, dtype=float)
    return FeedbackSeries(a[:, 0], a[:, 1], a[:, 2], a[:, 3])


@click.command(name="identify-yaw")
@click.argument("tlog", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--config", "config_path", default="companion", show_default=True,
              help="Companion YAML: the pan-scan pulsation and the model to compare with.")
@click.option("--omega", "omega_rad_s", type=float, default=None, help="Carrier pulsation, rad/s [config pan_scan].")
def command(tlog: Path, config_path: str, omega_rad_s: float | None) -> None:
    """Identify the closed-loop yaw response to the pan-scan carrier from a flight log (TELEOP_FEEDBACK)."""
    cfg = load_companion_config(config_path).pan_scan
    omega = cfg.omega_rad_s if omega_rad_s is None else omega_rad_s
    series = feedback_from_tlog(tlog)
    fit = fit_yaw_loop(series, omega)
    r, model = fit.response, pan_scan_params(cfg)
    span = float(series.t_s[-1] - series.t_s[0])
    click.echo(f"{tlog}: {series.t_s.size} TELEOP_FEEDBACK in teleop with the pan-scan on, {span:.1f} s")
    click.echo(f"  yaw-rate loop (commanded -> gyro): tau {fit.time_constant_s:.3f} s, delay {fit.delay_s:.3f} s, "
               f"static gain {fit.static_gain:.3f}; the model run from the command misses the gyro by "
               f"{fit.rms_residual_rad_s:.4f} rad/s RMS")
    click.echo(f"  at the carrier ({omega:.3f} rad/s): A' = {r.gain:.3f}, phi = {r.phase_rad:+.3f} rad")
    click.echo(f"  in use ({cfg.response}): A' = {model.gain:.3f}, phi = {model.phase_rad:+.3f} rad")
    if span * omega < 4 * math.pi:
        click.echo("  (less than two carrier periods: fly longer for a trustworthy figure)")
    click.echo("companion YAML to use it:")
    click.echo(f"pan_scan:\n  response: fixed\n  gain: {r.gain:.4f}\n  phase_rad: {r.phase_rad:.4f}")

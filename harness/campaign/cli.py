"""``quadlink campaign``: N randomized flights of the whole stack on Ray, and the campaign report."""

from __future__ import annotations

import logging
import math
import time
from pathlib import Path

import click

from harness.campaign.draws import CONTENTION_P, CPU_SHARE_CORES, StarvationRange
from harness.campaign.experiments import EXPERIMENTS
from harness.campaign.runner import CampaignCancelled, CampaignOptions, load_results, run_campaign
from harness.cpu_share import CpuShare, CpuShareUnavailable

log = logging.getLogger("harness.campaign")


def parse_cpu_share(text: str, contention_p: float, realtime: bool, experiment: str) -> StarvationRange:
    """``--cpu-share LO:HI`` (or one number: every flight at that share) as the range the flights draw from."""
    if not realtime:
        raise click.UsageError("--cpu-share needs --realtime: in lock-step the SITL waits for a starved part")
    if experiment != "teleop":
        raise click.UsageError("--cpu-share applies to the teleop campaign only")
    parts = text.split(":")
    try:
        lo, hi = (float(parts[0]), float(parts[-1])) if len(parts) <= 2 else (math.nan, math.nan)
        return StarvationRange(lo, hi, contention_p)
    except ValueError as exc:
        raise click.BadParameter(f"{text!r}: expected LO:HI in cores, e.g. 0.3:1.0 ({exc})",
                                 param_hint="--cpu-share") from None


def check_cpu_share() -> None:
    """Fail before the first flight where no CPU share can be set (not root, no cgroup with the cpu controller)."""
    try:
        with CpuShare(1.0):
            pass
    except CpuShareUnavailable as exc:
        raise click.ClickException(f"--cpu-share: {exc} (run as root, or in a delegated cgroup)") from None


@click.command(name="campaign")
@click.option("--flights", "n_flights", type=click.IntRange(min=1), required=True, help="Number of flights.")
@click.option("--seed", type=int, required=True, help="Campaign seed (flight i draws from SeedSequence(seed).spawn).")
@click.option("--out", "out_dir", type=click.Path(file_okay=False, path_type=Path), required=True,
              help="Folder for flight-NNNN/ folders, campaign.json and campaign.png.")
@click.option("--parallel", type=click.IntRange(min=1), default=1, show_default=True,
              help="Flights in the air at once (each on its own port slot).")
@click.option("--address", default=None, help="Join this Ray cluster (ray://HOST:10001 or HOST:6379) instead of "
                                              "starting an embedded local Ray.")
@click.option("--duration", "duration_s", default=60.0, show_default=True, help="Simulated seconds per flight.")
@click.option("--cpus-per-flight", default=1.0, show_default=True, help="CPUs each flight reserves (Ray num_cpus).")
@click.option("--port-offset", default=3000, show_default=True,
              help="Port slot k flies on the demo's ports shifted by PORT_OFFSET + 25 k.")
@click.option("--offboard-share", default=0.0, show_default=True,
              help="Share of flights flown by the scripted offboard client (SET_POSITION_TARGET_LOCAL_NED through "
                   "the companion) instead of the haptic operator's MANUAL_CONTROL.")
@click.option("--fixed-share", default=0.2, show_default=True, help="Share of flights in paper-arena or office.")
@click.option("--view/--no-view", default=False, show_default=True,
              help="Run each flight's operator image view (no effect on the flight; costs CPU; not deterministic).")
@click.option("--deterministic/--no-deterministic", default=True, show_default=True,
              help="Fly in the deterministic lock-step (quadlink/lockstep.py): the same seed and index re-fly the "
                   "same flight, bit for bit; --no-deterministic: the plain lock-step of earlier campaigns.")
@click.option("--realtime", is_flag=True,
              help="Fly every part on the wall clock, as on the vehicle (not deterministic; one flight per two cores "
                   "keeps the SITL in real time). What --cpu-share needs.")
@click.option("--cpu-share", "cpu_share", default=None, metavar="LO:HI",
              help="Starve the companion board (issue 30; with --realtime): each flight draws the bridge's and the "
                   "companion's CPU share from U(LO, HI) cores (CFS bandwidth control, 20 ms period; needs root or a "
                   f"delegated cgroup). The campaign's range is {CPU_SHARE_CORES[0]}:{CPU_SHARE_CORES[1]}.")
@click.option("--contention", "contention_p", default=CONTENTION_P, show_default=True,
              type=click.FloatRange(0.0, 1.0),
              help="With --cpu-share: the share of flights with a busy process spinning beside the stack.")
@click.option("--journal", is_flag=True,
              help="Each flight's companion and bridge journal their inputs (flight-NNNN/companion.qljn and "
                   "bridge.qlbj): quadlink replay-companion and replay-bridge re-run them offline.")
@click.option("--report-only", is_flag=True,
              help="Fly nothing: rebuild campaign.json and the summary from OUT's finished flights (wall time "
                   "estimated from the flights' wall times and --parallel).")
@click.option("--first-index", default=0, show_default=True, help="Index of the first flight (continue a campaign).")
@click.option("--experiment", type=click.Choice(["teleop", *EXPERIMENTS]), default="teleop", show_default=True,
              help="teleop: randomized operator sessions in randomized arenas (the safety envelope); paper003-oval / "
                   "paper003-hover: paper 003's experiment from a drawn start pose with the vehicle and sensor draws "
                   "(its figures against issue 19's targets; --duration, --offboard-share, --fixed-share and --view "
                   "do not apply).")
def command(n_flights: int, seed: int, out_dir: Path, parallel: int, address: str | None, duration_s: float,
            cpus_per_flight: float, port_offset: int, offboard_share: float, fixed_share: float,
            view: bool, deterministic: bool, realtime: bool, cpu_share: str | None, contention_p: float,
            journal: bool, report_only: bool, first_index: int, experiment: str) -> None:
    """Fly N randomized flights (arena, start, operator, vehicle and sensors) and report the safety envelope, or
    N flights of one of paper 003's experiments and report its figures."""
    from harness.campaign.experiment_report import experiment_summary_text, write_experiment_campaign
    from harness.campaign.report import summary_text, write_campaign

    starve = parse_cpu_share(cpu_share, contention_p, realtime, experiment) if cpu_share is not None else None
    if starve is not None and not report_only:
        check_cpu_share()
    options = CampaignOptions(n_flights, seed, out_dir, duration_s, parallel, address, cpus_per_flight, port_offset,
                              offboard_share, fixed_share, first_index, view, experiment,
                              deterministic and not realtime, realtime, starve, journal)
    t0 = time.monotonic()
    cancelled = False
    if report_only:
        results = load_results(out_dir)
        wall_s = sum(r.wall_s for r in results if r.wall_s == r.wall_s) / max(1, parallel)
    else:
        try:
            results = run_campaign(options, echo=lambda s: click.echo(s, nl=not s.startswith("\r")))
        except CampaignCancelled as exc:
            results, cancelled = exc.results, True
        wall_s = time.monotonic() - t0
    if experiment == "teleop":
        campaign = write_campaign(results, options, wall_s)
        click.echo(f"\nCampaign report ({out_dir}/campaign.json, {campaign['plot']}):")
        click.echo(summary_text(campaign))
    else:
        campaign = write_experiment_campaign(results, options, wall_s)
        click.echo(f"\nCampaign report ({out_dir}/campaign.json):")
        click.echo(experiment_summary_text(campaign))
    if cancelled:
        click.echo(f"quadlink campaign: cancelled; the report covers the {len(results)} finished flights", err=True)
        raise SystemExit(130)

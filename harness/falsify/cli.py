"""``quadlink falsify``: search the flight space for the lowest clearance; ``quadlink falsify export``: a finding as
a regression flight."""

from __future__ import annotations

import logging
from pathlib import Path

import click

from harness.falsify.search import (
    DEFAULT_PORT_OFFSET,
    SAMPLERS,
    STUDY_NAME,
    SearchCancelled,
    SearchOptions,
    load_search_options,
    run_search,
    storage_url,
)

log = logging.getLogger("harness.falsify")


def _report(out_dir: Path) -> None:
    import optuna

    from harness.falsify.report import summary_text, write_report

    study = optuna.load_study(study_name=STUDY_NAME, storage=storage_url(out_dir))
    summary = write_report(study, out_dir)
    click.echo(f"\nFalsification report ({out_dir}/falsify.json, convergence.png, distribution.png):")
    click.echo(summary_text(summary))


@click.group(name="falsify", invoke_without_command=True)
@click.option("--budget", type=click.IntRange(min=1), default=None,
              help="Flights to judge in all (a resumed study counts the flights it has).")
@click.option("--parallel", type=click.IntRange(min=1), default=None, help="Flights in the air at once [1].")
@click.option("--seed", type=int, default=None, help="The sampler's seed (a new study; required with --out).")
@click.option("--out", "out_dir", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Folder of a new study: study.db (Optuna, sqlite), trial-NNNN/ flights, the report.")
@click.option("--resume", "resume_dir", type=click.Path(file_okay=False, exists=True, path_type=Path), default=None,
              help="Continue the study in this folder (its seed, sampler and duration; --budget is the new total).")
@click.option("--address", default=None, help="Join this Ray cluster (ray://HOST:10001 or HOST:6379) instead of "
                                              "starting an embedded local Ray.")
@click.option("--sampler", type=click.Choice(SAMPLERS), default=None,
              help="tpe (random exploration first, then TPE) | cmaes | random [tpe].")
@click.option("--startup-trials", type=click.IntRange(min=0), default=None,
              help="Random flights before the model (TPE's n_startup_trials) [10].")
@click.option("--duration", "duration_s", type=click.FloatRange(min=19.0), default=None,
              help="Simulated seconds of each operator session: take-off 10 s, the push, landing 8 s [30].")
@click.option("--port-offset", type=int, default=None,
              help=f"Port slot k flies on the demo's ports shifted by PORT_OFFSET + 25 k [{DEFAULT_PORT_OFFSET}].")
@click.option("--report-only", is_flag=True, help="Fly nothing: write the report of the study in --resume DIR.")
@click.pass_context
def command(ctx: click.Context, budget: int | None, parallel: int | None, seed: int | None, out_dir: Path | None,
            resume_dir: Path | None, address: str | None, sampler: str | None, startup_trials: int | None,
            duration_s: float | None, port_offset: int | None, report_only: bool) -> None:
    """Search the flight space (arena relative to the path, operator push, sensor and calibration errors) for the
    flight with the lowest true clearance, with Optuna on the campaign runner's Ray tasks; resumable (Ctrl-C
    keeps the study), with a report and the command that re-flies each flight bit for bit."""
    if ctx.invoked_subcommand is not None:
        return
    import optuna

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    if (out_dir is None) == (resume_dir is None):
        raise click.UsageError("give exactly one of --out DIR (a new study) or --resume DIR")
    if resume_dir is not None:
        if seed is not None or sampler is not None or duration_s is not None or startup_trials is not None:
            raise click.UsageError("--resume continues the study with its own --seed, --sampler, --duration and "
                                   "--startup-trials (search.json)")
        if report_only:
            _report(resume_dir)
            return
        options = load_search_options(resume_dir, budget=budget, parallel=parallel, address=address,
                                      port_offset=port_offset)
        folder = resume_dir
    else:
        assert out_dir is not None
        if budget is None or seed is None:
            raise click.UsageError("a new study needs --budget and --seed")
        options = SearchOptions(budget, seed, out_dir, parallel or 1, address, sampler or "tpe",
                                10 if startup_trials is None else startup_trials, duration_s or 30.0,
                                DEFAULT_PORT_OFFSET if port_offset is None else port_offset)
        folder = out_dir
    log.info("falsify: %d flights, %s sampler, seed %d, %d in parallel, %s, study in %s", options.budget,
             options.sampler, options.seed, options.parallel, options.address or "local Ray", folder)
    cancelled = False
    try:
        run_search(options, resume=resume_dir is not None)
    except SearchCancelled as exc:
        cancelled = True
        click.echo(f"\nquadlink falsify: {exc}", err=True)
    _report(folder)
    if cancelled:
        raise SystemExit(130)


@command.command(name="export")
@click.argument("study_dir", type=click.Path(file_okay=False, exists=True, path_type=Path))
@click.option("--trial", "number", type=int, required=True, help="The trial to export (its number in the report).")
@click.argument("dest", type=click.Path(file_okay=False, path_type=Path))
def export_command(study_dir: Path, number: int, dest: Path) -> None:
    """Write trial N of STUDY_DIR as a regression flight in DEST: its fixed scenario, operator, vehicle, SITL and
    companion files and finding.json (tests/sitl/test_falsify_regressions.py flies every such folder under
    tests/regression_flights/)."""
    from harness.falsify.export import export_trial

    finding = export_trial(study_dir, number, dest)
    clearance = finding["clearance_m"]
    what = f"{clearance:.3f} m" if clearance is not None else finding["status"]
    click.echo(f"trial {number} ({what}) written to {dest}")
    if not finding["finding"]:
        click.echo(f"note: trial {number} is not a finding (at or above {finding['envelope_m']:.2f} m, no part died)")

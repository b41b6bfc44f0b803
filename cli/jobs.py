"""``freipose jobs``: the units of a prediction run through an executor, and ``--resume``."""

from __future__ import annotations

from pathlib import Path

import click

from freipose.cli._common import user_errors

STATES = ("done", "running", "queued", "failed", "waiting")


@click.command()
@click.argument("outdir", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option(
    "--resume",
    is_flag=True,
    help="Submit the units that are not done (failed, cancelled, never run) with the "
    "settings of the first run, wait for them and join the sessions.",
)
@click.option("--all", "show_all", is_flag=True, help="List every unit, also the done ones.")
@click.pass_context
def jobs(ctx: click.Context, outdir: Path, resume: bool, show_all: bool) -> None:
    """Show the units of a prediction run through an executor, and finish it.

    For `freipose predict --executor ... -o OUTDIR`: per session, the units that are done,
    running, queued, failed (with the reason and the log) or waiting, and the throughput.
    For `freipose train --executor ... --out RUN`: the training job's state and step.

    \b
    Examples:
      freipose jobs poses/              # what is done, what runs, what failed
      freipose jobs poses/ --resume     # submit what is missing and join the sessions
    """  # noqa: D301 - click needs the \b (backspace) paragraph marker
    with user_errors():
        from freipose.cluster.status import jobs_status
        from freipose.cluster.train import is_train_job

        if is_train_job(outdir):  # a run folder of `freipose train --executor`
            from freipose.cli.train import show_train_job

            show_train_job(ctx, outdir, resume)
            return

        if resume:
            _resume(ctx, outdir)
        status = jobs_status(outdir)
        _show(status, show_all)


def _resume(ctx: click.Context, outdir: Path) -> None:
    """Run the saved task again: only the missing units are submitted."""
    from freipose.cluster.predict import load_task, run_predict

    quiet = bool(ctx.obj and ctx.obj.get("quiet"))
    task, config = load_task(outdir)
    result = run_predict(task, config, progress=not quiet, say=click.echo)
    for p in result.joined:
        click.echo(f"wrote {p}")


def _show(status, show_all: bool) -> None:  # noqa: ANN001 - a JobsStatus
    """Print a line per session and one per unit that is not done (every unit with --all)."""
    by_session: dict[str, list] = {}
    for u in status.units:
        by_session.setdefault(u.session, []).append(u)
    click.echo(f"{status.outdir}: {len(status.units)} units on the {status.executor} executor")
    for session, units in by_session.items():
        counts = {state: sum(u.state == state for u in units) for state in STATES}
        summary = ", ".join(f"{n} {state}" for state, n in counts.items() if n)
        click.echo(f"  {session}: {summary}")
        for u in units:
            if u.state == "done" and not show_all:
                continue
            line = f"    {u.unit}: {u.state}"
            if u.job_id:
                line += f", job {u.job_id} (attempt {u.attempts})"
            if u.reason:
                line += f": {u.reason}"
            if u.state == "failed" and u.log:
                line += f"; log {u.log}"
            click.echo(line)
    if status.frames_per_s is not None:
        click.echo(f"throughput so far: {status.frames_per_s:.1f} frames/s")
    missing = status.missing()
    if missing and any(u.state in ("failed", "waiting") for u in missing):
        click.echo(f"finish with: freipose jobs {status.outdir} --resume")

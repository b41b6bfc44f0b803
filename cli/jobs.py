"""``freipose jobs``: the units of a command run through an executor, and ``--resume``."""

from __future__ import annotations

from pathlib import Path

import click

from freipose.cli._common import user_errors

STATES = ("done", "running", "queued", "failed", "waiting")


@click.command()
@click.argument("outdir", metavar="OUTPUT", type=click.Path(path_type=Path))
@click.option(
    "--resume",
    is_flag=True,
    help="Submit the units that are not done (failed, cancelled, never run) with the "
    "settings of the first run, wait for them and join the outputs.",
)
@click.option("--all", "show_all", is_flag=True, help="List every unit, also the done ones.")
@click.pass_context
def jobs(ctx: click.Context, outdir: Path, resume: bool, show_all: bool) -> None:
    """Show the units of a command run through an executor, and finish it.

    OUTPUT is what the command wrote with --executor: the output folder of `freipose
    predict` or `freipose smooth` (-o OUTDIR; also lists the jobs of single files written
    into it), or the output file of `freipose detect`, `render` or `analyze variables`.
    Per session or file: the units that are done, running, queued, failed (with the reason
    and the log) or waiting, and the throughput. For `freipose train --executor ... --out
    RUN`: the training job's state and step.

    \b
    Examples:
      freipose jobs poses/              # what is done, what runs, what failed
      freipose jobs poses/ --resume     # submit what is missing and join the sessions
      freipose jobs rec1/boxes.h5       # the units of `freipose detect ... -o rec1/boxes.h5`
    """  # noqa: D301 - click needs the \b (backspace) paragraph marker
    with user_errors():
        from freipose.cluster.stages import find_job_roots, load_task
        from freipose.cluster.status import jobs_status
        from freipose.cluster.train import is_train_job

        if outdir.is_dir() and is_train_job(outdir):  # a run of `freipose train --executor`
            from freipose.cli.train import show_train_job

            show_train_job(ctx, outdir, resume)
            return

        roots = find_job_roots(outdir)
        if not roots:
            load_task(outdir)  # raises the message that says which commands write a job
        for root in roots:
            if resume:
                _resume(ctx, root)
            _show(jobs_status(root), show_all)


def _resume(ctx: click.Context, root: Path) -> None:
    """Run the saved task again: only the missing units are submitted."""
    from freipose.cluster.stages import load_task, run_stage

    quiet = bool(ctx.obj and ctx.obj.get("quiet"))
    task, config = load_task(root)
    result = run_stage(task, config, progress=not quiet, say=click.echo)
    for p in result.joined:
        click.echo(f"wrote {p}")


def _show(status, show_all: bool) -> None:  # noqa: ANN001 - a JobsStatus
    """Print a line per session and one per unit that is not done (every unit with --all)."""
    by_session: dict[str, list] = {}
    for u in status.units:
        by_session.setdefault(u.session, []).append(u)
    target = status.target or status.outdir
    click.echo(f"{target}: {len(status.units)} units of `freipose {status.command}` on the "
               f"{status.executor} executor")  # fmt: skip
    for session, units in by_session.items():
        counts = {state: sum(u.state == state for u in units) for state in STATES}
        summary = ", ".join(f"{n} {state}" for state, n in counts.items() if n)
        joined = ", not joined" if session in status.unjoined else ""
        click.echo(f"  {session}: {summary}{joined}")
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
    stopped = not any(u.state in ("running", "queued") for u in missing)
    if any(u.state in ("failed", "waiting") for u in missing) or (status.unjoined and stopped):
        click.echo(f"finish with: freipose jobs {target} --resume")

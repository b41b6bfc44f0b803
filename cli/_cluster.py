"""The executor options of the commands whose work runs as units.

``predict``, ``detect``, ``smooth``, ``analyze variables``, ``render`` and ``train``.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import click

EXECUTOR_HELP = (
    "Run the work as units on an executor: local (worker processes on this machine) or "
    'slurm (a SLURM job array; needs `pip install "freipose[cluster]"`). Finished units are '
    "skipped when the command runs again; `freipose jobs OUTPUT` shows the units."
)


def cluster_options(
    fn: Callable[..., Any] | None = None, *, chunks: bool = True
) -> Callable[..., Any]:
    """``--executor``, ``--cluster FILE``, ``--chunk-frames``, ``--parallel``, ``--max-retries``.

    Args:
        fn: the command (``@cluster_options``), or None (``@cluster_options(chunks=False)``).
        chunks: whether the command splits its work in chunks of frames (``--chunk-frames``);
            without, each output is one unit and the command has no ``chunk_frames``.
    """
    if fn is None:
        return lambda f: cluster_options(f, chunks=chunks)
    options = [
        click.option("--executor", type=click.Choice(["local", "slurm"]), help=EXECUTOR_HELP),
        click.option(
            "--cluster",
            "cluster_file",
            type=click.Path(exists=True, dir_okay=False, path_type=Path),
            help="TOML file with a [cluster] table: executor, partition, account, gpus, cpus, "
            "mem_gb, time_min, array_parallelism, chunk_frames, max_retries, sbatch "
            "(docs: Run a study on a cluster). Options given here override it.",
        ),
        click.option("--chunk-frames", type=int, help="Frames per unit [default: 6000]."),
        click.option(
            "--parallel",
            type=int,
            help="Units running at once (SLURM array throttle; local "
            "worker processes) [default: 16].",
        ),  # fmt: skip
        click.option(
            "--max-retries",
            type=int,
            help="Further jobs for a unit that ended without its output [default: 2].",
        ),
    ]
    if not chunks:
        del options[2]
    for option in reversed(options):
        fn = option(fn)
    return fn


def run_through_executor(ctx: click.Context, task: Any, config: Any, overwrite: bool) -> Any:
    """Run a stage's ``task`` on the executor ``config`` names, saying what it does.

    Says which outputs are kept (complete already; ``--overwrite`` redoes them), the plan,
    the outputs written and how many units are done. Returns the ``StageResult``.
    """
    from freipose.cluster.stages import groups, run_stage

    quiet = bool(ctx.obj and ctx.obj.get("quiet"))
    kept = set()
    if not overwrite:
        kept = {task.output(g) for g in groups(task.plan_units()) if task.output_done(g)}
        for path in sorted(kept):
            click.echo(f"kept {path} (--overwrite redoes it)")
    result = run_stage(task, config, progress=not quiet, overwrite=overwrite,
                       say=(lambda m: None) if quiet else click.echo)  # fmt: skip
    for path in result.joined:
        if path not in kept:
            click.echo(f"wrote {path}")
    r = result.report
    click.echo(f"{len(r.done)} units done ({r.submitted} jobs submitted in this run), "
               f"{result.frames} frames, {r.seconds:.1f} s")  # fmt: skip
    return result


def cluster_config(
    executor: str | None,
    cluster_file: Path | None,
    chunk_frames: int | None,
    parallel: int | None,
    max_retries: int | None,
    **fixed: Any,
) -> Any:
    """The ``ClusterConfig`` the options ask for, or None when no executor was asked for.

    Raises:
        ClusterConfigError: a bad value (in the file or the options).
    """
    asked = (chunk_frames, parallel, max_retries)
    if executor is None and cluster_file is None:
        if any(v is not None for v in asked):
            raise click.UsageError(
                "--chunk-frames, --parallel and --max-retries apply to units: add "
                "--executor local|slurm (or --cluster FILE)"
            )
        return None
    from freipose.cluster.config import read_cluster_config

    return read_cluster_config(
        cluster_file,
        executor=executor,
        chunk_frames=chunk_frames,
        array_parallelism=parallel,
        max_retries=max_retries,
        **fixed,
    )

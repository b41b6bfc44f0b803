"""The executor options of the commands whose work runs as units (``predict``, ``train``)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import click

EXECUTOR_HELP = (
    "Run the work as units on an executor: local (worker processes on this machine) or "
    'slurm (a SLURM job array; needs `pip install "freipose[cluster]"`). Finished units are '
    "skipped when the command runs again; `freipose jobs OUTDIR` shows the units."
)


def cluster_options(fn: Callable[..., Any]) -> Callable[..., Any]:
    """``--executor``, ``--cluster FILE``, ``--chunk-frames``, ``--parallel``, ``--max-retries``."""
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
    for option in reversed(options):
        fn = option(fn)
    return fn


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

"""``freipose train``: train the pose network (or the box detector) from a TOML config."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import click

from freipose.cli._common import device_option, user_errors
from freipose.cli._threads import threads_option, use_threads


@click.command()
@click.argument("config", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option(
    "--stage",
    type=click.Choice(["pose", "detector", "baseline"]),
    default="pose",
    show_default=True,
    help="pose: the voxel network; detector: the box detector ([detector] table); "
    "baseline: the per-view 2D + triangulation reference network.",
)
@click.option("--resume", is_flag=True, help="Continue the run in the output folder bit for bit.")
@click.option(
    "--init",
    default=None,
    metavar="base|scratch|PATH",
    help="Starting weights, overriding the config's [model] init (or [detector] init): base "
    "(the base model shipped for the architecture), scratch, or a checkpoint [default: the "
    "config's, base when it names none].",
)
@device_option("cpu")
@click.option(
    "--out",
    "out_dir",
    type=click.Path(file_okay=False, path_type=Path),
    help="Run folder for checkpoints and logs [default: CONFIG without its suffix].",
)
@threads_option()
@click.option(
    "--executor",
    type=click.Choice(["local", "slurm"]),
    help="Run the training as a job: local (processes on this machine) or slurm (a SLURM "
    'job through submitit; needs `pip install "freipose[cluster]"`). The job continues from '
    "the run's checkpoint.pt when it is requeued, preempted or run again.",
)
@click.option(
    "--cluster",
    "cluster_file",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    help="TOML file with a [cluster] table (partition, account, qos, gpus, cpus, mem_gb, "
    "time_min, max_retries, sbatch; docs: Run a study on a cluster). Options override it.",
)
@click.option(
    "--gpus", type=int, help="GPUs per node, one process each (0: CPU processes) [default: 0]."
)
@click.option("--nodes", type=int, default=1, show_default=True, help="Nodes of the SLURM job.")
@click.option(
    "--tasks-per-node",
    type=int,
    help="Processes per node [default: --gpus, or 1 without GPUs]; CPU processes average "
    "their gradients with gloo.",
)
@click.option(
    "--max-retries",
    type=int,
    help="Further jobs when one ends without model.pt (cancelled, failed) [default: 2].",
)
@click.option(
    "--no-wait",
    is_flag=True,
    help="Submit the SLURM job and return; `freipose jobs RUN` shows its state.",
)
@click.pass_context
def train(
    ctx: click.Context,
    config: Path,
    stage: str,
    resume: bool,
    init: str | None,
    device: str,
    out_dir: Path | None,
    threads: int | None,
    executor: str | None,
    cluster_file: Path | None,
    gpus: int | None,
    nodes: int,
    tasks_per_node: int | None,
    max_retries: int | None,
    no_wait: bool,
) -> None:
    """Train the FreiPose network described by a TOML config.

    The config's [data] table names the labels (and optional eval labels), [model] picks a
    preset (tiny, small, paper) plus overrides, [schedule] and [augment] tune training;
    see docs/formats.md. The run folder gets config.toml (every default written out),
    checkpoint.pt (every schedule.checkpoint_every steps, atomic), model.pt (final),
    log.csv and log.png. A killed run continues with --resume. A new run starts from the
    base model shipped for its architecture ([model] init = "base", the default; see
    docs/models.md), from scratch, or from a checkpoint (--init).

    Several GPUs or nodes: --executor slurm --gpus N --nodes M runs one process per GPU
    under SLURM (or --executor local on this machine; --gpus 0 --tasks-per-node K: CPU
    processes); the command waits, showing the step, unless --no-wait. A requeued,
    preempted or cancelled job continues from the last checkpoint.pt, and the same
    command run again continues the run or reports it complete. Or launch with torchrun.

    \b
    Example:
      freipose train examples/train_small.toml --out runs/small
      freipose train examples/train_small.toml --out runs/small --resume
      freipose train examples/train_small.toml --stage baseline --out runs/small_baseline
      freipose train cfg.toml --out runs/big --executor slurm --gpus 4 --nodes 2 \\
          --cluster cluster.toml
      freipose train cfg.toml --out runs/cpu2 --executor local --tasks-per-node 2
      torchrun --nproc_per_node 4 -m freipose.cli.main train cfg.toml --device cuda
    """  # noqa: D301 - click needs the \b (backspace) paragraph marker
    with user_errors():
        quiet = bool(ctx.obj and ctx.obj.get("quiet"))
        if _train_as_job(ctx):
            return
        # torchrun starts LOCAL_WORLD_SIZE processes on this machine, each with its threads
        use_threads(threads, workers=int(os.environ.get("LOCAL_WORLD_SIZE", "1") or 1))
        init = _command_line_init(init)
        if stage == "detector":
            try:
                from freipose.detect.train import train_detector
            except ImportError as exc:
                raise click.ClickException(
                    "detector training is not available in this installation "
                    f"(freipose.detect.train.train_detector could not be imported: {exc})"
                ) from exc
            from freipose.io.toml import read_toml
            from freipose.nn.config import ConfigError

            data = read_toml(config, "training config", ConfigError)
            if init is not None:
                data["detector"] = {**data.get("detector", {}), "init": init}
            out = (
                out_dir
                if out_dir is not None
                else config.with_suffix("").with_name(config.stem + "_detector")
            )
            path = train_detector(
                config=data, config_path=config, out_dir=out, resume=resume, device=device
            )
        else:
            from freipose.nn.train import train_from_config

            path = train_from_config(
                config,
                out_dir,
                resume=resume,
                device=device,
                kind="baseline" if stage == "baseline" else None,
                progress=not quiet,
                init=init,
            )
        click.echo(f"wrote {path}")


def _command_line_init(init: str | None) -> str | None:
    """``--init`` with a checkpoint path made absolute against the current folder.

    A path inside the TOML is relative to the TOML's folder; one typed on the command line
    is relative to where the command runs.

    Raises:
        InputFileError: the path names no file.
    """
    if init is None or init in ("base", "scratch"):
        return init
    from freipose.errors import InputFileError

    path = Path(init).expanduser()
    if not path.is_file():
        raise InputFileError(
            f"--init {init}: no such checkpoint file (a path on the command line is relative "
            f"to the current folder, {Path.cwd()}); give base, scratch or the path of a "
            "model.pt (or, with --stage detector, a detector.pt)"
        )
    return str(path.resolve())


def _train_as_job(ctx: click.Context) -> bool:
    """Run ``freipose train --executor ...`` (True), or refuse its options without it (False).

    The training runs as a job of one process per GPU (or CPU processes) on the executor.
    """
    p = ctx.params
    if p["executor"] is None and p["cluster_file"] is None:
        job_options = ("gpus", "tasks_per_node", "max_retries")
        if any(p[k] is not None for k in job_options) or p["nodes"] != 1 or p["no_wait"]:
            raise click.UsageError(
                "--gpus, --nodes, --tasks-per-node, --max-retries and --no-wait apply to a "
                "training job: add --executor local|slurm (or --cluster FILE)"
            )
        return False
    if p["stage"] == "detector":
        raise click.UsageError(
            "--executor trains the pose or baseline network; train the detector without it"
        )
    from freipose.cli._cluster import cluster_config
    from freipose.cluster.train import TrainTask, run_train

    config, threads, nodes = p["config"], p["threads"], p["nodes"]
    cfg = cluster_config(p["executor"], p["cluster_file"], None, None, p["max_retries"],
                         gpus=p["gpus"], cpus=threads)  # fmt: skip
    procs = _job_processes(ctx, cfg, nodes, p["tasks_per_node"], p["no_wait"])
    out = (p["out_dir"] or config.with_suffix("")).resolve()
    steps = _check_job_config(config, procs * nodes)
    _check_job_folder(out, p["resume"])
    quiet = bool(ctx.obj and ctx.obj.get("quiet"))
    if cfg.executor == "local" and threads is None:
        from freipose.workers import choose_threads

        cfg = cfg.replace(cpus=choose_threads(None, workers=procs))
    task = TrainTask(
        config=config.resolve(), out=out, kind="baseline" if p["stage"] == "baseline" else None,
        init=_command_line_init(p["init"]), device="cuda" if cfg.gpus else "cpu", nodes=nodes,
        tasks_per_node=procs, threads=cfg.cpus, steps=steps, executor=cfg.executor,
    )  # fmt: skip
    click.echo(f"training {out} on the {cfg.executor} executor: {nodes} node(s) x {procs} "
               f"process(es) on {'GPUs' if cfg.gpus else 'CPUs'}, {cfg.cpus} thread(s) each; "
               f"status: freipose jobs {out}")  # fmt: skip
    result = run_train(task, cfg, wait=not p["no_wait"], progress=not quiet, say=click.echo)
    if result.model is not None:
        click.echo(f"wrote {result.model}")
    else:
        click.echo(f"job {result.job_id} runs on; follow it with: freipose jobs {out}")
    return True


def _job_processes(
    ctx: click.Context, cfg: Any, nodes: int, tasks_per_node: int | None, no_wait: bool
) -> int:
    """Processes per node of the job (one per GPU); refuses what the executor cannot run."""
    if nodes < 1 or (tasks_per_node is not None and tasks_per_node < 1):
        raise click.UsageError("--nodes and --tasks-per-node must be at least 1")
    if cfg.gpus and tasks_per_node not in (None, cfg.gpus):
        raise click.UsageError(
            f"--tasks-per-node {tasks_per_node} with --gpus {cfg.gpus}: the job runs one "
            "process per GPU; leave --tasks-per-node out"
        )
    wanted = "cuda" if cfg.gpus else "cpu"
    if ctx.get_parameter_source("device") == click.core.ParameterSource.COMMANDLINE and not (
        ctx.params["device"].startswith(wanted)
    ):
        raise click.UsageError(
            f"--device {ctx.params['device']} with --gpus {cfg.gpus}: a training job's "
            "processes run on the GPUs --gpus asks for, on CPUs with --gpus 0; leave --device out"
        )
    procs = cfg.gpus or tasks_per_node or 1
    if cfg.executor == "local":
        if nodes != 1 or no_wait:
            raise click.UsageError(
                "--nodes and --no-wait need --executor slurm; the local executor runs its "
                "processes on this machine while the command runs"
            )
        if cfg.gpus:
            import torch

            found = torch.cuda.device_count() if torch.cuda.is_available() else 0
            if found < cfg.gpus:
                raise click.UsageError(
                    f"--gpus {cfg.gpus} with --executor local needs {cfg.gpus} CUDA GPU(s) on "
                    f"this machine; found {found}. Train on CPU processes with --gpus 0 "
                    "--tasks-per-node N, or on a cluster with --executor slurm"
                )
    return procs


def _check_job_config(config: Path, world: int) -> int:
    """The config's steps, after the checks a job would otherwise fail on in the queue.

    Raises:
        ConfigError: a bad config, no labels, or a batch the processes cannot share.
    """
    from freipose.nn.config import ConfigError, load_config

    cfg = load_config(config)
    labels = Path(cfg.data.labels).expanduser() if cfg.data.labels else None
    if labels is not None and not labels.is_absolute():
        labels = config.resolve().parent / labels
    if labels is None or not labels.is_file():
        raise ConfigError(
            f"{config}: [data] labels must name a labels.h5 file (relative to the config's "
            f"folder); found {cfg.data.labels or 'none'}"
        )
    if cfg.schedule.batch_size % world:
        raise ConfigError(
            f"{config}: schedule.batch_size {cfg.schedule.batch_size} cannot be split over "
            f"{world} processes; choose a multiple of {world}"
        )
    return int(cfg.schedule.steps)


def _check_job_folder(out: Path, resume: bool) -> None:
    """A run folder with a checkpoint continues only with --resume or as a job's folder.

    Raises:
        TrainError: a checkpoint of another run, without --resume.
    """
    from freipose.cluster.train import is_train_job
    from freipose.nn.train import TrainError

    if (out / "checkpoint.pt").exists() and not resume and not is_train_job(out):
        raise TrainError(
            f"{out} already holds a training run (checkpoint.pt); pass --resume to "
            "continue it or choose another output folder with --out"
        )


def show_train_job(ctx: click.Context, run: Path, resume: bool) -> None:
    """``freipose jobs RUN`` of a training job: its state and step; ``--resume`` finishes it."""
    from freipose.cluster.train import load_train_task, run_train, train_job_status

    if resume:
        task, cfg = load_train_task(run)
        quiet = bool(ctx.obj and ctx.obj.get("quiet"))
        result = run_train(task, cfg, progress=not quiet, say=click.echo)
        click.echo(f"wrote {result.model}")
    st = train_job_status(run)
    t = st.task
    line = (
        f"{run}: training on the {st.executor} executor ({t.nodes} node(s) x "
        f"{t.tasks_per_node} process(es)): {st.state}, step {st.step} of {t.steps}"
    )
    if st.job_id:
        line += f", job {st.job_id} (attempt {st.attempts})"
    if st.reason:
        line += f": {st.reason}"
    if st.state == "failed" and st.log:
        line += f"; log {st.log}"
    click.echo(line)
    if st.state in ("failed", "waiting"):
        click.echo(f"finish with: freipose jobs {run} --resume")

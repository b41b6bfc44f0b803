"""``freipose train``: train the pose network (or the box detector) from a TOML config."""

from __future__ import annotations

import os
from pathlib import Path

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
) -> None:
    """Train the FreiPose network described by a TOML config.

    The config's [data] table names the labels (and optional eval labels), [model] picks a
    preset (tiny, small, paper) plus overrides, [schedule] and [augment] tune training;
    see docs/formats.md. The run folder gets config.toml (every default written out),
    checkpoint.pt (every schedule.checkpoint_every steps, atomic), model.pt (final),
    log.csv and log.png. A killed run continues with --resume. A new run starts from the
    base model shipped for its architecture ([model] init = "base", the default; see
    docs/models.md), from scratch, or from a checkpoint (--init). Several GPUs or nodes:
    launch with torchrun.

    \b
    Example:
      freipose train examples/train_small.toml --out runs/small
      freipose train examples/train_small.toml --out runs/small --resume
      freipose train examples/train_small.toml --stage baseline --out runs/small_baseline
      torchrun --nproc_per_node 4 -m freipose.cli.main train cfg.toml --device cuda
    """  # noqa: D301 - click needs the \b (backspace) paragraph marker
    with user_errors():
        quiet = bool(ctx.obj and ctx.obj.get("quiet"))
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

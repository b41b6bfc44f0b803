"""``freipose smooth``: temporal smoothing of poses with a posterior standard deviation."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import click

from freipose.cli._cluster import cluster_config, cluster_options, run_through_executor
from freipose.cli._common import (
    allow_incomplete_option,
    check_complete,
    device_option,
    overwrite_option,
    user_errors,
)

if TYPE_CHECKING:
    from freipose.predict.smooth_error import HeldOutError


def smoothed_name(path: Path) -> str:
    """The output file name of a poses file.

    ``x.poses.h5.partial`` -> ``x.poses.h5``; a movement dataset ``x.nc`` -> ``x.poses.h5``
    (the smoothed file is a poses.h5, with the posterior the netCDF format has no place for).
    """
    name = path.name
    if name.endswith(".nc"):
        return name[: -len(".nc")] + ".poses.h5"
    return name[: -len(".partial")] if name.endswith(".partial") else name


@click.command()
@click.argument("poses", nargs=-1, required=True, type=click.Path(exists=True, path_type=Path))
@click.option(
    "-o",
    "--outdir",
    required=True,
    type=click.Path(file_okay=False, path_type=Path),
    help="Folder for the smoothed <session>.poses.h5 files (not the inputs' folder).",
)
@click.option(
    "--validation",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    help="Held-out labels with 3D points (not trained on, e.g. the training config's "
    "eval_labels): the network's error on them is added to the standard deviation. "
    "Needs --model.",
)
@click.option(
    "--model",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    help="The pose checkpoint that predicted the poses (with --validation).",
)
@click.option(
    "--bones",
    is_flag=True,
    help="Pull the skeleton's bone lengths towards their median over the recording (a soft "
    "penalty, stronger for bones the recording shows to be rigid).",
)
@device_option("cpu")
@allow_incomplete_option()
@overwrite_option("smoothed files that exist")
@cluster_options(chunks=False)
@click.pass_context
def smooth(
    ctx: click.Context,
    poses: tuple[Path, ...],
    outdir: Path,
    validation: Path | None,
    model: Path | None,
    bones: bool,
    device: str,
    allow_incomplete: bool,
    overwrite: bool,
    executor: str | None,
    cluster_file: Path | None,
    parallel: int | None,
    max_retries: int | None,
) -> None:
    """Smooth predicted poses over time, with a standard deviation for every point.

    Each keypoint's true position follows a constant-velocity model; the network's
    prediction is that position plus an error correlated over frames (an offset that
    drifts with a correlation time of its own) plus a white error, one scale per
    keypoint (a confidence that falls with an unusual pose would damp it), with heavy
    (Student-t) tails: a prediction that deviates counts less the more it deviates, and
    only gross outliers (spikes) are left out
    (extra/rejected; a warning names the keypoints with more than 2 % of their predictions
    left out, far more than the model expects). The parameters are fitted per keypoint on
    the recording, and the process noise rises where a keypoint moves clearly faster than
    that over several frames or jumps in a step, so fast movements are followed rather
    than damped. The smoothed position keeps the correlated error, which one recording
    cannot tell from movement reliably. Frames without a prediction are filled
    (extra/filled); extra/smooth_std holds the standard deviation in mm per axis, which
    covers what the recording reveals of the network's error; with --validation and
    --model it also covers the network's error measured on held-out labels (an offset
    that persists over seconds, which one recording cannot reveal). The output has the
    poses.h5 schema; analyze, export and render read it.

    With --executor (or --cluster FILE) every file is one unit (a recording is smoothed
    whole) run in worker processes (local) or as a SLURM job array; existing smoothed
    files are kept. `freipose jobs OUTDIR` shows the units.

    \b
    Example:
      freipose smooth poses/*.poses.h5 -o poses_smooth/ \\
          --validation labels/eval.h5 --model train/pose/model.pt
      freipose smooth poses/*.poses.h5 -o poses_smooth/ --executor local --parallel 4
    """  # noqa: D301 - click needs the \b (backspace) paragraph marker
    with user_errors():
        from freipose.io.atomic import refuse_existing
        from freipose.predict.smooth import refuse_same, smooth_file

        config = cluster_config(executor, cluster_file, None, parallel, max_retries)
        jobs = [(p, outdir / smoothed_name(p)) for p in dict.fromkeys(poses)]
        for p, _ in jobs:
            check_complete(p, allow_incomplete)
        for p, out in jobs:
            refuse_same(p, out)
            if config is None:
                refuse_existing(out, overwrite)
        held_out = _held_out_error(validation, model, [p for p, _ in jobs], device)
        if config is not None:
            from freipose.cluster.smooth import SmoothTask

            task = SmoothTask.of(jobs, outdir, error_floor=held_out, bones=bones,
                                 threads=config.cpus)  # fmt: skip
            run_through_executor(ctx, task, config, overwrite)
            return
        for p, out in jobs:
            path = smooth_file(p, out, overwrite=overwrite, error_floor=held_out, bones=bones)
            click.echo(f"wrote {path}")


def _held_out_error(
    validation: Path | None, model: Path | None, poses: list[Path], device: str
) -> HeldOutError | None:
    """The network's error on the held-out labels (None without ``--validation``)."""
    from freipose.predict.smooth import SmoothingError
    from freipose.predict.smooth_error import model_validation_error, predicted_by

    if validation is None and model is None:
        return None
    if validation is None or model is None:
        raise SmoothingError(
            "--validation and --model go together: the held-out labels and the checkpoint "
            "that predicted the poses (pass both, or neither)"
        )
    how = predicted_by(poses, model)
    err = model_validation_error(
        model, validation, refine=how.refine, device=device, overrides=how.overrides
    )
    click.echo(f"held-out error of the network: {err.source}")
    return err

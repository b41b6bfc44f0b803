"""``freipose eval``: joint position errors of a trained network on labeled data."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from freipose.cli._common import (
    device_option,
    inference_options,
    inference_overrides,
    user_errors,
)

if TYPE_CHECKING:
    import numpy as np

    from freipose.nn.evaluate import Evaluation, Sanity


@click.command("eval")
@click.argument("ckpt", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.argument("labels", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option(
    "-o", "--output", "out_dir", type=click.Path(file_okay=False, path_type=Path), required=True,
    help="Folder for metrics.json, jpe_per_keypoint.csv, pck.csv/png, jpe_boxplot.png.",
)  # fmt: skip
@click.option(
    "--baseline",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    help="A second checkpoint (e.g. from --stage baseline) evaluated the same way.",
)
@click.option(
    "--root",
    type=click.Path(file_okay=False, path_type=Path),
    help="Folder the videos are relative to [default: the labels file's folder].",
)
@click.option(
    "--train-labels",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    help="Training labels for the constant-pose references [default: the labels the "
    "checkpoint was trained on, where it records them and they exist].",
)
@device_option("cpu")
@click.option("--batch-size", type=int, default=4, show_default=True, help="Samples per batch.")
@click.option(
    "--center-noise", type=float, default=0.0, show_default=True,
    help="Std (mm) of Gaussian noise added to the cube centre (mimics detector error).",
)  # fmt: skip
@inference_options
@click.pass_context
def evaluate(
    ctx: click.Context,
    ckpt: Path,
    labels: Path,
    out_dir: Path,
    baseline: Path | None,
    root: Path | None,
    train_labels: Path | None,
    device: str,
    batch_size: int,
    center_noise: float,
    fusion_reject: float | None,
    map_window: int | None,
) -> None:
    """Evaluate a pose network against 3D labels (JPE median, 30/70 % percentiles, PCK).

    The voxel cube is centred on each instant's mean labeled 3D point. For the voxel
    network both the initial (P0) and refined (P1) poses are reported; a baseline
    checkpoint given with --baseline is reported alongside.

    Failure modes: per left/right pair of the skeleton the median distance between the
    two keypoints predicted vs true and the share of instants with left and right
    swapped, per bone the median length predicted vs true; a warning for each pair a
    network collapses (predicted closer than half the true distance).

    Sanity references: the training labels' median pose (body-centred) placed at each
    held-out instant's centre, and at the training labels' mean centre; a network whose
    median JPE is not below the first has learned nothing beyond that pose (warned).

    Paired comparisons: for the two networks, and each against that reference, the
    differences of their median and of their mean JPE on the same instants, each with a
    95 % interval from a block bootstrap over the instants in time order (consecutive
    frames are near-copies), and the share of instants where the first is better; an
    interval that contains 0 says the held-out data cannot tell the two apart. The mean
    also weighs the few large errors (a hidden paw far off) that the median hides.

    \b
    Example:
      freipose eval runs/small/model.pt eval/labels.h5 -o runs/small/eval
      freipose eval runs/small/model.pt eval/labels.h5 -o out --baseline runs/base/model.pt
    """  # noqa: D301 - click needs the \b (backspace) paragraph marker
    with user_errors():
        from freipose.io.checkpoints import POSE_NETWORK, check_checkpoints
        from freipose.nn.evaluate import evaluate_checkpoints, sanity_checks, write_report

        quiet = bool(ctx.obj and ctx.obj.get("quiet"))
        check_checkpoints(("CKPT", ckpt, POSE_NETWORK), ("--baseline", baseline, POSE_NETWORK))
        methods = {"": ckpt} if baseline is None else {"": ckpt, "baseline": baseline}
        ev = evaluate_checkpoints(
            methods, labels, root=root, device=device, batch_size=batch_size,
            center_noise=center_noise, progress=not quiet,
            overrides=inference_overrides(fusion_reject, map_window),
        )  # fmt: skip
        train3d = _training_points(ev, train_labels)
        sanity = sanity_checks(ev, train3d)
        summary = write_report(out_dir, ev.errors, ev.keypoints, sanity, ev.settings)
        _echo_results(summary, sanity)
        _echo_settings(ev.settings)
        click.echo(f"wrote {out_dir}")


def _training_points(ev: Evaluation, given: Path | None) -> np.ndarray | None:
    """The training labels' 3D points for the references (None, said, where there are none)."""
    from freipose.io.labels import read_labels_h5
    from freipose.nn.evaluate import EvaluationError, trained_on

    if given is not None:
        path, why = given, "given with --train-labels"
    else:
        found, why = trained_on(ev)
        if found is None:
            click.echo(f"no sanity references: {why}; name the training labels with --train-labels")
            return None
        path = found
    click.echo(f"training labels for the references: {path} ({why})")
    lab = read_labels_h5(path)
    if tuple(lab.keypoints) != ev.keypoints:
        raise EvaluationError(
            f"{path}: the training labels have keypoints {list(lab.keypoints)}, the evaluated "
            f"networks {list(ev.keypoints)}; pass --train-labels with the labels the network "
            "was trained on"
        )
    return lab.points3d


def _echo_settings(settings: dict[str, Any]) -> None:
    """Print the inference settings of each result and those chosen on validation labels."""
    for name, rep in settings.items():
        used = ", ".join(f"{k} {v:g}" for k, v in rep["used"].items())
        val = rep.get("validation")
        if not val:
            click.echo(f"{name}: {used} (as configured; no validation labels in training)")
            continue
        click.echo(
            f"{name}: {used}; chosen after training on {val['instants']} validation instants "
            f"(median P1 {val['median_p1_mm']:.2f} mm; configured "
            + ", ".join(f"{k} {v:g}" for k, v in val["configured"].items())
            + ")"
        )


def _echo_results(summary: dict[str, Any], sanity: Sanity) -> None:
    """Print each method's JPE, the references, the failure modes and the warnings."""
    from freipose.nn.failure_modes import format_failure_modes

    for name, s in summary.items():
        o = s["overall"]
        click.echo(
            f"{name}: median JPE {o['median']:.2f} mm "
            f"(30-70 %: {o['p30']:.2f}-{o['p70']:.2f}), n = {o['n']}"
        )
    for name, r in sanity.references.items():
        click.echo(f"reference, {name} (no network): median JPE {r['median_mm']:.2f} mm")
    if sanity.comparisons:
        c0 = sanity.comparisons[0]
        click.echo(
            f"paired comparisons on the same {c0.instants} held-out instants (median and mean "
            f"JPE, differences, their intervals from a block bootstrap in blocks of {c0.block} "
            "consecutive instants):"
        )
        for c in sanity.comparisons:
            click.echo(f"  {c.sentence()}")
    for name, modes in sanity.failure_modes.items():
        lines = format_failure_modes({**modes, "warnings": []})
        if lines:
            click.echo(f"failure modes of {name}:")
            for ln in lines:
                click.echo(ln)
    for w in sanity.warnings:
        click.echo(w)

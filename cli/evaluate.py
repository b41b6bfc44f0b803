"""``freipose eval``: joint position errors of a trained network on labeled data."""

from __future__ import annotations

from pathlib import Path

import click

from freipose.cli._common import device_option, user_errors


@click.command()
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
@device_option("cpu")
@click.option("--batch-size", type=int, default=4, show_default=True, help="Samples per batch.")
@click.option(
    "--center-noise", type=float, default=0.0, show_default=True,
    help="Std (mm) of Gaussian noise added to the cube centre (mimics detector error).",
)  # fmt: skip
@click.pass_context
def evaluate(
    ctx: click.Context,
    ckpt: Path,
    labels: Path,
    out_dir: Path,
    baseline: Path | None,
    root: Path | None,
    device: str,
    batch_size: int,
    center_noise: float,
) -> None:
    """Evaluate a pose network against 3D labels (JPE median, 30/70 % percentiles, PCK).

    The voxel cube is centred on each instant's mean labeled 3D point. For the voxel
    network both the initial (P0) and refined (P1) poses are reported; a baseline
    checkpoint given with --baseline is reported alongside.

    \b
    Example:
      freipose eval runs/small/model.pt eval/labels.h5 -o runs/small/eval
      freipose eval runs/small/model.pt eval/labels.h5 -o out --baseline runs/base/model.pt
    """  # noqa: D301 - click needs the \b (backspace) paragraph marker
    with user_errors():
        from freipose.io.checkpoints import POSE_NETWORK, check_checkpoints
        from freipose.nn.evaluate import evaluate_checkpoints, write_report

        quiet = bool(ctx.obj and ctx.obj.get("quiet"))
        check_checkpoints(("CKPT", ckpt, POSE_NETWORK), ("--baseline", baseline, POSE_NETWORK))
        methods = {"": ckpt} if baseline is None else {"": ckpt, "baseline": baseline}
        results, keypoints = evaluate_checkpoints(
            methods, labels, root=root, device=device, batch_size=batch_size,
            center_noise=center_noise, progress=not quiet,
        )  # fmt: skip
        summary = write_report(out_dir, results, keypoints)
        for name, s in summary.items():
            o = s["overall"]
            click.echo(
                f"{name}: median JPE {o['median']:.2f} mm "
                f"(30-70 %: {o['p30']:.2f}-{o['p70']:.2f}), n = {o['n']}"
            )
        click.echo(f"wrote {out_dir}")

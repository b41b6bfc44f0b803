"""``freipose demo``: the whole workflow on built-in synthetic data, with an HTML report."""

from __future__ import annotations

from pathlib import Path

import click

from freipose.cli._common import user_errors
from freipose.cli._threads import threads_option, use_threads


@click.command()
@click.argument("outdir", required=False, default="freipose_demo", type=click.Path(path_type=Path))
@click.option(
    "--preset",
    type=click.Choice(["small", "tiny"]),
    default="small",
    show_default=True,
    help="small: the real workflow, under 10 min on an otherwise idle 2-core CPU (measured "
    "times: docs/benchmarks.md); other processes on the same cores slow it down (the thread "
    "count follows the free cores, see --threads); tiny: a few minutes, meaningless numbers "
    "(a smoke test).",
)
@click.option(
    "--seed",
    type=int,
    default=0,
    show_default=True,
    help="Training seed of the networks (the data stay the same): run a few to see how much "
    "the figures move with the training alone.",
)
@click.option("--device", default="cpu", show_default=True, help="cpu, cuda or cuda:N.")
@threads_option()
@click.pass_context
def demo(
    ctx: click.Context, outdir: Path, preset: str, seed: int, device: str, threads: int | None
) -> None:
    """Run the whole FreiPose workflow on synthetic data and write OUTDIR/report.html.

    Renders a calibration recording and three stimulated days of a rat filmed by 7 cameras,
    calibrates the cameras and compares them with the true rig, imports labels of day 1,
    trains the detector, the voxel network and the triangulation baseline, predicts days 2
    and 3, evaluates against the truth, analyzes the stimulation effect (the classifier
    trains on day 3 and is tested on day 2) and writes a report with every step's figures.
    Each step runs the library code of the matching command (examples/workflow.sh runs the
    commands themselves). Finished steps are recorded in OUTDIR/.demo/; running the command
    again skips them and continues an interrupted step.

    \b
    Example:
      freipose demo                      # -> freipose_demo/report.html
      freipose demo demo_tiny --preset tiny
    """  # noqa: D301 - click needs the \b (backspace) paragraph marker
    with user_errors():
        from freipose.demo.runner import run_demo

        quiet = bool(ctx.obj and ctx.obj.get("quiet"))
        use_threads(threads)
        report = run_demo(
            outdir,
            preset,
            device=device,
            say=(lambda m: None) if quiet else click.echo,
            progress=None if not quiet else False,
            seed=seed,
        )
        if quiet:
            click.echo(f"wrote {report}")

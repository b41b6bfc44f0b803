"""``freipose detect``: boxes of the animal that agree across views, and its 3D centre."""

from __future__ import annotations

from pathlib import Path

import click

from freipose.cli._cluster import cluster_config, cluster_options, run_through_executor
from freipose.cli._common import (
    calibration_option,
    camera_map_from,
    camera_map_option,
    device_option,
    frames_option,
    overwrite_option,
    user_errors,
)
from freipose.cli._threads import threads_option, use_threads
from freipose.errors import FreiPoseError


@click.command()
@click.argument("session", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option(
    "-o", "--output", type=click.Path(dir_okay=False, path_type=Path), required=True,
    help="Output boxes.h5 (format in docs/formats.md).",
)  # fmt: skip
@calibration_option("Calibration file [default: SESSION/calibration.toml].")
@camera_map_option()
@click.option(
    "--model",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    help="Detector checkpoint (from `freipose train CONFIG --stage detector`).",
)
@click.option(
    "--method",
    type=click.Choice(["detector", "bgsub", "fixed"]),
    help="Box source [default: detector with --model, fixed with --fixed-boxes].",
)
@click.option(
    "--fixed-boxes",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    help="TOML with a [boxes] table: camera = [x0, y0, x1, y1].",
)
@frames_option()
@device_option()
@click.option(
    "--cube-size",
    type=float,
    default=400.0,
    show_default=True,
    help="Edge (mm) of the cube whose projection gives the crop boxes.",
)
@click.option(
    "--min-views",
    type=int,
    default=2,
    show_default=True,
    help="Fewest agreeing views for a 3D centre.",
)
@click.option(
    "--batch-size", type=int, default=8, show_default=True, help="Time instants per detector batch."
)
@click.option(
    "--bg-samples",
    type=int,
    default=40,
    show_default=True,
    help="Frames per camera for the median background (bgsub).",
)
@overwrite_option("OUTPUT if it exists")
@cluster_options
@threads_option()
@click.pass_context
def detect(
    ctx: click.Context,
    session: Path,
    output: Path,
    calibration: Path | None,
    camera_map: tuple[str, ...],
    model: Path | None,
    method: str | None,
    fixed_boxes: Path | None,
    frames: str | None,
    device: str,
    cube_size: float,
    min_views: int,
    batch_size: int,
    bg_samples: int,
    overwrite: bool,
    executor: str | None,
    cluster_file: Path | None,
    chunk_frames: int | None,
    parallel: int | None,
    max_retries: int | None,
    threads: int | None,
) -> None:
    """Find the animal in every view and frame, consistently across views.

    Every camera's candidate boxes are combined into a robust 3D centre; each view gets
    the box that agrees with it (or a replacement box where the detector missed), and a
    crop box from a cube of --cube-size mm around the centre. Writes per frame and camera
    the boxes, scores, crop boxes, the 3D centre and how many views agreed. An
    interrupted run leaves .OUTPUT.progress.npz next to the output; running the same
    command again continues from there. An existing OUTPUT is kept unless --overwrite;
    a second run on the same OUTPUT is refused while the first one works.

    With --executor (or --cluster FILE) the frames are cut into units of --chunk-frames
    frames (whole batches) that run in worker processes (local) or as a SLURM job array;
    their boxes are joined into OUTPUT, equal to a single run's with the same --threads
    (each unit runs --threads threads, or the [cluster] table's cpus). `freipose jobs OUTPUT`
    shows the units; the same command again submits only what is missing.

    \b
    Example:
      freipose detect session1/ --model runs/detector/detector.pt -o session1/boxes.h5
      freipose detect session1/ --method bgsub --frames 0:500 -o boxes.h5
      freipose detect session1/ --fixed-boxes boxes.toml -o boxes.h5
      freipose detect session1/ --model detector.pt -o boxes.h5 --cluster cluster.toml
    """  # noqa: D301 - click needs the \b (backspace) paragraph marker
    with user_errors():
        from freipose.detect.multiview import ConsistencyConfig
        from freipose.detect.pipeline import make_source, open_sources
        from freipose.io.boxes import read_boxes_h5
        from freipose.io.session import discover_sessions
        from freipose.io.video import frame_range

        if batch_size < 1:
            raise FreiPoseError(f"--batch-size must be >= 1, got {batch_size}")
        config = cluster_config(executor, cluster_file, chunk_frames, parallel, max_retries,
                                cpus=threads)  # fmt: skip
        use_threads(threads)
        cfg = ConsistencyConfig(cube_size=cube_size, min_views=min_views)
        opened = discover_sessions(
            [session],
            calibration,
            cameras="calibration",
            need_fps=False,
            camera_map=camera_map_from(camera_map),
        )
        rig, sources = opened[0].rig, open_sources(opened[0])
        rng = frame_range(frames, opened[0].num_frames)
        source, method_name, desc = make_source(
            rig, sources, rng, model, method, fixed_boxes, device, bg_samples
        )
        if config is not None:
            from freipose.cluster.detect import DetectTask

            task = DetectTask(opened[0], output, frames, model, method, fixed_boxes, device,
                              bg_samples, cube_size, min_views, batch_size,
                              config.chunk_frames, config.cpus)  # fmt: skip
            run_through_executor(ctx, task, config, overwrite)
            _say_result(output, read_boxes_h5(output))
            return
        data = _detect_here(output, overwrite, rig, sources, rng, source, cfg, batch_size,
                            method_name, desc)  # fmt: skip
        _say_result(output, data)


def _say_result(output: Path, data) -> None:  # noqa: ANN001 - a BoxesData
    """One line: frames, cameras, method, how often a 3D centre was found."""
    n = len(data)
    found = int((data.n_agree > 0).sum())
    click.echo(
        f"{output}: {n} frames x {len(data.cameras)} cameras ({data.method}); 3D centre in "
        f"{found}/{n} frames, {float(data.n_agree.mean()):.2f} agreeing views on average"
    )


def _detect_here(output: Path, overwrite: bool, rig, sources, rng, source, cfg, batch_size: int,
                 method_name: str, desc: str):  # fmt: skip
    """Detect in this process under the output's lock; returns the written BoxData.

    Partial results survive an interruption (.OUTPUT.progress.npz); rerunning continues.
    """
    from freipose.detect.pipeline import detect_session
    from freipose.io.atomic import refuse_existing, remove_leftover_partials
    from freipose.io.boxes import write_boxes_h5
    from freipose.io.lock import output_lock

    refuse_existing(output, overwrite)  # before the work; again under the lock
    progress = output.with_name(f".{output.name}.progress.npz")
    with output_lock(output, "boxes file"):
        refuse_existing(output, overwrite)
        remove_leftover_partials(output)
        remove_leftover_partials(progress)
        data = detect_session(rig, sources, rng, source, cfg, batch_size, method_name, desc,
                              progress_file=progress)  # fmt: skip
        write_boxes_h5(data, output)
        progress.unlink(missing_ok=True)
    return data

"""``freipose render``: overlay video of predicted poses on the session's videos."""

from __future__ import annotations

from pathlib import Path

import click

from freipose.cli._cluster import cluster_config, cluster_options, run_through_executor
from freipose.cli._common import (
    allow_incomplete_option,
    check_complete,
    overwrite_option,
    user_errors,
)
from freipose.errors import FreiPoseError


@click.command()
@click.argument("session", type=click.Path(exists=True, path_type=Path))
@click.argument("poses", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option(
    "-o",
    "--output",
    type=click.Path(dir_okay=False, path_type=Path),
    required=True,
    help="Overlay video (.mp4: H.264, plays in web browsers; .avi; lossless .mkv).",
)
@click.option(
    "--cameras",
    help="Comma-separated cameras to show, in this order [default: all with a video].",
)
@click.option("--frames", help="Frame range START:STOP (video frame numbers) [default: all].")
@click.option(
    "--tile-width", type=int, default=480, show_default=True, help="Width of each view in pixels."
)
@click.option("--no-3d", is_flag=True, help="Leave out the 3D skeleton panel.")
@click.option(
    "--force",
    is_flag=True,
    help="Draw the poses even if they do not belong to SESSION (other session, cameras or "
    "frame count).",
)
@allow_incomplete_option()
@overwrite_option("the overlay video")
@cluster_options(chunks=False)
@click.pass_context
def render(
    ctx: click.Context,
    session: Path,
    poses: Path,
    output: Path,
    cameras: str | None,
    frames: str | None,
    tile_width: int,
    no_3d: bool,
    force: bool,
    allow_incomplete: bool,
    overwrite: bool,
    executor: str | None,
    cluster_file: Path | None,
    parallel: int | None,
    max_retries: int | None,
) -> None:
    """Draw predicted poses onto the videos: one tile per camera plus a 3D panel.

    Keypoints and limbs are coloured by confidence (red 0, yellow 0.5, green 1). The
    cameras come from the calibration stored in POSES (or SESSION/calibration.toml).
    POSES must be a finished prediction of SESSION (its session name, videos and frame
    count are checked; --force draws them anyway), and an existing OUTPUT is kept unless
    --overwrite.

    With --executor (or --cluster FILE) the video is rendered by one unit (one encoded
    stream) in a worker process (local) or as a SLURM job; an existing OUTPUT is kept
    unless --overwrite. `freipose jobs OUTPUT` shows it.

    \b
    Examples:
      freipose render rec1/ poses/rec1.poses.h5 -o rec1_overlay.mp4 --frames 0:300
      freipose render rec1/ poses/rec1.poses.h5 -o clip.mkv --cameras cam0,cam3 --no-3d
      freipose render rec1/ poses/rec1.poses.h5 -o rec1.mp4 --cluster cluster.toml
    """  # noqa: D301 - click needs the \b (backspace) paragraph marker
    with user_errors():
        from freipose.io.atomic import refuse_existing, remove_leftover_partials
        from freipose.io.calibration import load_calibration
        from freipose.io.lock import output_lock
        from freipose.io.poses import read_poses_h5
        from freipose.io.session import CALIBRATION_NAMES
        from freipose.io.video import find_camera_videos, frame_range
        from freipose.predict.render import check_session, render_overlay

        quiet = bool(ctx.obj and ctx.obj.get("quiet"))
        if tile_width < 32:
            raise FreiPoseError(f"--tile-width must be at least 32 pixels, got {tile_width}")
        config = cluster_config(executor, cluster_file, None, parallel, max_retries)
        check_complete(poses, allow_incomplete)
        data = read_poses_h5(poses)
        rig = data.calibration
        if rig is None:
            found = [session / n for n in CALIBRATION_NAMES] if session.is_dir() else []
            calib = next((p for p in found if p.is_file()), None)
            if calib is None:
                raise FreiPoseError(
                    f"{poses} stores no calibration and {session} has no calibration.toml"
                )
            rig = load_calibration(calib)
        videos = find_camera_videos(session)
        names = _camera_names(cameras, rig, videos, session)
        for problem in check_session(data, poses, session, videos, force):
            click.echo(f"warning: {problem} (--force)", err=True)
        rng = None
        if frames:
            stop = int(data.frame_index.max()) + 1
            r = frame_range(frames, stop)
            rng = (r.start, r.stop)
        if config is not None:
            from freipose.cluster.render import RenderTask

            n = len(data.frame_index) if rng is None else rng[1] - rng[0]
            task = RenderTask(poses, tuple(videos[c] for c in names), rig.subset(names),
                              output, rng, n, tile_width, not no_3d,
                              threads=config.cpus)  # fmt: skip
            run_through_executor(ctx, task, config, overwrite)
            return
        with output_lock(output, "overlay video"):
            refuse_existing(output, overwrite)
            remove_leftover_partials(output, output.suffix.lower())
            remove_leftover_partials(output)
            out = render_overlay(
                [videos[n] for n in names],
                rig.subset(names),
                data,
                output,
                frames=rng,
                tile_width=tile_width,
                show_3d=not no_3d,
                progress=not quiet,
            )
        click.echo(f"wrote {out}")


def _camera_names(cameras: str | None, rig, videos: dict, session: Path) -> list[str]:  # noqa: ANN001
    """The cameras to show: ``--cameras`` in its order, else every calibrated one with a video.

    Raises:
        FreiPoseError: a camera is not both in the calibration and among the videos, or none is.
    """
    names = (
        [c.strip() for c in cameras.split(",")]
        if cameras
        else [n for n in rig.names if n in videos]
    )
    bad = [n for n in names if n not in rig.names or n not in videos]
    if bad:
        raise FreiPoseError(
            f"cameras {bad} are not both in the calibration {rig.names} and among the "
            f"videos {sorted(videos)}"
        )
    if not names:
        raise FreiPoseError(f"no video in {session} matches the calibration's cameras {rig.names}")
    return names

"""``freipose synth``: render a synthetic multi-camera session with exact ground truth."""

from __future__ import annotations

from typing import Any

import click

from freipose.cli._common import user_errors


def _parse_size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise click.BadParameter(f"expected WIDTHxHEIGHT such as 320x256, got {text!r}") from None
    return w, h


@click.command()
@click.argument("outdir", type=click.Path(file_okay=False))
@click.option(
    "--cameras",
    "n_cameras",
    type=int,
    default=None,
    help="Number of cameras of the default rig [7].",
)
@click.option(
    "--rig",
    "rig_file",
    type=click.Path(exists=True, dir_okay=False),
    help="Rig TOML file (camera positions, look-at points, sizes, focal lengths, "
    "distortion); see examples/rig.toml.",
)
@click.option("--frames", type=int, default=None, help="Number of frames [200].")
@click.option("--fps", type=float, default=None, help="Frame rate [50].")
@click.option("--size", type=str, default=None, help="Image size WIDTHxHEIGHT [320x256].")
@click.option("--seed", type=int, default=None, help="Random seed [0]; same seed, same scene.")
@click.option(
    "--appearance",
    type=click.Choice(["hooded", "albino", "random"]),
    default=None,
    help="Coat of the animal [random].",
)
@click.option(
    "--stimulation",
    "stim",
    type=str,
    default=None,
    help="Stimulation protocol: comma-separated key=value pairs (body_part, effect, "
    "frequency_hz, amplitude_mm, duration_s, spacing_s, onset_s, count), e.g. "
    "'effect=lift,duration_s=2'; '' for the defaults (right front paw oscillating at "
    "10 Hz, 1 s windows 2 s apart). Effects: oscillate, lift, freeze. Writes events.csv.",
)
@click.option(
    "--calibration-video",
    is_flag=True,
    default=None,
    help="Also render the rig filming a calibration board (OUTDIR/calibration/).",
)
@click.option(
    "--calibration-frames", type=int, default=None, help="Frames of the calibration video [120]."
)
@click.option(
    "--board",
    "board_file",
    type=click.Path(exists=True, dir_okay=False),
    help="Board file for the calibration video [a ChArUco board sized for the arena].",
)
@click.option(
    "--lossless", is_flag=True, default=None, help="Write lossless .mkv (FFV1) instead of .mp4."
)
@click.option(
    "--config",
    "config_file",
    type=click.Path(exists=True, dir_okay=False),
    help="Reproduce a scene: read the settings from its scene.toml (options given "
    "on the command line override them).",
)
@click.option("--workers", type=int, default=None, help="Parallel processes [up to 2].")
@click.option("--overwrite", is_flag=True, help="Replace a different scene already in OUTDIR.")
def synth(
    outdir: str,
    n_cameras: int | None,
    rig_file: str | None,
    frames: int | None,
    fps: float | None,
    size: str | None,
    seed: int | None,
    appearance: str | None,
    stim: str | None,
    calibration_video: bool | None,
    calibration_frames: int | None,
    board_file: str | None,
    lossless: bool | None,
    config_file: str | None,
    workers: int | None,
    overwrite: bool,
) -> None:
    """Render a synthetic multi-camera session of a moving rat with exact ground truth.

    Writes one video per camera, calibration.toml (the true cameras), labels.h5 (exact 3D
    keypoints, their 2D projections and per-view visibility for every frame), events.csv
    (with --stimulation) and scene.toml (all settings and the seed; --config reproduces it).

    \b
    Example:
      freipose synth demo/session1 --frames 300 --cameras 7 --seed 1
      freipose synth demo/stim --stimulation 'body_part=Paw Front Right,duration_s=2'
      freipose synth demo/rig_test --rig examples/rig.toml --calibration-video
    """  # noqa: D301 - click needs the \b (backspace) paragraph marker
    with user_errors():
        from freipose.synth import SceneConfig, StimulationConfig, generate_session

        base = SceneConfig.from_toml(config_file) if config_file else SceneConfig()
        given = {  # options not given stay None and keep the base config's value
            "n_cameras": n_cameras,
            "rig_file": str(rig_file) if rig_file is not None else None,
            "frames": frames,
            "fps": fps,
            "size": _parse_size(size) if size is not None else None,
            "seed": seed,
            "appearance": appearance,
            "stimulation": StimulationConfig.parse(stim) if stim is not None else None,
            "calibration_video": True if calibration_video else None,
            "calibration_frames": calibration_frames,
            "video_format": ".mkv" if lossless else None,
        }
        changes: dict[str, Any] = {k: v for k, v in given.items() if v is not None}
        if board_file is not None:
            from freipose.calibration.board_files import load_board

            changes["board"] = load_board(board_file).to_dict()
        cfg = SceneConfig.from_dict({**base.to_dict(), **changes})
        paths = generate_session(outdir, cfg, workers=workers, overwrite=overwrite)
        click.echo(
            f"wrote {len(paths.videos)} videos, {paths.calibration.name}, {paths.labels.name}"
            + (f", {paths.events.name}" if paths.events else "")
            + (f", calibration/ ({len(paths.calibration_videos)} board videos)"
               if paths.calibration_videos else "")
            + f" to {paths.folder}"
        )  # fmt: skip

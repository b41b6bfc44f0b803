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


def _scales(text: str) -> tuple[float, ...]:
    try:
        return tuple(float(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise click.BadParameter(
            f"expected size factors such as 1.0,0.6, got {text!r}", param_hint="--animal-scales"
        ) from None


def _formats(text: str) -> tuple[str, ...]:
    return tuple(v.strip() for v in text.split(",") if v.strip())


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
    "--animal-seed",
    type=int,
    default=None,
    help="Seed of the individual (size, proportions, random coat) [the --seed]: sessions with "
    "the same animal seed film the same animal.",
)
@click.option(
    "--appearance",
    type=click.Choice(["hooded", "albino", "dark", "piebald", "random"]),
    default=None,
    help="Coat of the animal [random: hooded or albino for a rat, dark or albino for a mouse; "
    "piebald (dark patches on white) is never drawn at random].",
)
@click.option(
    "--animal",
    type=click.Choice(["rat", "mouse"]),
    default=None,
    help="The animal [rat]; a mouse is 0.42 times a rat's size (give it --arena-size 250x250).",
)
@click.option(
    "--animal-scale", type=float, default=None, help="Body size factor, rat = 1 [the animal's]."
)
@click.option(
    "--animals",
    type=click.IntRange(1, 4),
    default=None,
    help="Number of animals, 1..4 [1]; 2..4: a social scene (they meet, cross, climb over and "
    "hide each other); labels.h5 then has a row per frame and animal, and true_poses.h5 the "
    "truth (time, animal, keypoint, xyz) with per-view visibility.",
)
@click.option(
    "--coat-mix",
    type=click.Choice(["random", "same", "different"]),
    default=None,
    help="Coats of several animals with a random --appearance [random: each drawn].",
)
@click.option(
    "--animal-scales",
    type=str,
    default=None,
    help="Body size factor of each animal, comma-separated, e.g. 1.0,0.6 [each the animal's].",
)
@click.option(
    "--arena-size", type=str, default=None, help="Inner arena size WIDTHxDEPTH in mm [600x600]."
)
@click.option("--wall-height", type=float, default=None, help="Arena wall height, mm [100].")
@click.option(
    "--grayscale", is_flag=True, default=None, help="Grayscale cameras (R = G = B in every pixel)."
)
@click.option(
    "--lens",
    type=click.Choice(["standard", "fisheye", "pinhole"]),
    default=None,
    help="Lenses of the default rig [standard: mild barrel distortion; fisheye: strong].",
)
@click.option(
    "--layout",
    type=click.Choice(["ring", "above", "side", "below", "arc"]),
    default=None,
    help="Default rig layout [ring]; below: the last camera films through a transparent floor; "
    "arc: all cameras on one side (never drawn by --randomize).",
)
@click.option(
    "--reflections",
    type=float,
    default=None,
    help="Wall reflectivity 0..0.9: mirror images of the animal in the walls [0].",
)
@click.option(
    "--walls",
    type=click.Choice(["opaque", "acrylic"]),
    default=None,
    help="Arena walls [opaque]; acrylic: transparent, the animal is seen through them.",
)
@click.option(
    "--rest-fraction",
    type=float,
    default=None,
    help="Share of the time the animal rests, almost still for seconds [0].",
)
@click.option(
    "--floor", type=click.Choice(["mat", "bedding"]), default=None, help="Floor texture [mat]."
)
@click.option(
    "--label-files",
    type=str,
    default=None,
    help="Also write per-camera label files of predicted instances, comma-separated formats: "
    "sleap (<camera>/<camera>.slp), dlc (labeled-data/<session>_<camera>/CollectedData_synthetic"
    ".csv), sleap-session (<session>.slp: one SLEAP multi-camera file with the cameras and an "
    "instance group per animal and frame); visible points only.",
)
@click.option(
    "--label-noise", type=float, default=None, help="Noise of the label files' points, px [1]."
)
@click.option(
    "--randomize",
    is_flag=True,
    default=None,
    help="Domain randomisation: coat, size, arena, cameras (3-8), image size, layout, lens, "
    "grayscale, floor, colours, lighting, blur, noise, reflections and resting drawn from --seed.",
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
    animal_seed: int | None,
    appearance: str | None,
    animal: str | None,
    animal_scale: float | None,
    animals: int | None,
    coat_mix: str | None,
    animal_scales: str | None,
    arena_size: str | None,
    wall_height: float | None,
    grayscale: bool | None,
    lens: str | None,
    layout: str | None,
    reflections: float | None,
    walls: str | None,
    rest_fraction: float | None,
    floor: str | None,
    label_files: str | None,
    label_noise: float | None,
    randomize: bool | None,
    stim: str | None,
    calibration_video: bool | None,
    calibration_frames: int | None,
    board_file: str | None,
    lossless: bool | None,
    config_file: str | None,
    workers: int | None,
    overwrite: bool,
) -> None:
    """Render a synthetic multi-camera session of moving rats or mice with exact ground truth.

    Writes one video per camera, true_calibration.toml (the true cameras), labels.h5 (exact 3D
    keypoints, their 2D projections and per-view visibility for every frame), events.csv
    (with --stimulation) and scene.toml (all settings and the seed; --config reproduces it).

    \b
    Example:
      freipose synth demo/session1 --frames 300 --cameras 7 --seed 1
      freipose synth demo/stim --stimulation 'body_part=Paw Front Right,duration_s=2'
      freipose synth demo/rig_test --rig examples/rig.toml --calibration-video
      freipose synth lab/mouse --animal mouse --arena-size 250x250 --grayscale
          --lens fisheye --walls acrylic --reflections 0.3 --rest-fraction 0.6 --floor bedding
          --label-files sleap
      freipose synth base/s1000 --seed 1000 --randomize
      freipose synth social/pair --animals 2 --coat-mix different --label-files sleap,dlc
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
            "animal_seed": animal_seed,
            "appearance": appearance,
            "stimulation": StimulationConfig.parse(stim) if stim is not None else None,
            "calibration_video": True if calibration_video else None,
            "calibration_frames": calibration_frames,
            "video_format": ".mkv" if lossless else None,
            "animal": animal,
            "animal_scale": animal_scale,
            "animals": animals,
            "coat_mix": coat_mix,
            "animal_scales": _scales(animal_scales) if animal_scales is not None else None,
            "arena_size": _parse_size(arena_size) if arena_size is not None else None,
            "wall_height": wall_height,
            "grayscale": True if grayscale else None,
            "lens": lens,
            "layout": layout,
            "reflections": reflections,
            "walls": walls,
            "rest_fraction": rest_fraction,
            "floor": floor,
            "label_files": _formats(label_files) if label_files is not None else None,
            "label_noise_px": label_noise,
            "randomize": True if randomize else None,
        }
        changes: dict[str, Any] = {k: v for k, v in given.items() if v is not None}
        if board_file is not None:
            from freipose.calibration.board_files import load_board

            changes["board"] = load_board(board_file).to_dict()
        cfg = SceneConfig.from_dict({**base.to_dict(), **changes})
        paths = generate_session(outdir, cfg, workers=workers, overwrite=overwrite)
        click.echo(_summary(paths))


def _summary(paths: Any) -> str:
    """What ``generate_session`` wrote (its ``SessionPaths``), in one line."""
    return (
        f"wrote {len(paths.videos)} videos, {paths.calibration.name}, {paths.labels.name}"
        + (f", {paths.truth.name}" if paths.truth is not None else "")
        + (f", {paths.events.name}" if paths.events else "")
        + (f", {len(paths.label_files)} label files" if paths.label_files else "")
        + (f", calibration/ ({len(paths.calibration_videos)} board videos)"
           if paths.calibration_videos else "")
        + f" to {paths.folder}"
    )  # fmt: skip

"""``freipose predict``: synchronized videos -> 3D poses in ``<session>.poses.h5``."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import click

from freipose.cli._cluster import cluster_config, cluster_options
from freipose.cli._common import (
    calibration_option,
    camera_map_from,
    camera_map_option,
    detection_options,
    detector_spec,
    device_option,
    echo_result,
    frames_option,
    inference_options,
    inference_overrides,
    user_errors,
)
from freipose.cli._threads import threads_option, use_threads
from freipose.errors import FreiPoseError


@click.command()
@click.argument("sessions", nargs=-1, required=True, type=click.Path(exists=True, path_type=Path))
@click.option(
    "--model",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    required=True,
    help="Pose network checkpoint (model.pt from `freipose train`).",
)
@click.option(
    "-o",
    "--outdir",
    type=click.Path(file_okay=False, path_type=Path),
    required=True,
    help="Output folder; each session gives OUTDIR/<session>.poses.h5.",
)
@calibration_option()
@camera_map_option()
@detection_options
@frames_option()
@click.option("--batch", type=int, default=8, show_default=True, help="Time steps per batch.")
@device_option()
@click.option(
    "--refine/--no-refine",
    default=True,
    show_default=True,
    help="Report the refined pose (P1) or the 3D network's initial pose (P0).",
)
@inference_options
@click.option(
    "--backend",
    type=click.Choice(["auto", "optimized", "eager", "bf16"]),
    default="auto",
    show_default=True,
    help="How the network runs: optimized (auto; channels-last layout and a gathered "
    "unprojection, the eager poses within fp32 rounding), eager (the reference) or bf16 "
    "(optimized in bfloat16, for CPUs with AVX-512-BF16 or AMX and GPUs of compute "
    "capability 8.0 or newer; poses a median 0.25 mm from fp32, see docs/explanation/"
    "backends.md).",
)
@click.option(
    "--shard",
    help="I/N: process only the I-th (0-based) of N contiguous parts of the frames; join the "
    "parts with `freipose merge`.",
)
@click.option(
    "--skeleton",
    help="Expected skeleton (name or TOML); fail early if the model predicts other keypoints.",
)
@click.option(
    "--smooth",
    is_flag=True,
    help="Also smooth each session's poses over time (as `freipose smooth`) into "
    "OUTDIR/smoothed/<session>.poses.h5.",
)
@click.option(
    "--animals",
    type=click.IntRange(min=1),
    default=1,
    show_default=True,
    help="Animals in each session. 2 or more: every animal is found in every view (--method "
    "bgsub or --detector), followed over the whole recording (a first, cheap pass over the "
    "frames that a resumed run repeats), and the network predicts each one's cube; the poses "
    "file has an animal axis (individuals animal_0, animal_1, ..., identity confidence and "
    "flags; --smooth smooths each animal on its own). Not with --shard or --executor.",
)
@click.option("--overwrite", is_flag=True, help="Redo outputs that exist and are complete.")
@cluster_options
@threads_option()
@click.pass_context
def predict(
    ctx: click.Context,
    sessions: tuple[Path, ...],
    model: Path,
    outdir: Path,
    calibration: Path | None,
    camera_map: tuple[str, ...],
    detector: Path | None,
    method: str | None,
    fixed_boxes: Path | None,
    min_views: int,
    bg_samples: int,
    frames: str | None,
    batch: int,
    device: str,
    refine: bool,
    fusion_reject: float | None,
    map_window: int | None,
    backend: str,
    shard: str | None,
    skeleton: str | None,
    smooth: bool,
    animals: int,
    overwrite: bool,
    executor: str | None,
    cluster_file: Path | None,
    chunk_frames: int | None,
    parallel: int | None,
    max_retries: int | None,
    threads: int | None,
) -> None:
    """Predict 3D poses from synchronized videos of one or more sessions.

    A SESSION is a folder with one video per camera (file stem = camera name in the
    calibration), or the video files of one session. Every input is checked before any
    work starts. Outputs are written in chunks: a killed run started again with the same
    command continues where it stopped, and finished outputs are skipped (--overwrite
    redoes them). Frames where the animal is not found hold NaN with confidence 0.

    With --executor (or --cluster FILE) every session is cut into units of --chunk-frames
    frames that run in worker processes (local) or as a SLURM job array (slurm); a unit
    that fails is submitted again (--max-retries), and each session's units are joined
    into OUTDIR/<session>.poses.h5 as soon as all are complete. `freipose jobs OUTDIR`
    shows the units; running the same command again submits only what is missing.

    \b
    Examples:
      freipose predict rec1/ rec2/ --model runs/small/model.pt \\
          --detector runs/det/detector.pt -o poses/
      freipose predict rec1/ --model model.pt --method bgsub --frames 0:3000 -o poses/
      # a study on a SLURM cluster: settings in cluster.toml ([cluster] table)
      freipose predict study/*/ --model model.pt --detector det.pt -o poses/ \\
          --cluster cluster.toml
      freipose jobs poses/
      freipose predict rec1/ --model model.pt --detector det.pt -o poses/ --smooth
      # two animals: found by background subtraction, followed, a pose per animal
      freipose predict pair/ --model model.pt --method bgsub --animals 2 -o poses/
    """  # noqa: D301 - click needs the \b (backspace) paragraph marker
    with user_errors():
        from freipose.io.checkpoints import DETECTOR, POSE_NETWORK, check_checkpoints
        from freipose.io.session import discover_sessions
        from freipose.predict.network import predict_sessions
        from freipose.predict.run import parse_shard
        from freipose.skeleton import load_skeleton

        quiet = bool(ctx.obj and ctx.obj.get("quiet"))
        config = cluster_config(executor, cluster_file, chunk_frames, parallel, max_retries,
                                cpus=threads)  # fmt: skip
        shard_t = _check_options(batch, parse_shard(shard), smooth, config is not None)
        _check_animals(animals, shard_t, config is not None)
        spec = detector_spec(detector, method, fixed_boxes, bg_samples, min_views)
        overrides = inference_overrides(fusion_reject, map_window)
        expected = load_skeleton(skeleton) if skeleton else None
        use_threads(threads)
        check_checkpoints(("--model", model, POSE_NETWORK), ("--detector", detector, DETECTOR))
        found = discover_sessions(sessions, calibration, camera_map=camera_map_from(camera_map))
        _say_calibrations(found, calibration is not None, quiet)
        if smooth:
            _refuse_stale_smoothed(outdir, [s.name for s in found], overwrite)
        if animals > 1:
            done = _predict_animals(found, model, spec, outdir, animals, frames, batch,
                                    device, refine, overrides, backend, overwrite, expected,
                                    quiet)  # fmt: skip
            if smooth:
                _smooth_results(done, outdir, overwrite)
            return
        if config is not None:
            paths = _predict_units(found, model, spec, outdir, frames, batch, device, refine,
                                   overrides, expected, config, overwrite, quiet)  # fmt: skip
            if smooth:
                _smooth_results([_Done(p) for p in paths], outdir, overwrite)
            return
        results = predict_sessions(
            found, model, spec, outdir, frames=frames, batch_size=batch, device=device,
            refine=refine, overrides=overrides, backend=backend, shard=shard_t,
            overwrite=overwrite, expected_skeleton=expected, progress=not quiet,
            report=echo_result,
        )  # fmt: skip
        if smooth:
            _smooth_results(results, outdir, overwrite)


def _check_options(
    batch: int, shard: tuple[int, int] | None, smooth: bool, units: bool
) -> tuple[int, int] | None:
    """Refuse options that do not go together; returns the shard.

    Raises:
        FreiPoseError: a batch below 1, --smooth with --shard, --shard with --executor.
    """
    if batch < 1:
        raise FreiPoseError(f"--batch must be at least 1, got {batch}")
    if smooth and shard is not None:
        raise FreiPoseError(
            "--smooth needs the whole recording, not one shard: run `freipose merge` "
            "and then `freipose smooth OUTDIR/<session>.poses.h5 -o OUTDIR/smoothed`"
        )
    if units and shard is not None:
        raise FreiPoseError(
            "--shard is what --executor does for you (one unit per chunk of frames): "
            "give one or the other"
        )
    return shard


def _check_animals(animals: int, shard: tuple[int, int] | None, units: bool) -> None:
    """Refuse options that several animals do not take.

    Raises:
        FreiPoseError: --animals 2+ with --shard or --executor.
    """
    if animals < 2:
        return
    whole = "who is who is followed over the whole recording in one run"
    refused = (
        ("--shard", shard is not None, whole),
        ("--executor/--cluster", units, whole),
    )
    for name, on, why in refused:
        if on:
            raise FreiPoseError(f"--animals {animals} does not go with {name}: {why}; leave it out")


def _predict_animals(
    found: list, model: Path, spec: Any, outdir: Path, animals: int, frames: str | None,
    batch: int, device: str, refine: bool, overrides: Any, backend: str, overwrite: bool,
    expected: Any, quiet: bool,
) -> list:  # fmt: skip
    """``--animals N``: track every session's animals, then predict each one's poses."""
    from freipose.predict.animals_run import predict_animal_sessions

    return predict_animal_sessions(
        found, model, spec, outdir, animals, frames=frames, batch_size=batch, device=device,
        refine=refine, overrides=overrides, backend=backend, overwrite=overwrite,
        expected_skeleton=expected, progress=not quiet, report=echo_result,
    )  # fmt: skip


@dataclass(frozen=True)
class _Done:
    """A joined poses file, as ``_smooth_results`` takes it."""

    path: Path
    skipped: bool = False


def _predict_units(
    found: list, model: Path, spec: Any, outdir: Path, frames: str | None, batch: int,
    device: str, refine: bool, overrides: Any, expected: Any, config: Any, overwrite: bool,
    quiet: bool,
) -> tuple[Path, ...]:  # fmt: skip
    """Predict through the executor ``config`` names; returns the joined poses files."""
    from freipose.cluster.predict import PredictTask, run_predict

    task = PredictTask(
        tuple(found), model, spec, outdir, frames, batch, device, refine, overrides,
        config.chunk_frames, config.cpus, expected,
    )  # fmt: skip
    result = run_predict(task, config, progress=not quiet, overwrite=overwrite,
                         say=(lambda m: None) if quiet else click.echo)  # fmt: skip
    for p in result.joined:
        click.echo(f"wrote {p}")
    r = result.report
    click.echo(f"{len(r.done)} units done ({r.submitted} jobs submitted in this run), "
               f"{result.frames} frames, {r.seconds:.1f} s")  # fmt: skip
    return result.joined


def _say_calibrations(found: list, explicit: bool, quiet: bool) -> None:
    """Say which calibration each session uses and where it came from; warn on a true rig."""
    import logging

    from freipose.io.session import TRUE_CALIBRATION_NAME

    for s in found:
        origin = "given with --calibration" if explicit else "found in the session folder"
        if not quiet:
            click.echo(f"{s.name}: calibration {s.calibration_path} ({origin})")
        if not explicit and s.calibration_path.name == TRUE_CALIBRATION_NAME:
            logging.getLogger(__name__).warning(
                "%s: %s is the true rig of a synthetic session (freipose synth), in the "
                "generator's world frame, not a calibration made from board videos; pass "
                "--calibration FILE to predict with your calibration",
                s.name,
                s.calibration_path,
            )


def _refuse_stale_smoothed(outdir: Path, names: list[str], overwrite: bool) -> None:
    """Refuse, before predicting, a smoothed output whose poses file is to be made anew.

    Raises:
        OutputExistsError: ``OUTDIR/smoothed/<name>.poses.h5`` exists, the poses file does
            not, and ``overwrite`` is false.
    """
    from freipose.io.atomic import refuse_existing

    for name in names:
        if not (outdir / f"{name}.poses.h5").exists():
            refuse_existing(outdir / "smoothed" / f"{name}.poses.h5", overwrite)


def _smooth_results(results: list, outdir: Path, overwrite: bool) -> None:
    """Smooth every finished poses file; a kept prediction keeps its smoothed file."""
    from freipose.predict.smooth import smooth_file

    for r in results:
        out = outdir / "smoothed" / r.path.name
        if r.skipped and out.exists() and not overwrite:
            click.echo(f"kept {out} (--overwrite redoes it)")
            continue
        click.echo(f"wrote {smooth_file(r.path, out, overwrite=overwrite or not r.skipped)}")

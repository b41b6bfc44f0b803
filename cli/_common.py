"""Shared helpers for CLI commands: library errors as ClickExceptions, common options."""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import click

from freipose.errors import FreiPoseError, filesystem_message


@contextlib.contextmanager
def user_errors(*extra: type[BaseException]) -> Iterator[None]:
    """Turn the errors a user can fix into ``click.ClickException`` (one message, no traceback).

    Library code raises a :class:`~freipose.errors.FreiPoseError` (and subclasses such as
    the format errors) with a message that says what was expected, what was found and how
    to fix it. Exactly those, the ``extra`` types a command names, and an ``OSError`` of a
    full disk, a read-only folder or a denied access (the message of
    :func:`~freipose.errors.filesystem_message`: the path and what to do) become messages;
    any other exception is a bug and keeps its traceback.

    Args:
        extra: further exception types that this command shows as messages.
    """
    try:
        yield
    except click.ClickException:
        raise
    except (FreiPoseError, *extra) as exc:
        msg = exc.args[0] if isinstance(exc, KeyError) and exc.args else str(exc)
        raise click.ClickException(str(msg)) from exc
    except OSError as exc:
        fs_msg = filesystem_message(exc)
        if fs_msg is None:
            raise
        raise click.ClickException(fs_msg) from exc


Decorator = Callable[[Any], Any]

FRAMES_HELP = "Frame range START:STOP (Python slice, e.g. 0:1000) [default: all]."
SESSION_CALIBRATION_HELP = (
    "Calibration for every session [default: calibration.toml in each session folder]."
)


def device_option(default: str = "auto") -> Decorator:
    """``--device``: ``auto`` also picks CUDA when there is one (commands that allow it)."""
    choices = "cpu, cuda, cuda:N or auto." if default == "auto" else "cpu, cuda or cuda:N."
    return click.option("--device", default=default, show_default=True, help=choices)


def frames_option(help: str = FRAMES_HELP) -> Decorator:
    """``--frames START:STOP`` (parsed by :func:`freipose.io.video.frame_range`)."""
    return click.option("--frames", help=help)


def calibration_option(help: str = SESSION_CALIBRATION_HELP) -> Decorator:
    """``--calibration FILE`` (an existing file)."""
    return click.option(
        "--calibration", type=click.Path(exists=True, dir_okay=False, path_type=Path), help=help
    )


def camera_map_option() -> Decorator:
    """``--camera-map VIDEO_STEM=CAMERA`` (repeatable): videos not named after their cameras."""
    return click.option(
        "--camera-map",
        "camera_map",
        multiple=True,
        metavar="VIDEO_STEM=CAMERA",
        help="Camera of a video whose file stem is not the calibration's camera name "
        "(e.g. --camera-map min_session_back=back); repeat per video.",
    )


def camera_map_from(items: tuple[str, ...]) -> dict[str, str]:
    """The parsed ``--camera-map`` values: video stem -> camera name."""
    from freipose.labels.mapping import parse_map_options

    return parse_map_options(items, "--camera-map")


def detection_options(f: Any) -> Any:
    """The options that say how to find the animal (``predict``, ``labels select``)."""
    opts = [
        click.option(
            "--detector",
            type=click.Path(exists=True, dir_okay=False, path_type=Path),
            help="Box detector checkpoint (from `freipose train CONFIG --stage detector`).",
        ),
        click.option(
            "--method",
            type=click.Choice(["detector", "bgsub", "fixed", "auto"]),
            help="How to find the animal [default: detector with --detector, fixed with "
            "--fixed-boxes, else auto]; bgsub = background subtraction (static cameras, one "
            "animal); auto = the first of detector, bgsub and fixed boxes from the model's "
            "training labels that finds the animal in sampled frames (said in the log).",
        ),
        click.option(
            "--fixed-boxes",
            type=click.Path(exists=True, dir_okay=False, path_type=Path),
            help="TOML with a [boxes] table: camera = [x0, y0, x1, y1] (for --method fixed).",
        ),
        click.option(
            "--min-views", type=int, default=2, show_default=True, help="Fewest agreeing views."
        ),
        click.option(
            "--bg-samples",
            type=int,
            default=40,
            show_default=True,
            help="Frames for the bgsub background.",
        ),
    ]
    return _with_options(f, opts)


def _with_options(f: Any, opts: list[Decorator]) -> Any:
    """``f`` with the click options ``opts``, listed in ``--help`` in this order."""
    for opt in reversed(opts):
        f = opt(f)
    return f


def detector_spec(
    detector: Path | None,
    method: str | None,
    fixed_boxes: Path | None,
    bg_samples: int,
    min_views: int,
) -> Any:
    """The :class:`~freipose.predict.network.DetectorSpec` of :func:`detection_options`."""
    from freipose.predict.network import DetectorSpec

    if method is None:
        if detector is not None and fixed_boxes is not None:
            raise FreiPoseError("give either --detector or --fixed-boxes, not both")
        method = "detector" if detector else "fixed" if fixed_boxes is not None else "auto"
    return DetectorSpec(method, detector, fixed_boxes, bg_samples, min_views)


def inference_options(f: Any) -> Any:
    """The inference-only network settings one run may change (``eval``, ``predict``)."""
    opts = [
        click.option(
            "--fusion-reject",
            type=float,
            metavar="VOXELS",
            help="The voxel network's P1 leaves out the views whose refined point lies "
            "farther than this from the first fusion (0: every view) [default: the "
            "checkpoint's model.fusion_reject]. Compare both on your held-out labels.",
        ),
        click.option(
            "--map-window",
            type=int,
            metavar="PIXELS",
            help="The 2D points of the refinement and of the baseline are the soft-argmax "
            "within this many map pixels of each map's peak (0: the whole map, which can help "
            "a network trained for few steps whose peaks are off) [default: the checkpoint's "
            "model.map_window].",
        ),
    ]
    return _with_options(f, opts)


def inference_overrides(fusion_reject: float | None, map_window: int | None) -> Any:
    """The :class:`~freipose.nn.config.InferenceOverrides` of :func:`inference_options`."""
    from freipose.nn.config import InferenceOverrides

    return InferenceOverrides(fusion_reject=fusion_reject, map_window=map_window)


def echo_result(res: Any) -> None:
    """Report one session's prediction result (a ``predict_sessions`` report callback)."""
    if res.skipped:
        click.echo(f"{res.path}: complete, skipped (use --overwrite to redo it)")
        return
    fps = res.frames / res.seconds if res.seconds > 0 else float("nan")
    counts = ", ".join(f"{v} {k}" for k, v in res.status_counts.items() if v)
    click.echo(
        f"{res.path}: {counts} ({res.frames} frames in {res.seconds:.1f} s, {fps:.1f} frames/s)"
    )
    for cam, i in res.missing.items():
        click.echo(
            f"  warning: camera {cam}: frames from {i} on could not be decoded (truncated video?)",
            err=True,
        )


def allow_incomplete_option() -> Decorator:
    """``--allow-incomplete``: use a poses file whose prediction run has not finished."""
    return click.option(
        "--allow-incomplete",
        is_flag=True,
        help="Use a poses file whose prediction has not finished (missing frames are empty).",
    )


def overwrite_option(what: str = "the output") -> Decorator:
    """``--overwrite``: replace an existing complete output."""
    return click.option("--overwrite", is_flag=True, help=f"Replace {what} if it exists.")


def check_complete(path: Path, allow_incomplete: bool) -> None:
    """Refuse an unfinished poses file, or warn how many frames it lacks when allowed.

    Raises:
        IncompletePosesError: the file is unfinished and ``allow_incomplete`` is false.
    """
    from freipose.io.poses import require_complete

    missing = require_complete(path, allow_incomplete)
    if missing:
        click.echo(
            f"warning: {path} is incomplete: {missing} frames have no prediction "
            "(empty in the output)",
            err=True,
        )

"""``freipose calib run`` (calibrate cameras from board videos) and ``freipose calib board``."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from freipose.cli._common import user_errors
from freipose.cli.calib_files import FORMATS_HELP
from freipose.cli.calib_up import parse_up
from freipose.errors import FreiPoseError, InputFileError

if TYPE_CHECKING:  # the calibration package is imported when a command runs
    from freipose.calibration.boards import Board

BOARD_OPTIONS = (
    click.option(
        "--board",
        "board_file",
        type=click.Path(dir_okay=False, path_type=Path),
        help="Board file (TOML or JSON, lengths in mm; FreiCalib marker JSON works).",
    ),
    click.option(
        "--board-type",
        type=click.Choice(["charuco", "chessboard", "aprilgrid"]),
        help="Board type when the board is given by options instead of a file.",
    ),
    click.option("--squares-x", type=int, help="ChArUco: squares along x."),
    click.option("--squares-y", type=int, help="ChArUco: squares along y."),
    click.option("--square-size", type=float, help="ChArUco/chessboard: square side (mm)."),
    click.option("--marker-size", type=float, help="ChArUco: marker side (mm)."),
    click.option("--dictionary", help="ChArUco: OpenCV dictionary, e.g. DICT_4X4_50."),
    click.option(
        "--legacy-pattern/--no-legacy-pattern",
        default=None,
        help="ChArUco: board printed by OpenCV < 4.6 or aniposelib.",
    ),
    click.option("--inner-corners-x", type=int, help="Chessboard: inner corners along x."),
    click.option("--inner-corners-y", type=int, help="Chessboard: inner corners along y."),
    click.option("--tags-x", type=int, help="AprilGrid: tags along x."),
    click.option("--tags-y", type=int, help="AprilGrid: tags along y."),
    click.option("--tag-size", type=float, help="AprilGrid: tag side (mm)."),
    click.option("--tag-spacing", type=float, help="AprilGrid: gap as a fraction of the tag size."),
    click.option("--family", help="AprilGrid: tag family (36h11, 16h5, ...)."),
)

_FIELD_OPTIONS = (
    "squares_x",
    "squares_y",
    "square_size",
    "marker_size",
    "dictionary",
    "legacy_pattern",
    "inner_corners_x",
    "inner_corners_y",
    "tags_x",
    "tags_y",
    "tag_size",
    "tag_spacing",
    "family",
)


def _board_options(f: Callable[..., Any], with_file: bool = True) -> Callable[..., Any]:
    for opt in reversed(BOARD_OPTIONS if with_file else BOARD_OPTIONS[1:]):
        f = opt(f)
    return f


def _board_field_options(f: Callable[..., Any]) -> Callable[..., Any]:
    return _board_options(f, with_file=False)


def _resolve_board(board_file: Path | None, board_type: str | None, kw: dict[str, Any]) -> Board:
    """Board from a file, overridden or completed by command-line fields."""
    from freipose.calibration.board_files import board_from_dict, load_board
    from freipose.calibration.boards import BoardError

    fields = {k: kw[k] for k in _FIELD_OPTIONS if kw.get(k) is not None}
    if board_file is None and board_type is None and not fields:
        raise BoardError(
            "no board given: pass --board BOARD_FILE (see examples/board.toml) or the board "
            "fields as options, e.g. --board-type charuco --squares-x 7 --squares-y 5 "
            "--square-size 40 --marker-size 30 --dictionary DICT_4X4_50"
        )
    if board_file is not None:
        base = load_board(board_file).to_dict()
        if board_type is not None and board_type != base["type"]:
            raise BoardError(
                f"--board-type {board_type} contradicts {board_file} (type {base['type']})"
            )
        base.update(fields)
        return board_from_dict(base, source=f"{board_file} with command-line fields")
    if board_type is None:
        raise BoardError("board fields given without --board-type (charuco, chessboard, aprilgrid)")
    return board_from_dict({"type": board_type, **fields}, source="command-line board options")


# An existing output larger than this is no calibration file (those are a few kB): it is
# not read to find out.
_MAX_CALIBRATION_BYTES = 16 << 20


def _suffix_text(writers: Sequence[str], suffixes: dict[str, str]) -> str:
    """``.toml (toml), .json (mjson), ...``: the suffixes that name a writable format."""
    by_format: dict[str, list[str]] = {f: [] for f in writers}
    for sfx, f in suffixes.items():
        if sfx != "/" and f in by_format:
            by_format[f].append(sfx)
    return ", ".join(f"{' or '.join(s)} ({f})" for f, s in by_format.items() if s)


def output_format(output: Path, fmt: str | None) -> str:
    """The format that ``-o OUTPUT`` is written in: ``--format``, else from the suffix.

    Raises:
        FreiPoseError: ``fmt`` is no format that FreiPose writes, or it is ``None`` and the
            suffix names none (the message lists the suffixes and ``--format``'s names).
    """
    from freipose.io.calibration import SUFFIXES, WRITERS, CalibrationFormatError, detect_format

    names = ", ".join(sorted(WRITERS))
    if fmt is not None:
        if fmt not in WRITERS:
            raise FreiPoseError(
                f"--format {fmt}: not a calibration format that FreiPose writes; expected one "
                f"of {names}"
            )
        return fmt
    fix = f"rename it (e.g. -o {output.with_suffix('.toml')}) or pass --format, one of {names}"
    expected = f"expected {_suffix_text(list(WRITERS), dict(SUFFIXES))}"
    try:
        found = detect_format(output)
    except CalibrationFormatError:
        sfx = repr(output.suffix) if output.suffix else "(none)"
        raise FreiPoseError(
            f"cannot tell the calibration format of -o {output} from its suffix {sfx}: "
            f"{expected}; {fix}"
        ) from None
    if found not in WRITERS:
        raise FreiPoseError(
            f"-o {output}: {output.suffix!r} is the {found} format, which FreiPose reads but "
            f"does not write; {expected}; {fix}"
        )
    return found


def _writable_folder(folder: Path, what: str) -> None:
    """Raise unless ``folder`` exists or can be made.

    It can be made when its nearest existing ancestor is a folder this process may write in.
    """
    p = folder.absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    if not p.is_dir():
        raise FreiPoseError(
            f"{what}: {p} is a file, not a folder, so {folder} cannot be made; choose a path "
            f"in a folder"
        )
    if not os.access(p, os.W_OK | os.X_OK):
        raise FreiPoseError(f"{what}: no permission to write in {p}; choose another folder")


def _check_replaceable(output: Path, fmt: str) -> None:
    """Raise if the existing file ``output`` is not a calibration (it would be replaced)."""
    from freipose.io.calibration import READERS, detect_format, load_calibration

    size = output.stat().st_size
    why = f"{size} bytes, more than any calibration file"
    if size <= _MAX_CALIBRATION_BYTES:
        formats = [fmt] if fmt in READERS else []
        with contextlib.suppress(FreiPoseError):
            formats.append(detect_format(output))
        for f in dict.fromkeys(formats):
            try:
                load_calibration(output, f)
                return
            except (ValueError, OSError, KeyError) as e:  # FreiPoseError is a ValueError
                why = str(e)
    raise FreiPoseError(
        f"-o {output} exists and is not a calibration file ({why}); it would be replaced: "
        f"choose another output name, or delete it first if it may go"
    )


def _check_jarvis_output(output: Path, cameras: Sequence[str]) -> None:
    """Raise if the JARVIS writer would refuse ``output`` for a rig of ``cameras``."""
    if output.suffix.lower() in (".yaml", ".yml") and not output.is_dir():
        if len(cameras) != 1:
            raise FreiPoseError(
                f"-o {output}: a JARVIS .yaml file holds one camera, the rig has "
                f"{len(cameras)}; give a folder instead, e.g. -o {output.with_suffix('')}/"
            )
        if output.exists():
            _check_replaceable(output, "jarvis")
        return
    if output.is_file():
        raise FreiPoseError(
            f"-o {output} is a file; a JARVIS calibration is a folder of <camera>.yaml: give "
            f"a folder name, e.g. -o {output.with_suffix('')}_jarvis/"
        )
    if output.is_dir():
        others = sorted(
            p.name
            for p in output.iterdir()
            if p.suffix.lower() in (".yaml", ".yml")
            and not p.name.startswith(".")
            and p.stem not in cameras
        )
        if others:
            raise FreiPoseError(
                f"-o {output}: the folder already holds camera files {others} that are not in "
                f"this rig ({', '.join(cameras)}); they would be read as extra cameras. Write "
                f"to an empty folder"
            )


def check_outputs(
    output: Path, fmt: str | None, report_dir: Path | None, cameras: Sequence[str]
) -> str:
    """Check every output of ``freipose calib run`` before any work; return the format.

    Args:
        output: ``-o``, the calibration file (a folder for ``jarvis``).
        fmt: ``--format``; ``None``: from ``output``'s suffix.
        report_dir: ``--report``; ``None``: no report.
        cameras: the camera names (the inputs' stems).

    Returns:
        the calibration format that ``output`` is written in.

    Raises:
        FreiPoseError: an output that could not be written, or an existing ``output`` that
            is not a calibration.
    """
    from freipose.calibration.pipeline import detection_cache_dir

    if fmt is None and output.is_dir():
        raise FreiPoseError(
            f"-o {output} is a folder; expected a calibration file name, e.g. -o "
            f"{output / 'calibration.toml'}, or --format jarvis to write a JARVIS folder of "
            f"<camera>.yaml into it"
        )
    f = output_format(output, fmt)
    if f == "jarvis":
        _check_jarvis_output(output, cameras)
    elif output.is_dir():
        raise FreiPoseError(
            f"-o {output} is a folder; a {f} calibration is one file: give a file name, e.g. "
            f"-o {output / 'calibration.toml'}"
        )
    elif output.exists():
        _check_replaceable(output, f)
    _writable_folder(output.parent, f"-o {output}")
    cache = detection_cache_dir(output)
    if cache.exists() and not cache.is_dir():
        raise FreiPoseError(
            f"{cache} (the detection cache of -o {output}) is a file, not a folder; move it "
            f"away or choose another output name"
        )
    if report_dir is not None:
        _writable_folder(report_dir, f"--report {report_dir}")
    return f


def _camera_line(result: Any, s: Any, back: int) -> str:
    """One line for a calibrated camera: its board views, error, intrinsics and lens model."""
    rms = f"{s.rms:.3f} px" if s.rms == s.rms else "n/a"
    behind = f" ({back} seen from behind)" if back else ""
    line = (
        f"{s.name}: {s.frames_detected} frames with the board{behind}, {s.points_used} points "
        f"used, reprojection RMS {rms}"
    )
    if s.name not in result.rig or "intrinsics_model" not in result.rig.metadata:
        return line
    K = result.rig[s.name].K
    model = result.rig.metadata["intrinsics_model"].get(s.name, {})
    se = result.standard_errors.get(s.name) or {}

    def pm(key: str) -> str:
        return f" ± {se[key]:.2g}" if key in se else ""

    focal = f"f {K[0, 0]:.1f}{pm('fx')} px"
    if model.get("focal") == "fx, fy":
        focal = f"fx {K[0, 0]:.1f}{pm('fx')}, fy {K[1, 1]:.1f}{pm('fy')} px"
    centre = f"principal point ({K[0, 2]:.1f}{pm('cx')}, {K[1, 2]:.1f}{pm('cy')}) px"
    if model.get("principal_point") == "image centre":
        centre = "principal point at the image centre"
    dist = model.get("distortion", "")
    return f"{line}; {focal}, {centre}, distortion {dist or 'none'}"


def _echo_result(result: Any, output: Path) -> None:
    """Print one line per camera, the warnings and findings of a calibration.

    The intrinsics' standard errors in full are a debug message (``-v``).
    """
    import logging

    log = logging.getLogger("freipose.calib")
    back = {d.name: d.back_views for d in result.detections}
    for s in result.stats:
        click.echo(_camera_line(result, s, back.get(s.name, 0)))
    for w in result.warnings:
        log.warning(w)
    for name, se in result.standard_errors.items():
        if se:
            parts = ", ".join(f"{k} {v:.3g}" for k, v in se.items())
            log.debug("%s: intrinsics standard errors %s", name, parts)
    click.echo(f"world frame: {result.world}")
    for f in result.findings:
        click.echo(f"SUSPECT (written with --force): {f.message}", err=True)
    click.echo(f"wrote {output}" + (" (marked as suspect)" if result.findings else ""))


def _check_exclusive(
    origin_frame: int | None,
    up: tuple[float, float, float] | None,
    fix_intrinsics: Path | None,
    intrinsics_from: Path | None,
) -> None:
    """Refuse options that give the same thing twice (the up; the intrinsics)."""
    if origin_frame is not None and up is not None:
        raise FreiPoseError(
            "--origin-frame and --up both set the up direction (the board on the floor has "
            "z up): pass one"
        )
    if fix_intrinsics is not None and intrinsics_from is not None:
        raise FreiPoseError(
            "--fix-intrinsics and --intrinsics-from both give the intrinsics: pass one"
        )


@click.command("run")
@click.argument("inputs", nargs=-1, type=click.Path(path_type=Path))
@_board_options
@click.option(
    "-o",
    "--output",
    type=click.Path(path_type=Path),
    required=True,
    help="Output calibration file (calibration.toml), or folder with --format jarvis.",
)
@click.option(
    "--format",
    "fmt",
    default=None,
    metavar="F",
    help="Format of OUTPUT, whatever its name (default: from its suffix: .toml native, "
    f".json M.json, .yaml/.yml JARVIS). A writable one of: {FORMATS_HELP}.",
)
@click.option(
    "--origin-frame",
    type=int,
    default=None,
    help="Frame whose board pose defines the world (board on the floor, z up).",
)
@click.option(
    "--up",
    "up",
    default=None,
    metavar="X,Y,Z",
    callback=lambda _ctx, _param, v: None if v is None else parse_up(v),
    help="The world's up direction in the first camera's frame, stored with the calibration "
    "(without --origin-frame, whose world has z up). Without either, the up direction is "
    "unknown: set it later with freipose calib up.",
)
@click.option("--intrinsics-only", is_flag=True, help="Calibrate intrinsics only.")
@click.option(
    "--fix-intrinsics",
    type=click.Path(dir_okay=False, path_type=Path),
    help="Calibration file with known intrinsics, kept fixed (cameras matched by name).",
)
@click.option(
    "--intrinsics-from",
    type=click.Path(exists=True, path_type=Path),
    help="Intrinsics from a separate recording, kept fixed: a calibration file (cameras "
    "matched by name), or a folder with one board video or image folder per camera, named "
    "after it (their intrinsics are calibrated first, with the same board).",
)
@click.option(
    "--force",
    is_flag=True,
    help="Write the calibration even when it fails the plausibility checks; it is then "
    "marked as suspect in its metadata and the report.",
)
@click.option(
    "--report",
    "report_dir",
    type=click.Path(file_okay=False, path_type=Path),
    help="Write summary.json and figures to this folder.",
)
@click.option(
    "--dist-model",
    type=click.Choice(["auto", "none", "k1", "k1k2", "k1k2p", "full"]),
    default="auto",
    show_default=True,
    help="Distortion coefficients to estimate: auto = k1 k2, plus p1 p2 where they are "
    "significant; k1k2p = k1 k2 p1 p2; full adds k3.",
)
@click.option(
    "--principal-point",
    type=click.Choice(["auto", "free", "centre"]),
    default="auto",
    show_default=True,
    help="auto: the image centre unless the data show a significant offset; free: always "
    "estimated; centre: fixed at the image centre.",
)
@click.option(
    "--aspect",
    type=click.Choice(["auto", "free", "square"]),
    default="auto",
    show_default=True,
    help="auto: fy = fx (square pixels) unless the data show a significant difference; free: "
    "fx and fy estimated separately; square: always fy = fx.",
)
@click.option(
    "--refine-board/--no-refine-board",
    default=True,
    show_default=True,
    help="Correct the position in the board plane of each board point seen in at least 100 "
    "views (print errors, per-corner detector bias).",
)
@click.option(
    "--view-weights/--no-view-weights",
    default=True,
    show_default=True,
    help="Weight each board view's detections by its own noise level (blurred or steep views "
    "count less).",
)
@click.option(
    "--jobs",
    "-j",
    type=int,
    default=None,
    help="Detection processes, and threads that initialise the cameras (default: CPUs).",
)
@click.option("--no-cache", is_flag=True, help="Re-detect even if cached detections exist.")
def run(
    inputs: tuple[Path, ...],
    board_file: Path | None,
    board_type: str | None,
    output: Path,
    fmt: str | None,
    origin_frame: int | None,
    up: tuple[float, float, float] | None,
    intrinsics_only: bool,
    fix_intrinsics: Path | None,
    intrinsics_from: Path | None,
    force: bool,
    report_dir: Path | None,
    dist_model: str,
    principal_point: str,
    aspect: str,
    refine_board: bool,
    view_weights: bool,
    jobs: int | None,
    no_cache: bool,
    **board_fields: Any,
) -> None:
    """Calibrate synchronized cameras from videos (or image folders) of a moving board.

    Each INPUT is one camera (its name is the file or folder stem); frames are matched by index.
    Detections are cached in OUTPUT's folder as <output stem>.detections/. OUTPUT's format
    comes from its suffix, or from --format (which writes that format under any name). Every
    output is checked before the detection starts; an existing OUTPUT is replaced only if it
    is a calibration.

    After the bundle adjustment the calibration is checked for physical plausibility: each
    camera's field of view (5-170 degrees), principal point (at most 25 % of the image size
    outside it), distortion (must not fold the image where the board was, nor anywhere when
    the board reached the image corners; a fold only beyond the board's farthest corner is a
    warning naming that radius), board poses (as the other cameras'), the rig's error (at most
    twice the camera's own), detections beyond 5 times its own noise and 2 px (at most 30 %),
    focal-length SE (5 %). A failed calibration is not written (nor its report): the message
    names the camera, the numbers and the fix (--fix-intrinsics, --intrinsics-from, ...).
    --force writes it anyway, marked as suspect.

    Inverted boards need `inverted = true` in the board file; boards seen from behind are found
    in the mirror image (each camera's line counts them); a board at rest counts as one view.
    --report writes summary.json, report.txt and per camera the errors and the coverage (image
    cells, distances, floor: a camera whose board never came near the floor is warned about).

    \b
    Example:
      freipose calib cams/cam0.mp4 cams/cam1.mp4 cams/cam2.mp4 --board board.toml \\
          -o calibration.toml --origin-frame 0 --report calib_report/
      freipose calib left/ right/ --board-type chessboard --inner-corners-x 9 \\
          --inner-corners-y 6 --square-size 30 -o stereo.toml
      freipose calib cams/*.mp4 --board board.toml -o calib_jarvis/ --format jarvis
    """  # noqa: D301 - click needs the \b (backspace) paragraph marker
    import shutil
    from dataclasses import replace

    with user_errors():
        from freipose.calibration.options import CalibrationOptions
        from freipose.calibration.pipeline import calibrate, detection_cache_dir
        from freipose.calibration.pipeline import intrinsics_from as intrinsics_from_recording
        from freipose.calibration.report import write_report
        from freipose.io.calibration import load_calibration, save_calibration

        if not inputs:
            raise FreiPoseError(
                "no INPUT given: pass one video file or image folder per camera, e.g. "
                "freipose calib cams/*.mp4 --board board.toml -o calibration.toml"
            )
        for p in inputs:
            if not p.exists():
                raise InputFileError(f"input {p} does not exist (expected a video or folder)")
        cameras = [p.stem if p.is_file() else p.name for p in inputs]
        out_format = check_outputs(output, fmt, report_dir, cameras)
        board = _resolve_board(board_file, board_type, board_fields)
        _check_exclusive(origin_frame, up, fix_intrinsics, intrinsics_from)
        fixed = load_calibration(fix_intrinsics) if fix_intrinsics is not None else None
        if no_cache:
            shutil.rmtree(detection_cache_dir(output), ignore_errors=True)
        opts = CalibrationOptions(
            origin_frame=origin_frame,
            up=up,
            intrinsics_only=intrinsics_only,
            fixed_intrinsics=fixed,
            dist_model=dist_model,
            principal_point=principal_point,
            aspect=aspect,
            refine_board=refine_board,
            view_weights=view_weights,
            jobs=jobs,
            accept_implausible=force,
        )
        if intrinsics_from is not None:
            rig = intrinsics_from_recording(intrinsics_from, cameras, board, opts)
            opts = replace(opts, fixed_intrinsics=rig)
        result = calibrate(list(inputs), board, output, opts, board_file=board_file)
        save_calibration(result.rig, output, out_format)
        _echo_result(result, output)
        if report_dir is not None:
            paths = write_report(result, report_dir)
            click.echo(f"wrote report ({len(paths)} files) to {report_dir}")


@click.command("board")
@click.argument("board_file", required=False, type=click.Path(dir_okay=False, path_type=Path))
@_board_field_options
@click.option(
    "-o",
    "--output",
    type=click.Path(dir_okay=False, path_type=Path),
    required=True,
    help="Image file to write (.png, .tif, ...).",
)
@click.option(
    "--dpi",
    type=float,
    default=300.0,
    show_default=True,
    help="Printer resolution; print at 100 % scale.",
)
def board(
    board_file: Path | None,
    board_type: str | None,
    output: Path,
    dpi: float,
    **board_fields: Any,
) -> None:
    """Render a printable image of a calibration board (print at 100 %, no scaling).

    \b
    Example:
      freipose calib board examples/board.toml -o board.png --dpi 300
    """  # noqa: D301 - click needs the \b (backspace) paragraph marker
    with user_errors():
        import cv2

        from freipose.io.atomic import atomic_path

        b = _resolve_board(board_file, board_type, board_fields)
        if not dpi > 0:
            raise FreiPoseError(f"--dpi must be positive, got {dpi}")
        img = b.texture(dpi / 25.4)
        with atomic_path(output) as tmp:
            params = []
            if output.suffix.lower() == ".png":
                params = [cv2.IMWRITE_PNG_COMPRESSION, 9]
            if not cv2.imwrite(str(tmp), img, params):
                raise FreiPoseError(f"cannot write {output}: use a .png, .tif or .bmp file name")
        w, h = b.size_mm
        click.echo(
            f"wrote {output}: {img.shape[1]}x{img.shape[0]} px = {w:.1f} x {h:.1f} mm at "
            f"{dpi:g} dpi; print at 100 % and measure a square to check"
        )

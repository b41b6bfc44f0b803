"""``freipose calib convert`` and ``freipose calib show``: calibration-file utilities."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import click

from freipose.cli._common import user_errors
from freipose.errors import FreiPoseError

FORMATS_HELP = (
    "toml (native), anipose, mjson (FreiPose/FreiCalib M.json), jarvis (folder of "
    "<camera>.yaml), dannce (label3d .mat, read only)"
)


def _parse_sizes(values: tuple[str, ...]) -> dict[str | None, tuple[int, int]]:
    """``WxH`` (every camera) or ``CAMERA=WxH`` (one camera) -> ``{name or None: (w, h)}``."""
    out: dict[str | None, tuple[int, int]] = {}
    for v in values:
        name, _, size = v.rpartition("=")
        m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", size)
        if not m or int(m.group(1)) <= 0 or int(m.group(2)) <= 0:
            raise click.BadParameter(
                f"expected WIDTHxHEIGHT or CAMERA=WIDTHxHEIGHT (e.g. 1280x1024), got {v!r}",
                param_hint="--size",
            )
        out[name or None] = (int(m.group(1)), int(m.group(2)))
    return out


@click.command()
@click.argument("input_path", metavar="IN", type=click.Path(exists=True, path_type=Path))
@click.argument("output_path", metavar="OUT", type=click.Path(path_type=Path))
@click.option(
    "--format-in",
    "format_in",
    default=None,
    metavar="F",
    help=f"Format of IN (default: from its suffix; a folder is jarvis). One of: {FORMATS_HELP}.",
)
@click.option(
    "--format",
    "format_out",
    default=None,
    metavar="F",
    help="Format of OUT (default: from its suffix). Same names as --format-in.",
)
@click.option(
    "--units",
    type=click.Choice(["mm", "cm", "m"]),
    default="mm",
    show_default=True,
    help="Length unit of the translations in an Anipose file (read or written) that "
    "does not state its units.",
)
@click.option(
    "--size",
    "sizes",
    multiple=True,
    metavar="[CAMERA=]WxH",
    help="Image size for cameras whose file stores none (M.json, JARVIS, DANNCE "
    "without FreiPose extras); WxH sets every camera. Repeatable.",
)
@click.option("--overwrite", is_flag=True, help="Replace OUT if it exists.")
def convert(
    input_path: Path,
    output_path: Path,
    format_in: str | None,
    format_out: str | None,
    units: str,
    sizes: tuple[str, ...],
    overwrite: bool,
) -> None:
    """Convert a calibration between formats (lengths become millimetres on the way).

    Formats are chosen by suffix: .toml native, .json FreiPose M.json, .yaml/.yml or a
    folder JARVIS, .mat DANNCE; use --format/--format-in for anipose or to override.

    \b
    Examples:
      freipose calib convert calibration.toml M.json
      freipose calib convert M.json calibration.toml --size 1280x1024
      freipose calib convert calibration.toml calib_jarvis/ --format jarvis
      freipose calib convert label3d_dannce.mat calibration.toml --size 1152x1024
      freipose calib convert anipose/calibration.toml calibration.toml --format-in anipose --units m
    """  # noqa: D301 - click needs the \b (backspace) paragraph marker
    size_map = _parse_sizes(sizes)
    with user_errors():
        from freipose.io import calibration as cal
        from freipose.io import calibration_formats as cf

        if output_path.exists() and output_path.resolve() == input_path.resolve():
            raise FreiPoseError(f"OUT is the same as IN ({input_path}); choose another output path")
        if output_path.exists() and not overwrite:
            raise FreiPoseError(f"{output_path} already exists; pass --overwrite to replace it")
        fin = cal.detect_format(input_path, format_in)
        fout = cal.detect_format(output_path, format_out)
        if fin == "anipose":
            rig = cf.read_anipose_calibration(input_path, units=units)
        else:
            rig = cal.load_calibration(input_path, fin)
        if size_map:
            rig = cf.with_image_sizes(rig, size_map)
        if fout == "anipose":
            cf.write_anipose_calibration(rig, output_path, units=units)
        else:
            cal.save_calibration(rig, output_path, fout)
        est = rig.metadata.get(cf.ESTIMATED_KEY)
        click.echo(f"wrote {len(rig)} cameras ({', '.join(rig.names)}) to {output_path} [{fout}]")
        if est:
            click.echo(
                f"note: image sizes of {list(est)} were estimated from the principal point; "
                f"pass --size WxH if they are wrong",
                err=True,
            )


def _fmt(v: float, digits: int = 1) -> str:
    return f"{v:.{digits}f}"


def rig_summary(rig: Any, title: str) -> str:
    """A readable multi-line summary of a rig (cameras, intrinsics, positions, baselines)."""
    import numpy as np

    from freipose.io.calibration_formats import ESTIMATED_KEY

    est = set(rig.metadata.get(ESTIMATED_KEY, []))
    lines = [title, f"{len(rig)} cameras; lengths in mm", *_metadata_lines(rig.metadata)]
    suspect = rig.metadata.get(_SUSPECT_KEY) or []
    if suspect:
        lines.append("SUSPECT: written with --force although it failed the plausibility checks:")
        lines += [f"  - {f.get('message', f) if isinstance(f, dict) else f}" for f in suspect]
    head = [
        "camera",
        "size",
        "fx",
        "fy",
        "cx",
        "cy",
        "skew",
        "k1",
        "k2",
        "p1",
        "p2",
        "k3",
        "position x",
        "y",
        "z",
    ]
    rows = []
    for c in rig:
        K, d, pos = c.K, c.dist, c.center
        size = f"{c.size[0]}x{c.size[1]}" + ("*" if c.name in est else "")
        rows.append(
            [
                c.name,
                size,
                _fmt(K[0, 0]),
                _fmt(K[1, 1]),
                _fmt(K[0, 2]),
                _fmt(K[1, 2]),
                _fmt(K[0, 1], 2),
            ]
            + [f"{x:.4g}" for x in d]
            + [_fmt(x) for x in pos]
        )
    lines += ["", *_table(head, rows)]
    lines += _model_lines(rig.metadata.get(_MODEL_KEY) or {})
    lines += _standard_error_lines(rig.metadata.get(_SE_KEY) or {})
    if est:
        lines.append("* image size not stored in the file; estimated as 2 * principal point + 1")
    centers = rig.centers
    dists = np.linalg.norm(centers[:, None] - centers[None], axis=-1)
    lines += ["", "Baselines (distance between camera centres, mm):"]
    lines += _table(
        [""] + rig.names, [[n] + [_fmt(x) for x in row] for n, row in zip(rig.names, dists)]
    )
    if len(rig) > 1:
        off = dists[~np.eye(len(rig), dtype=bool)]
        lines.append(f"min {off.min():.1f}, median {np.median(off):.1f}, max {off.max():.1f} mm")
    return "\n".join(lines)


_SE_KEY = "intrinsics_standard_errors"
_SUSPECT_KEY = "suspect"
_MODEL_KEY = "intrinsics_model"
# metadata key -> (label, format of its value); keys not listed are shown by name
_LABELS = {
    "world": ("world frame", "{}"),
    "up": ("up direction", "{}"),
    "up_source": ("up direction from", "{}"),
    "floor_mm": ("floor height along up", "{} mm"),
    "calibrated_by": ("calibrated by", "{}"),
    "board": ("board", "{}"),
    "reprojection_rms_px": ("reprojection RMS", "{} px"),
    "distortion_model": ("distortion model option", "{}"),
    "view_weights": ("per-view weights", "{}"),
    "board_point_corrections_rms_mm": ("board point corrections", "{} mm RMS"),
    "origin_frame": ("origin frame", "{}"),
    "source_format": ("read from", "{}"),
}
_HIDDEN = ("units", _SE_KEY, _SUSPECT_KEY, _MODEL_KEY)


def _plain(v: Any) -> str:
    """A metadata value as text: mappings as ``key value, ...``, lists joined by commas."""
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, dict):
        return ", ".join(f"{str(k).replace('_', ' ')} {_plain(x)}" for k, x in v.items())
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_plain(x) for x in v) + "]"
    return str(v)


def _metadata_lines(md: Any) -> list[str]:
    """The file's metadata as ``label: value`` lines (tables of its own come later)."""
    from freipose.io.calibration_formats import ESTIMATED_KEY

    out = []
    for k, v in md.items():
        if k in _HIDDEN or k == ESTIMATED_KEY:
            continue
        label, fmt = _LABELS.get(k, (k.replace("_", " "), "{}"))
        out.append(f"  {label}: {fmt.format(_plain(v))}")
    return out


def _model_lines(models: dict[str, dict[str, str]]) -> list[str]:
    """The table of each camera's lens model (what the bundle adjustment estimated)."""
    if not models:
        return []
    keys = ("principal_point", "distortion", "focal")
    rows = [[c] + [str(m.get(k, "")) for k in keys] for c, m in models.items()]
    return ["", "Lens model (estimated where the data support it):"] + _table(
        ["camera", "principal point", "distortion", "focal length"], rows
    )


def _standard_error_lines(se: dict[str, dict[str, float]]) -> list[str]:
    """The table of the intrinsic standard errors a calibration file carries."""
    if not se:
        return []
    keys = [
        k
        for k in ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
        if any(k in v for v in se.values())
    ]
    rows = [[c] + [f"{v[k]:.3g}" if k in v else "fixed" for k in keys] for c, v in se.items()]
    return ["", "Intrinsics standard errors (px for f and c; parameters not listed: fixed):"] + (
        _table(["camera", *keys], rows)
    )


def _table(head: list[str], rows: list[list[str]]) -> list[str]:
    widths = [max(len(str(x)) for x in col) for col in zip(head, *rows)]

    def line(cells: list[str]) -> str:
        first = str(cells[0]).ljust(widths[0])
        rest = [str(c).rjust(w) for c, w in zip(cells[1:], widths[1:])]
        return "  ".join([first, *rest]).rstrip()

    return [line(head), *(line(r) for r in rows)]


@click.command()
@click.argument("file", type=click.Path(exists=True, path_type=Path))
@click.option(
    "--format",
    "fmt",
    default=None,
    metavar="F",
    help=f"Format of FILE (default: from its suffix). One of: {FORMATS_HELP}.",
)
@click.option(
    "--units",
    type=click.Choice(["mm", "cm", "m"]),
    default="mm",
    show_default=True,
    help="Length unit of an Anipose file's translations (with --format anipose).",
)
def show(file: Path, fmt: str | None, units: str) -> None:
    """Print a summary of a calibration: cameras, image sizes, focal lengths, positions, baselines.

    \b
    Examples:
      freipose calib show calibration.toml
      freipose calib show M.json
      freipose calib show calib_jarvis/
      freipose calib show label3d_dannce.mat
    """  # noqa: D301 - click needs the \b (backspace) paragraph marker
    with user_errors():
        from freipose.io import calibration as cal
        from freipose.io import calibration_formats as cf

        f = cal.detect_format(file, fmt)
        rig = (
            cf.read_anipose_calibration(file, units)
            if f == "anipose"
            else cal.load_calibration(file, f)
        )
        click.echo(rig_summary(rig, f"Calibration {file} [{f}]"))

"""Entry point of the ``freipose`` command: the group, logging and error handling."""

from __future__ import annotations

import logging
import os
import sys
import warnings

import click

from freipose import __version__
from freipose.cli._lazy import LazyGroup

# Command name -> "module:attribute". One module per command under cli/.
COMMANDS = {
    "synth": "freipose.cli.synth:synth",
    "calib": "freipose.cli.calib:calib",
    "labels": "freipose.cli.labels:labels",
    "label": "freipose.cli.label:label",
    "detect": "freipose.cli.detect:detect",
    "train": "freipose.cli.train:train",
    "eval": "freipose.cli.evaluate:evaluate",
    "predict": "freipose.cli.predict:predict",
    "merge": "freipose.cli.merge:merge",
    "jobs": "freipose.cli.jobs:jobs",
    "export": "freipose.cli.export:export",
    "smooth": "freipose.cli.smooth:smooth",
    "render": "freipose.cli.render:render",
    "analyze": "freipose.cli.analyze:analyze",
    "demo": "freipose.cli.demo:demo",
}


def quiet_native_warnings(verbose: int) -> None:
    """Keep FFmpeg's, OpenCV's and NumPy's own warnings off the terminal unless ``-v``.

    FreiPose reports what matters about a video or a computation in its own messages;
    the libraries' lines (``[mov,mp4 @ 0x...] moov atom not found``, ``[ WARN:0@...]``,
    ``RuntimeWarning: Mean of empty slice``) are shown with ``-v`` only. The environment
    variables are read by OpenCV when it first opens a video, so they are set before any
    command imports it; a value the user set is kept.
    """
    if verbose:
        return
    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")  # AV_LOG_QUIET
    os.environ.setdefault("OPENCV_LOG_LEVEL", "ERROR")
    warnings.filterwarnings("ignore", category=RuntimeWarning, module=r"numpy(\.|$)")


def setup_logging(verbose: int, quiet: bool) -> None:
    """Configure the root logger once: WARNING with -q, INFO by default, DEBUG with -v."""
    level = logging.WARNING if quiet else (logging.DEBUG if verbose else logging.INFO)
    logging.basicConfig(
        level=level,
        format="%(levelname)s %(name)s: %(message)s" if verbose else "%(levelname)s: %(message)s",
        stream=sys.stderr,
        force=True,
    )


@click.group(
    cls=LazyGroup,
    lazy_commands=COMMANDS,
    context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100},
)
@click.version_option(__version__, prog_name="freipose")
@click.option("-v", "--verbose", count=True, help="More log output (debug messages).")
@click.option("-q", "--quiet", is_flag=True, help="Only warnings and errors.")
@click.pass_context
def cli(ctx: click.Context, verbose: int, quiet: bool) -> None:
    """FreiPose: markerless 3D motion capture of lab animals from synchronized cameras.

    \b
    Typical workflow:
      freipose calib cams/*.mp4 --board board.toml -o calibration.toml
      freipose labels import --format dlc ... -o labels.h5
      freipose train config.toml
      freipose predict session/ --model model.pt -o poses/
      freipose analyze study.toml -o results/

    Units are millimetres; see docs/formats.md for every file format.
    """  # noqa: D301 - click needs the \b (backspace) paragraph marker
    ctx.ensure_object(dict)
    ctx.obj["quiet"] = quiet
    setup_logging(verbose, quiet)
    quiet_native_warnings(verbose)
    if sys.stderr.isatty():  # log lines above the progress bars instead of through them
        from tqdm.contrib.logging import logging_redirect_tqdm

        ctx.with_resource(logging_redirect_tqdm())


def main() -> None:
    """Console-script entry point."""
    cli(prog_name="freipose")


if __name__ == "__main__":  # pragma: no cover
    main()

"""``freipose label``: label time instants in the browser, all camera views at once."""

from __future__ import annotations

import contextlib
from pathlib import Path

import click

from freipose.cli._common import user_errors


@click.command()
@click.argument("sessions", nargs=-1, required=True, type=click.Path(exists=True, path_type=Path))
@click.option(
    "--calibration",
    required=True,
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    help="Calibration of the sessions' cameras (camera name = video file stem).",
)
@click.option(
    "--skeleton", required=True, help="Skeleton name (rat, mouse, paw) or skeleton TOML file."
)
@click.option(
    "-o",
    "--output",
    required=True,
    type=click.Path(dir_okay=False, path_type=Path),
    help="labels.h5 to write after every edit (read first if it exists: resume).",
)
@click.option(
    "--frames",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    help="Selection CSV of `freipose labels select` (its order: least confident first) "
    "[default: --n instants evenly over each session].",
)
@click.option(
    "--n", "per_session", type=int, default=20, show_default=True,
    help="Instants per session without --frames.",
)  # fmt: skip
@click.option(
    "--poses-dir",
    type=click.Path(exists=True, file_okay=False, path_type=Path),
    help="Folder with <session>.poses.h5 predictions that pre-fill the instants (shown as "
    "predicted until confirmed).",
)
@click.option(
    "--host", default="127.0.0.1", show_default=True,
    help="Address to listen on (0.0.0.0: every network interface; the page is then served "
    "over plain HTTP to the network, and anyone with the token can edit the labels).",
)  # fmt: skip
@click.option(
    "--port", type=click.IntRange(0, 65535), default=0, show_default=True,
    help="Port to listen on (0: a free one).",
)  # fmt: skip
@click.option(
    "--max-residual", type=float, default=3.0, show_default=True,
    help="Reprojection residual (px) above which a label is highlighted.",
)  # fmt: skip
@click.option(
    "--animals",
    help="Label several animals at each instant: their number (named animal_0, animal_1, "
    "... as `freipose predict --animals` names them) or their names, comma-separated "
    "(e.g. resident,intruder) [default: the animals of OUTPUT if it exists, else those of "
    "the --poses-dir predictions, else one].",
)
@click.option("--no-browser", is_flag=True, help="Do not open the page in a web browser.")
def label(
    sessions: tuple[Path, ...],
    calibration: Path,
    skeleton: str,
    output: Path,
    frames: Path | None,
    per_session: int,
    poses_dir: Path | None,
    host: str,
    port: int,
    max_residual: float,
    animals: str | None,
    no_browser: bool,
) -> None:
    """Label keypoints in every camera view of an instant at once, in the browser.

    Starts a local web server and prints the page's address with its access token.
    Clicking a keypoint in one view draws its epipolar curve in the others; a second view
    triangulates it and projects it into the rest, where Enter accepts the projections.
    Every edit is written to OUTPUT at once (labels.h5, read by train, labels check and
    labels export); Ctrl-C stops the server. With several animals (--animals) each animal
    of an instant is labeled on its own (A switches between them; the others' labels are
    drawn for reference) and OUTPUT has a row per animal. See docs/tutorials/labeling.md.

    \b
    Example:
      freipose labels select rec/day1 --poses-dir poses -o selection.csv
      freipose label rec/day1 --calibration calibration.toml --skeleton rat \\
          --frames selection.csv --poses-dir poses -o labels.h5
    """  # noqa: D301 - click needs the \b (backspace) paragraph marker
    with user_errors():
        from freipose.io.labels import labels_file_lock
        from freipose.labelui.server import network_warning, serving
        from freipose.labelui.startup import open_store, parse_animals
        from freipose.labelui.store import StoreSettings

        names = None if animals is None else parse_animals(animals)
        with labels_file_lock(output):  # before the file is read: no writer in between
            store = open_store(
                sessions, calibration, skeleton, output, frames=frames, poses_dir=poses_dir,
                per_session=per_session, settings=StoreSettings(max_residual=max_residual),
                animals=names,
            )  # fmt: skip
            with (
                serving(store, host, port, lock=False) as (running, handle),
                contextlib.suppress(KeyboardInterrupt),  # Ctrl-C: stop, report below
            ):
                who = (
                    f" ({len(store.animals)} animals each: {', '.join(store.animals)})"
                    if store.animals
                    else ""
                )
                click.echo(
                    f"labeling {len(store)} instants{who} of {len(store.sessions)} sessions "
                    f"into {output}"
                )
                if (warning := network_warning(host)) is not None:
                    click.echo(f"warning: {warning}", err=True)
                click.echo(f"open {running.url}")
                if not no_browser:
                    import webbrowser

                    webbrowser.open(running.url)
                handle.run()
        if store.saves:
            edits = f"{store.saves} edit" + ("s" if store.saves > 1 else "")
            click.echo(f"labels saved in {output} ({edits})")
        elif output.exists():
            click.echo(f"no edits; {output} left as it was")
        else:
            click.echo(f"no edits; nothing saved ({output} not written)")

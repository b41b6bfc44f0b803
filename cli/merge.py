"""``freipose merge``: join the shard files of ``freipose predict --shard I/N``."""

from __future__ import annotations

from pathlib import Path

import click

from freipose.cli._common import overwrite_option, user_errors


@click.command()
@click.argument("shards", nargs=-1, required=True, type=click.Path(exists=True, path_type=Path))
@click.option(
    "-o",
    "--outdir",
    type=click.Path(file_okay=False, path_type=Path),
    default=None,
    help="Folder for the merged <session>.poses.h5 (default: the shards' folder).",
)
@click.option("--remove-shards", is_flag=True, help="Delete the shard files after merging.")
@overwrite_option("merged files that exist")
def merge(
    shards: tuple[Path, ...], outdir: Path | None, remove_shards: bool, overwrite: bool
) -> None:
    """Merge the shards of sharded predictions into one poses.h5 per session.

    SHARDS are shard files (<session>.shard-I-of-N.poses.h5) or folders holding them. All N
    shards of a session must be complete and come from the same command; the result equals
    the file an unsharded run writes. An existing merged file is kept unless --overwrite
    (nothing is merged then).

    \b
    Example:
      # SLURM array job, 8 tasks: freipose predict rec1/ --model m.pt -o out/ --shard $ID/8
      freipose merge out/ --remove-shards
    """  # noqa: D301 - click needs the \b (backspace) paragraph marker
    with user_errors():
        from freipose.predict.merge import merge_outputs

        for path in merge_outputs(shards, outdir, remove=remove_shards, overwrite=overwrite):
            click.echo(f"wrote {path}")

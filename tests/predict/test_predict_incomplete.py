"""Unfinished predictions (a ``.partial`` file, or ``complete`` false) are refused by
``export`` and ``render`` with the command that finishes them, or used with
``--allow-incomplete`` (the missing frames are counted)."""

from __future__ import annotations

import shutil

import h5py
import pandas as pd
import pytest
from click.testing import CliRunner
from predict_helpers import BlobEstimator, make_session

from freipose.cli.main import cli
from freipose.io.session import discover_sessions
from freipose.predict.run import predict_session

N = 40
PROVENANCE = {"model_file": "model.pt", "detection": "bgsub", "bg_samples": 40, "min_views": 2}


class _Kill(Exception):
    pass


@pytest.fixture(scope="module")
def partial(tmp_path_factory):
    """(session folder, the .partial file of a run killed after 16 of 40 frames)."""
    root = tmp_path_factory.mktemp("incomplete")
    folder = root / "rec3"
    make_session(folder, N)
    (s,) = discover_sessions([folder])

    def kill(rows: int) -> None:
        if rows >= 16:
            raise _Kill

    with pytest.raises(_Kill):
        predict_session(
            s, BlobEstimator(), root / "out", batch_size=4, chunk_frames=8, progress=False,
            provenance=PROVENANCE, on_batch=kill,
        )  # fmt: skip
    path = root / "out" / "rec3.poses.h5.partial"
    assert path.is_file()
    return folder, path


def _expected(path) -> str:
    return (
        f"{path} is incomplete (16 of 40 frames predicted): finish it with `freipose predict "
        f"rec3 --model model.pt --method bgsub --frames 0:40 -o {path.parent}` (it resumes)"
    )


def test_export_refuses_a_partial_file(partial, tmp_path):
    _, path = partial
    res = CliRunner().invoke(cli, ["export", str(path), "-o", str(tmp_path / "p.csv")])
    assert res.exit_code != 0
    assert _expected(path) in " ".join(res.output.split())
    assert "--allow-incomplete" in res.output
    assert not (tmp_path / "p.csv").exists()


def test_a_final_name_with_complete_false_is_refused_too(partial, tmp_path):
    from freipose.io.poses import IncompletePosesError, require_complete

    _, path = partial
    copy = tmp_path / "rec3.poses.h5"
    shutil.copy(path, copy)
    with pytest.raises(IncompletePosesError, match=r"\(16 of 40 frames predicted\)"):
        require_complete(copy)
    res = CliRunner().invoke(cli, ["export", str(copy), "--format", "dlc3d"])
    assert res.exit_code != 0 and "is incomplete (16 of 40 frames predicted)" in res.output


def test_allow_incomplete_exports_and_counts_the_missing_frames(partial, tmp_path):
    _, path = partial
    out = tmp_path / "p.csv"
    res = CliRunner().invoke(cli, ["export", str(path), "-o", str(out), "--allow-incomplete"])
    assert res.exit_code == 0, res.output
    assert "24 frames have no prediction" in res.output
    df = pd.read_csv(out)
    assert len(df) == N and df["red_x_mm"][:16].notna().all() and df["red_x_mm"][16:].isna().all()


def test_render_refuses_a_partial_file(partial, tmp_path):
    folder, path = partial
    out = tmp_path / "o.mkv"
    res = CliRunner().invoke(cli, ["render", str(folder), str(path), "-o", str(out)])
    assert res.exit_code != 0
    assert _expected(path) in " ".join(res.output.split())
    assert not out.exists()
    args = ["render", str(folder), str(path), "-o", str(out), "--allow-incomplete",
            "--frames", "12:20", "--tile-width", "64", "--no-3d"]  # fmt: skip
    res = CliRunner().invoke(cli, args)
    assert res.exit_code == 0, res.output
    assert out.is_file() and "24 frames have no prediction" in res.output


def test_complete_and_foreign_files_pass(partial, tmp_path):
    from freipose.io.poses import require_complete

    folder, _ = partial
    (s,) = discover_sessions([folder])
    done = predict_session(s, BlobEstimator(), tmp_path, batch_size=8, progress=False).path
    assert require_complete(done) == 0
    with h5py.File(done, "a") as f:  # a file written in one go has no 'complete' flag
        del f.attrs["complete"]
        del f.attrs["completed_frames"]
    assert require_complete(done) == 0

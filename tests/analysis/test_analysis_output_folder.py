"""``freipose analyze -o OUTDIR``: an earlier analysis is replaced only when asked, wholly."""

from __future__ import annotations

from click.testing import CliRunner

from freipose.analysis.simulate import simulate_study
from freipose.cli.main import cli
from freipose.io.lock import output_lock


def _study(folder):
    return simulate_study(
        folder, ("rat1",), "10Hz", duration_s=30.0, fps=20.0, period_s=6.0, length_s=2.0, seed=1
    )


def _analyze(study, out, *extra):
    args = ["analyze", str(study), "-o", str(out), "--stft-window", "16", *extra]
    return CliRunner().invoke(cli, args)


def test_existing_analysis_is_refused_without_overwrite_and_replaced_wholly_with_it(tmp_path):
    study, out = _study(tmp_path), tmp_path / "out"
    res = _analyze(study, out, "--top", "1")
    assert res.exit_code == 0, res.output
    figures = sorted(p.name for p in out.glob("*.png"))
    assert figures and (out / "classification.csv").is_file()
    table = (out / "classification.csv").read_bytes()
    # a second run into the same folder: refused, nothing touched
    res = _analyze(study, out, "--no-figures")
    assert res.exit_code == 1 and "Traceback" not in res.output
    assert "not empty" in res.output and "--overwrite" in res.output
    assert sorted(p.name for p in out.glob("*.png")) == figures
    # --overwrite --no-figures: the old figures do not stay beside the new tables
    res = _analyze(study, out, "--no-figures", "--overwrite")
    assert res.exit_code == 0, res.output
    assert not list(out.glob("*.png"))
    assert (out / "classification.csv").read_bytes() == table
    assert not (tmp_path / "out.lock").exists()


def test_an_analysis_folder_in_use_is_refused(tmp_path):
    study, out = _study(tmp_path), tmp_path / "out"
    with output_lock(out, "analysis folder"):
        res = _analyze(study, out, "--no-figures")
    assert res.exit_code == 1 and "Traceback" not in res.output
    assert not out.exists() or not any(out.iterdir())

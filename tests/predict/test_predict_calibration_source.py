"""freipose predict says which calibration each session uses, and warns on a synthetic truth."""

from __future__ import annotations

from click.testing import CliRunner
from predict_helpers import make_session

from freipose.cli.main import cli
from freipose.errors import FreiPoseError


class _Stop(FreiPoseError):
    """Raised by the patched prediction once the sessions were found."""


def _predict(monkeypatch, tmp_path, *extra):
    def stop(*args, **kwargs):
        raise _Stop("stopped before predicting")

    monkeypatch.setattr("freipose.io.checkpoints.check_checkpoints", lambda *a: None)
    monkeypatch.setattr("freipose.predict.network.predict_sessions", stop)
    model = tmp_path / "model.pt"
    model.write_bytes(b"x")
    args = ["predict", str(tmp_path / "s1"), "--model", str(model), "-o", str(tmp_path / "out")]
    return CliRunner().invoke(cli, [*args, "--method", "bgsub", "--threads", "1", *extra])


def test_predict_names_the_calibration_and_its_origin(monkeypatch, tmp_path):
    make_session(tmp_path / "s1", n_frames=3)
    r = _predict(monkeypatch, tmp_path)
    assert "stopped before predicting" in r.output
    assert (
        f"s1: calibration {tmp_path / 's1' / 'calibration.toml'} (found in the session folder)"
        in r.output
    )
    (tmp_path / "s1" / "calibration.toml").rename(tmp_path / "mine.toml")
    r = _predict(monkeypatch, tmp_path, "--calibration", str(tmp_path / "mine.toml"))
    assert f"s1: calibration {tmp_path / 'mine.toml'} (given with --calibration)" in r.output
    # a synthetic session's true rig is used only when nothing else is there, with a warning
    (tmp_path / "mine.toml").rename(tmp_path / "s1" / "true_calibration.toml")
    r = _predict(monkeypatch, tmp_path)
    assert "true_calibration.toml (found in the session folder)" in r.output, r.output
    assert "WARNING: s1: " in r.output and "is the true rig of a synthetic session" in r.output

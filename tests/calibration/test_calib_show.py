"""freipose calib show: the metadata as readable lines, never Python dicts."""

from __future__ import annotations

from click.testing import CliRunner

from freipose.cli.main import cli
from freipose.geometry import CameraRig
from freipose.io.calibration import save_calibration
from freipose.io.calibration_world import WorldUp, with_world_up
from freipose.testing import make_circle_rig


def test_show_prints_metadata_as_lines_and_the_lens_model_as_a_table(tmp_path):
    rig = make_circle_rig(n=2, radius=700.0, height=400.0, size=(320, 240), focal=300.0)
    md = {
        "world": "board on the floor in frame 0",
        "board": {"type": "charuco", "squares_x": 5, "square_size": 24.0, "inverted": True},
        "reprojection_rms_px": 0.21,
        "view_weights": True,
        "intrinsics_model": {
            c: {"principal_point": "image centre", "distortion": "k1 k2", "focal": "fx = fy"}
            for c in rig.names
        },
        "intrinsics_standard_errors": {c: {"fx": 0.5, "k1": 0.001} for c in rig.names},
    }
    rig = with_world_up(CameraRig(rig.cameras, md), WorldUp([0, 0, 1], "the board", 0.0))
    save_calibration(rig, tmp_path / "c.toml")
    r = CliRunner().invoke(cli, ["calib", "show", str(tmp_path / "c.toml")])
    assert r.exit_code == 0, r.output
    assert "{" not in r.output and "'" not in r.output, r.output
    for text in [
        "board: type charuco, squares x 5, square size 24.0, inverted yes",
        "reprojection RMS: 0.21 px",
        "per-view weights: yes",
        "up direction: [0.0, 0.0, 1.0]",
        "up direction from: the board",
        "floor height along up: 0.0 mm",
        "Lens model",
    ]:
        assert text in r.output, (text, r.output)
    row = next(ln for ln in r.output.splitlines() if ln.startswith(rig.names[0]) and "k1 k2" in ln)
    assert "image centre" in row and "fx = fy" in row

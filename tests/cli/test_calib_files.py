"""``freipose calib convert`` and ``freipose calib show``."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
from click.testing import CliRunner

from freipose._compat import tomllib
from freipose.cli.main import cli
from freipose.io.calibration import load_calibration
from freipose.io.calibration_toml import write_calibration_toml
from freipose.testing import make_circle_rig


def _run(*args: str):
    return CliRunner().invoke(cli, ["-q", *map(str, args)])


def test_convert_toml_mjson_toml(tmp_path):
    rig = make_circle_rig(4, distortion=True)
    src = tmp_path / "calibration.toml"
    write_calibration_toml(rig, src)
    r = _run("calib", "convert", src, tmp_path / "M.json")
    assert r.exit_code == 0, r.output
    assert "wrote 4 cameras" in r.output and "[mjson]" in r.output
    data = json.loads((tmp_path / "M.json").read_text())
    np.testing.assert_allclose(
        np.array(data["M"]["cam1"])[:3, 3], rig["cam1"].center / 1000, atol=1e-12
    )
    r = _run("calib", "convert", tmp_path / "M.json", tmp_path / "back.toml")
    assert r.exit_code == 0, r.output
    assert load_calibration(tmp_path / "back.toml").allclose(rig, rtol=1e-9, atol=1e-9)


def test_convert_jarvis_anipose_and_sizes(tmp_path):
    rig = make_circle_rig(3)
    src = tmp_path / "calibration.toml"
    write_calibration_toml(rig, src)
    r = _run("calib", "convert", src, tmp_path / "jv", "--format", "jarvis")
    assert r.exit_code == 0, r.output
    assert sorted(p.name for p in (tmp_path / "jv").iterdir()) == [
        "cam0.yaml",
        "cam1.yaml",
        "cam2.yaml",
    ]
    r = _run("calib", "convert", tmp_path / "jv", tmp_path / "ani.toml", "--format", "anipose",
             "--units", "m", "--size", "1920x1080", "--size", "cam2=800x600")  # fmt: skip
    assert r.exit_code == 0, r.output
    ani = tomllib.loads((tmp_path / "ani.toml").read_text())
    assert "metadata" not in ani
    np.testing.assert_allclose(ani["cam_0"]["translation"], rig[0].t / 1000)
    assert ani["cam_0"]["size"] == [1920, 1080] and ani["cam_2"]["size"] == [800, 600]
    r = _run("calib", "show", tmp_path / "ani.toml", "--format", "anipose", "--units", "m")
    assert r.exit_code == 0, r.output
    assert "1920x1080" in r.output and "1000.0" in r.output


def test_convert_notes_estimated_sizes(tmp_path):
    rig = make_circle_rig(2)
    mj = tmp_path / "M.json"
    data = {
        "K": {c.name: c.K.tolist() for c in rig},
        "dist": {c.name: c.dist.tolist() for c in rig},
        "M": {},
    }
    for c in rig:  # FreiCalib's layout: camera->world in metres, no image sizes
        E = c.extrinsics.copy()
        E[:3, 3] /= 1000
        data["M"][c.name] = np.linalg.inv(E).tolist()
    mj.write_text(json.dumps(data))
    r = CliRunner().invoke(cli, ["calib", "convert", str(mj), str(tmp_path / "c.toml")])
    assert r.exit_code == 0, r.output
    assert "estimated from the principal point" in r.output
    r = _run("calib", "show", mj)
    assert "640x480*" in r.output and "estimated" in r.output
    r = _run("calib", "convert", mj, tmp_path / "d.toml", "--size", "640x480")
    assert "principal point" not in r.output
    back = load_calibration(tmp_path / "d.toml")
    assert back.allclose(rig, rtol=1e-9, atol=1e-9)
    assert "image_size_estimated" not in back.metadata


def test_show_summary(tmp_path):
    rig = make_circle_rig(6)
    src = tmp_path / "calibration.toml"
    write_calibration_toml(rig, src)
    r = _run("calib", "show", src)
    assert r.exit_code == 0, r.output
    out = r.output
    for name in rig.names:
        assert name in out
    assert "640x480" in out and "800.0" in out and "Baselines" in out
    # Six cameras on a 1 m circle: neighbours 1000 mm apart, opposite ones 2000 mm.
    assert "1000.0" in out and "2000.0" in out and "1732.1" in out
    assert "min 1000.0, median 1732.1, max 2000.0 mm" in out
    assert "world frame: origin at the arena centre" in out


def test_convert_and_show_errors(tmp_path):
    rig = make_circle_rig(2)
    src = tmp_path / "calibration.toml"
    write_calibration_toml(rig, src)
    (tmp_path / "exists.json").write_text("{}")
    r = _run("calib", "convert", src, tmp_path / "exists.json")
    assert r.exit_code == 1 and "--overwrite" in r.output
    r = _run("calib", "convert", src, tmp_path / "exists.json", "--overwrite")
    assert r.exit_code == 0, r.output
    r = _run("calib", "convert", src, src, "--overwrite")
    assert r.exit_code == 1 and "same as IN" in r.output
    r = _run("calib", "convert", src, tmp_path / "out.txt")
    assert r.exit_code == 1 and "--format" in r.output and "Traceback" not in r.output
    r = _run("calib", "convert", src, tmp_path / "out.mat")
    assert r.exit_code == 1 and "can be read but not written" in r.output
    r = _run("calib", "convert", src, tmp_path / "o.toml", "--format", "bogus")
    assert r.exit_code == 1 and "unknown calibration format 'bogus'" in r.output
    r = _run("calib", "convert", src, tmp_path / "o.toml", "--size", "big")
    assert r.exit_code == 2 and "WIDTHxHEIGHT" in r.output
    r = _run("calib", "convert", src, tmp_path / "o.toml", "--size", "cam9=10x10")
    assert r.exit_code == 1 and "cam9" in r.output
    r = _run("calib", "show", tmp_path / "missing.toml")
    assert r.exit_code == 2 and "does not exist" in r.output
    bad = tmp_path / "bad.toml"
    bad.write_text("[cam_0]\nname = 'x'\n")
    r = _run("calib", "show", bad)
    assert r.exit_code == 1 and "lacks" in r.output and "Traceback" not in r.output
    assert not (tmp_path / "o.toml").exists()


def test_installed_entry_point(tmp_path):
    src = tmp_path / "calibration.toml"
    write_calibration_toml(make_circle_rig(3), src)
    exe = Path(sys.executable).parent / "freipose"
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "freipose.cli.main"]
    r = subprocess.run(
        [*cmd, "calib", "show", str(src)], capture_output=True, text=True, timeout=120
    )
    assert r.returncode == 0, r.stderr
    assert "3 cameras" in r.stdout and "cam2" in r.stdout

"""Unknown keys in a calibration file are errors with a "did you mean", in every reader
(native / Anipose TOML, M.json, JARVIS YAML, DANNCE); the keys that real files of those
tools carry still load."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from freipose.io import calibration_formats as cf
from freipose.io.calibration import load_calibration, save_calibration
from freipose.io.calibration_toml import CalibrationFormatError, rig_to_toml_text
from freipose.testing import make_circle_rig

DATA = Path("/work/shared/data")


def _toml(tmp_path: Path, old: str, new: str) -> Path:
    text = rig_to_toml_text(make_circle_rig(2))
    assert old in text
    p = tmp_path / "calibration.toml"
    p.write_text(text.replace(old, new, 1))
    return p


def test_toml_misspelled_camera_key_is_an_error(tmp_path):
    p = _toml(tmp_path, "distortions =", "distortion =")
    with pytest.raises(CalibrationFormatError) as e:
        load_calibration(p)
    assert str(e.value) == (
        f"{p}: [cam_0]: unknown key 'distortion'; did you mean 'distortions'? (known keys: "
        "distortions, fisheye, matrix, name, rotation, size, translation)"
    )


def test_toml_extra_camera_key_is_an_error(tmp_path):
    p = _toml(tmp_path, 'name = "cam0"', 'name = "cam0"\nfocal = 300')
    with pytest.raises(CalibrationFormatError, match=r"\[cam_0\]: unknown key 'focal'"):
        load_calibration(p)


def test_toml_unknown_table_and_fisheye(tmp_path):
    p = _toml(tmp_path, "[cam_1]", "[cam1]")
    with pytest.raises(CalibrationFormatError, match=r"unknown table 'cam1'; did you mean 'cam_1'"):
        load_calibration(p)
    p = _toml(tmp_path, 'name = "cam0"', 'name = "cam0"\nfisheye = true')
    with pytest.raises(CalibrationFormatError, match="fisheye camera"):
        load_calibration(p)
    p = _toml(tmp_path, 'name = "cam0"', 'name = "cam0"\nfisheye = false')
    assert load_calibration(p).names == ["cam0", "cam1"]


def test_anipose_file_with_metadata_loads(tmp_path):
    p = tmp_path / "anipose.toml"
    save_calibration(make_circle_rig(3), p, "anipose")
    p.write_text(p.read_text() + "\n[metadata]\nadjusted = false\nerror = 0.42\n")
    assert cf.read_anipose_calibration(p).names == ["cam0", "cam1", "cam2"]
    sleap = DATA / "sleap-8cam-2mice" / "calibration.toml"
    if sleap.is_file():
        assert len(load_calibration(sleap)) == 8


def test_mjson_unknown_keys(tmp_path):
    p = tmp_path / "M.json"
    save_calibration(make_circle_rig(2), p, "mjson")
    data = json.loads(p.read_text())
    data["distortion"] = data.pop("dist")
    p.write_text(json.dumps(data))
    with pytest.raises(CalibrationFormatError, match="'K', 'dist' and 'M'"):
        load_calibration(p)
    data["dist"] = data.pop("distortion")
    data["img_sizes"] = data.pop("img_size")
    p.write_text(json.dumps(data))
    with pytest.raises(
        CalibrationFormatError, match="unknown key 'img_sizes'; did you mean 'img_size'"
    ):
        load_calibration(p)
    data["img_size"] = data.pop("img_sizes")
    data["M"]["cam2"] = data["M"]["cam1"]
    p.write_text(json.dumps(data))
    with pytest.raises(CalibrationFormatError, match=r"'M' .*unknown key 'cam2'"):
        load_calibration(p)


def test_jarvis_unknown_keys(tmp_path):
    folder = tmp_path / "jarvis"
    save_calibration(make_circle_rig(2), folder, "jarvis")
    f = folder / "cam1.yaml"
    good = f.read_text()
    f.write_text(good.replace("distortionCoefficients:", "distortionCoefficient:"))
    with pytest.raises(CalibrationFormatError, match="missing 'distortionCoefficients'"):
        load_calibration(folder)
    f.write_text(good + "focal: 300.\n")
    with pytest.raises(CalibrationFormatError, match=r"cam1.yaml: unknown key 'focal'"):
        load_calibration(folder)
    eye = (
        "!!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n"
        "   data: [ 1., 0., 0., 0., 1., 0., 0., 0., 1. ]\n"
    )
    f.write_text(good + f"E: {eye}F: {eye}")  # JARVIS's stereo step adds E and F
    assert load_calibration(folder).names == ["cam0", "cam1"]


def test_dannce_unknown_params_field(tmp_path):
    from scipy.io import savemat

    rig = make_circle_rig(2)
    params = []
    for cam in rig:
        params.append({"K": cam.K.T, "RDistort": np.zeros(3), "TDistort": np.zeros(2),
                       "r": cam.R.T, "t": cam.t.reshape(1, 3)})  # fmt: skip
    good = tmp_path / "good.mat"
    savemat(good, {"params": np.array(params, dtype=object).reshape(-1, 1),
                   "camnames": np.array(rig.names, dtype=object), "sync": 1.0})  # fmt: skip
    assert load_calibration(good).names == ["cam0", "cam1"]
    params[1]["Rdistort"] = params[1].pop("RDistort")
    bad = tmp_path / "bad.mat"
    savemat(bad, {"params": np.array(params, dtype=object).reshape(-1, 1),
                  "camnames": np.array(rig.names, dtype=object)})  # fmt: skip
    with pytest.raises(
        CalibrationFormatError, match="unknown key 'Rdistort'; did you mean 'RDistort'"
    ):
        load_calibration(bad)


@pytest.mark.parametrize(
    "rel",
    [
        "dannce-markerless-mouse/markerless_mouse_1/label3d_dannce.mat",
        "dannce-markerless-mouse/markerless_mouse_2/label3d_dannce.mat",
        "dannce-markerless-mouse/markerless_mouse_1/label3d_demo.mat",
    ],
)
def test_real_files_still_load(rel, tmp_path):
    path = DATA / rel
    if not path.is_file():
        pytest.skip(f"{path} is not here")
    copy = tmp_path / path.name  # no videos next to it: sizes are estimated
    shutil.copy(path, copy)
    assert len(load_calibration(copy)) == 6

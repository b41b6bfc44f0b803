"""Native calibration.toml and the other tools' formats: round trips and clear errors."""

from __future__ import annotations

import json

import numpy as np
import pytest
import tomli_w

from freipose._compat import tomllib
from freipose.geometry import Camera, CameraRig, project
from freipose.io import calibration_formats as cf
from freipose.io.calibration import detect_format, load_calibration, save_calibration
from freipose.io.calibration_toml import (
    CalibrationFormatError,
    read_calibration_toml,
    rig_from_toml_text,
    rig_to_toml_text,
    write_calibration_toml,
)
from freipose.testing import make_circle_rig


def _rel_close(a: CameraRig, b: CameraRig, rtol: float = 1e-6) -> None:
    """Every camera equal to ``rtol`` relative (absolute floor for zero entries)."""
    assert a.names == b.names
    for ca, cb in zip(a, b):
        assert ca.size == cb.size
        for f in ("K", "dist", "R", "t"):
            x, y = getattr(ca, f), getattr(cb, f)
            scale = max(np.abs(x).max(), 1e-12)
            np.testing.assert_allclose(y, x, rtol=rtol, atol=rtol * scale, err_msg=f"{ca.name}.{f}")


def _skewed_rig() -> CameraRig:
    rig = make_circle_rig(4, distortion=True, size=(1280, 1024), focal=1200.0)
    cams = [
        c.replace(K=c.K + np.array([[0, -3.0 + i, 2.5 * i], [0, 0, -i], [0, 0, 0]]))
        for i, c in enumerate(rig)
    ]
    return CameraRig(tuple(cams), rig.metadata)


def test_toml_round_trip_and_layout(tmp_path):
    rig = _skewed_rig()
    p = tmp_path / "calibration.toml"
    write_calibration_toml(rig, p)
    data = tomllib.loads(p.read_text())
    assert data["metadata"]["units"] == "mm"
    assert set(data["cam_0"]) == {
        "name",
        "size",
        "matrix",
        "distortions",
        "rotation",
        "translation",
    }
    back = read_calibration_toml(p)
    assert back.allclose(rig, rtol=1e-12, atol=1e-9)
    assert back.metadata["world"] == rig.metadata["world"]
    assert rig_from_toml_text(rig_to_toml_text(rig)).allclose(rig, rtol=1e-12, atol=1e-9)
    assert load_calibration(p).allclose(rig, rtol=1e-12, atol=1e-9)


def test_toml_numeric_camera_order(tmp_path):
    rig = make_circle_rig(12)
    d = tomllib.loads(rig_to_toml_text(rig))
    # Write the tables in lexicographic key order (cam_0, cam_1, cam_10, cam_11, cam_2, ...).
    lines = []
    for key in sorted(k for k in d if k.startswith("cam_")):
        tab = d[key]
        lines.append(f"[{key}]")
        lines += [f"{k} = {json.dumps(v)}" for k, v in tab.items()]
    lines.append('[metadata]\nunits = "mm"')
    p = tmp_path / "calibration.toml"
    p.write_text("\n".join(lines))
    assert load_calibration(p).names == [f"cam{i}" for i in range(12)]


def test_toml_units_and_errors(tmp_path):
    rig = make_circle_rig(2)
    d = tomllib.loads(rig_to_toml_text(rig))
    p = tmp_path / "c.toml"
    p.write_text(rig_to_toml_text(rig).replace('units = "mm"', 'units = "m"'))
    np.testing.assert_allclose(load_calibration(p).t, rig.t * 1000)
    p.write_text(rig_to_toml_text(rig).replace('units = "mm"', 'units = "inch"'))
    with pytest.raises(CalibrationFormatError, match="'inch'"):
        load_calibration(p)
    p.write_text("not = [valid")
    with pytest.raises(CalibrationFormatError, match="not a valid TOML"):
        load_calibration(p)
    p.write_text('[metadata]\nunits = "mm"\n')
    with pytest.raises(CalibrationFormatError, match=r"no \[cam_N\] tables"):
        load_calibration(p)
    del d["cam_0"]["rotation"]
    with pytest.raises(CalibrationFormatError, match=r"\[cam_0\] lacks \['rotation'\]"):
        rig_from_toml_text(tomli_w.dumps(d))
    with pytest.raises(CalibrationFormatError, match="'rotatio'; did you mean 'rotation'"):
        rig_from_toml_text(rig_to_toml_text(rig).replace("rotation =", "rotatio ="))
    with pytest.raises(FileNotFoundError, match="not found"):
        load_calibration(tmp_path / "missing.toml")
    with pytest.raises(CalibrationFormatError, match="--format"):
        detect_format(tmp_path / "calib.txt")
    with pytest.raises(CalibrationFormatError, match="unknown calibration format"):
        detect_format(p, "nope")


def test_mjson_round_trip_is_camera_to_world_metres(tmp_path):
    rig = _skewed_rig()
    toml = tmp_path / "calibration.toml"
    write_calibration_toml(rig, toml)
    mj = tmp_path / "M.json"
    save_calibration(load_calibration(toml), mj)
    data = json.loads(mj.read_text())
    assert set(data) >= {"K", "dist", "M"}
    for cam in rig:
        M = np.array(data["M"][cam.name])
        # Camera->world: the translation is the camera centre in metres, and M maps the
        # camera's own origin there; its inverse is the world->camera extrinsics in metres.
        np.testing.assert_allclose(M[:3, 3], cam.center / 1000.0, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(M[:3, :3], cam.R.T, atol=1e-12)
        np.testing.assert_allclose(np.linalg.inv(M)[:3, 3] * 1000.0, cam.t, atol=1e-9)
        np.testing.assert_allclose(data["K"][cam.name], cam.K)
        np.testing.assert_allclose(data["dist"][cam.name], cam.dist)
    back_toml = tmp_path / "back.toml"
    save_calibration(load_calibration(mj), back_toml)
    _rel_close(rig, load_calibration(back_toml), 1e-6)
    assert load_calibration(back_toml).metadata["world"] == rig.metadata["world"]


def test_mjson_as_freicalib_writes_it(tmp_path, caplog):
    caplog.set_level("INFO")
    """A FreiCalib-style file: no sizes, nested 1x5 dist, cam10 after cam2, world = cam0."""
    cams = {
        f"cam{i}": Camera.look_at(
            f"cam{i}",
            (400.0 * np.cos(i), 400.0 * np.sin(i), 300.0),
            (0, 0, 0),
            (1280, 1024),
            1000.0,
        )
        for i in (0, 2, 10)
    }
    data = {"K": {}, "dist": {}, "M": {}}
    for n, c in cams.items():
        data["K"][n] = c.K.tolist()
        data["dist"][n] = [[0.01, 0.0, 0.0, 0.0, 0.0]]
        M = np.eye(4)
        M[:3, :3], M[:3, 3] = c.R.T, c.center / 1000
        data["M"][n] = M.tolist()
    p = tmp_path / "M.json"
    p.write_text(json.dumps(data))
    rig = load_calibration(p)
    assert rig.names == ["cam0", "cam2", "cam10"]
    assert rig.metadata[cf.ESTIMATED_KEY] == ["cam0", "cam2", "cam10"]
    assert rig["cam2"].size == (1280, 1024)  # principal point (639.5, 511.5) -> 2c+1
    assert "estimated" in caplog.text
    for n, c in cams.items():
        np.testing.assert_allclose(rig[n].t, c.t, atol=1e-9)
        assert rig[n].dist[0] == 0.01
    fixed = cf.with_image_sizes(rig, {None: (1920, 1080), "cam2": (640, 480)})
    assert fixed["cam0"].size == (1920, 1080) and fixed["cam2"].size == (640, 480)
    assert cf.ESTIMATED_KEY not in fixed.metadata
    with pytest.raises(KeyError, match="cam7"):
        cf.with_image_sizes(rig, {"cam7": (10, 10)})


def test_mjson_sizes_from_videos_next_to_it(tmp_path):
    from freipose.io.video import VideoWriter

    rig = make_circle_rig(2, size=(64, 48))
    p = tmp_path / "M.json"
    cf.write_mjson(rig, p)
    data = json.loads(p.read_text())
    del data["img_size"]
    p.write_text(json.dumps(data))
    for name, size in (("cam0", (40, 30)), ("cam10", (20, 10))):  # cam10 is not cam1
        with VideoWriter(tmp_path / f"run000_{name}.avi", 10, size) as w:
            w.write(np.zeros((size[1], size[0], 3), np.uint8))
    rig2 = load_calibration(p)
    assert rig2["cam0"].size == (40, 30)
    assert rig2["cam1"].size == (64, 48) and rig2.metadata[cf.ESTIMATED_KEY] == ["cam1"]


def test_mjson_errors(tmp_path):
    p = tmp_path / "M.json"
    p.write_text("{")
    with pytest.raises(CalibrationFormatError, match="not a valid JSON"):
        load_calibration(p)
    p.write_text(json.dumps({"K": {}}))
    with pytest.raises(CalibrationFormatError, match="'K', 'dist' and 'M'"):
        load_calibration(p)
    K = np.eye(3).tolist()
    p.write_text(json.dumps({"K": {"cam0": K}, "dist": {"cam0": [0] * 5}, "M": {}}))
    with pytest.raises(CalibrationFormatError, match=r"\['cam0'\] have a 'K' but no 'M'"):
        load_calibration(p)
    M = np.eye(4)
    M[3, 0] = 1
    p.write_text(
        json.dumps({"K": {"cam0": K}, "dist": {"cam0": [0] * 5}, "M": {"cam0": M.tolist()}})
    )
    with pytest.raises(CalibrationFormatError, match="last row"):
        load_calibration(p)


def test_anipose_units_and_no_extras(tmp_path):
    rig = _skewed_rig()
    p = tmp_path / "anipose.toml"
    save_calibration(rig, p, "anipose")
    data = tomllib.loads(p.read_text())
    assert "metadata" not in data and sorted(data) == ["cam_0", "cam_1", "cam_2", "cam_3"]
    _rel_close(rig, load_calibration(p, "anipose"), 1e-12)
    cf.write_anipose_calibration(rig, p, units="m")
    np.testing.assert_allclose(
        tomllib.loads(p.read_text())["cam_1"]["translation"], rig[1].t / 1000
    )
    _rel_close(rig, cf.read_anipose_calibration(p, units="m"), 1e-12)
    with pytest.raises(CalibrationFormatError, match="units must be one of"):
        cf.read_anipose_calibration(p, units="ft")


def test_anipose_sleap_file_reads(shared_data):
    rig = load_calibration(shared_data / "sleap-8cam-2mice" / "calibration.toml", "anipose")
    assert rig.names == ["back", "backL", "mid", "midL", "side", "sideL", "top", "topL"]
    assert rig["top"].size == (1280, 1024)


def test_jarvis_folder_round_trip(tmp_path):
    rig = _skewed_rig()
    folder = tmp_path / "jarvis"
    save_calibration(rig, folder, "jarvis")
    assert sorted(p.name for p in folder.iterdir()) == [f"cam{i}.yaml" for i in range(4)]
    text = (folder / "cam1.yaml").read_text()
    assert text.startswith("%YAML:1.0") and "intrinsicMatrix: !!opencv-matrix" in text
    back = load_calibration(folder)  # a folder is JARVIS by default
    _rel_close(rig, back, 1e-12)
    # The stored matrices are transposed (MATLAB convention), T is world->camera mm.
    import cv2

    fs = cv2.FileStorage(str(folder / "cam1.yaml"), cv2.FILE_STORAGE_READ)
    np.testing.assert_allclose(fs.getNode("intrinsicMatrix").mat(), rig[1].K.T)
    np.testing.assert_allclose(fs.getNode("R").mat(), rig[1].R.T)
    np.testing.assert_allclose(fs.getNode("T").mat().ravel(), rig[1].t)
    fs.release()
    one = load_calibration(folder / "cam2.yaml")
    assert one.names == ["cam2"] and one[0].allclose(back["cam2"])
    (folder / "other.yaml").write_text((folder / "cam0.yaml").read_text())
    with pytest.raises(CalibrationFormatError, match="not in this rig"):
        save_calibration(rig, folder, "jarvis")
    with pytest.raises(CalibrationFormatError, match="holds one camera"):
        save_calibration(rig, tmp_path / "one.yaml")


def test_jarvis_file_as_jarvis_writes_it(tmp_path):
    """The layout JARVIS's calibration tool writes (no image size), numeric camera order."""
    cam = make_circle_rig(1)[0]
    K, R, t = (a.ravel().tolist() for a in (cam.K.T, cam.R.T, cam.t))
    text = (
        "%YAML:1.0\n---\nintrinsicMatrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n"
        f"   data: [ {', '.join(map(repr, K))} ]\n"
        "distortionCoefficients: !!opencv-matrix\n   rows: 1\n   cols: 5\n   dt: d\n"
        "   data: [ -4.3e-02, 5.7e-02, 0., 0., 0. ]\n"
        "R: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n"
        f"   data: [ {', '.join(map(repr, R))} ]\n"
        "T: !!opencv-matrix\n   rows: 3\n   cols: 1\n   dt: d\n"
        f"   data: [ {', '.join(map(repr, t))} ]\n"
    )
    for name in ("Camera_2", "Camera_10", "Camera_1"):
        (tmp_path / f"{name}.yaml").write_text(text)
    rig = load_calibration(tmp_path)
    assert rig.names == ["Camera_1", "Camera_2", "Camera_10"]
    np.testing.assert_allclose(rig[0].R, cam.R)
    np.testing.assert_allclose(rig[0].dist, [-0.043, 0.057, 0, 0, 0])
    assert rig[0].size == (640, 480)  # (2 * 319.5 + 1, 2 * 239.5 + 1)
    (tmp_path / "bad.yaml").write_text("%YAML:1.0\n---\nfoo: 1\n")
    with pytest.raises(CalibrationFormatError, match="missing 'intrinsicMatrix'"):
        load_calibration(tmp_path)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(CalibrationFormatError, match="no camera files"):
        load_calibration(empty)


def test_dannce_cameras_reproject_labels_exactly(shared_data):
    from freipose.io.matlab import load_mat

    path = shared_data / "dannce-markerless-mouse" / "markerless_mouse_1" / "label3d_dannce.mat"
    rig = load_calibration(path)
    assert rig.names == [f"Camera{i}" for i in range(1, 7)]
    assert rig["Camera1"].K[0, 1] == pytest.approx(-5.815, abs=1e-3)  # the skew survives
    labels = load_mat(path)["labelData"]
    for cam, lab in zip(rig, labels):
        X = lab["data_3d"].reshape(-1, 22, 3)
        uv = lab["data_2d"].reshape(-1, 22, 2)
        err = np.linalg.norm(project(X, cam) - uv, axis=-1)
        assert np.isfinite(err).sum() > 1000
        assert np.nanmax(err) < 1e-6
        # Dropping the skew (what OpenCV does) costs up to about a pixel or more.
        no_skew = cam.replace(K=cam.K * np.array([[1, 0, 1], [1, 1, 1], [1, 1, 1]]))
        if abs(cam.K[0, 1]) > 5:
            assert np.nanmax(np.linalg.norm(project(X, no_skew) - uv, axis=-1)) > 0.5


def test_dannce_errors(tmp_path):
    import scipy.io

    p = tmp_path / "x.mat"
    scipy.io.savemat(p, {"foo": np.eye(2)})
    with pytest.raises(CalibrationFormatError, match="no 'params' variable"):
        load_calibration(p)
    with pytest.raises(CalibrationFormatError, match="can be read but not written"):
        save_calibration(make_circle_rig(1), tmp_path / "y.mat")


def test_metadata_none_and_numpy_values_survive(tmp_path):
    rig = make_circle_rig(2).with_metadata(
        note=None,
        scale=np.float32(2.0),
        flag=np.bool_(True),
        origin=np.zeros(3),
        nested={"a": None, "b": 1},
    )
    p = tmp_path / "c.toml"
    write_calibration_toml(rig, p)
    md = load_calibration(p).metadata
    assert "note" not in md and md["scale"] == 2.0 and md["flag"] is True
    assert md["origin"] == [0.0, 0.0, 0.0] and md["nested"] == {"b": 1}


def test_atomic_outputs_get_normal_permissions(tmp_path):
    import os

    from freipose.io import atomic

    p = tmp_path / "x.txt"
    atomic.atomic_write_text(p, "hi")
    assert p.stat().st_mode & 0o777 == 0o666 & ~atomic._UMASK  # not mkstemp's 0600
    os.chmod(p, 0o640)
    atomic.atomic_write_text(p, "again")  # an existing file keeps its mode
    assert p.stat().st_mode & 0o777 == 0o640 and p.read_text() == "again"
    with pytest.raises(RuntimeError), atomic.atomic_path(p) as tmp:
        tmp.write_text("half")
        raise RuntimeError("killed")
    assert p.read_text() == "again" and sorted(q.name for q in tmp_path.iterdir()) == ["x.txt"]

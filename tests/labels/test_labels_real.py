"""Importers on real files from other tools: every label preserved exactly."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner

from freipose.cli.main import cli
from freipose.geometry import reprojection_errors
from freipose.io.calibration import save_calibration
from freipose.io.labels import read_labels_h5
from freipose.labels.dlc import read_dlc_table
from freipose.labels.formats import IMPORTERS
from freipose.labels.importing import ImportOptions, build_labelset
from freipose.labels.mapping import NameMapping
from freipose.testing import make_circle_rig


def test_dlc_project_exact(shared_data, tmp_path):
    proj = shared_data / "dlc-openfield-pranav"
    base = proj / "labeled-data" / "m4s1" / "CollectedData_Pranav"
    h5, csv = read_dlc_table(base.with_suffix(".h5")), read_dlc_table(base.with_suffix(".csv"))
    assert h5.index == csv.index and h5.columns == csv.columns
    np.testing.assert_array_equal(h5.values, csv.values)
    ref = pd.read_csv(base.with_suffix(".csv"), header=[0, 1, 2], index_col=0)
    out = tmp_path / "labels.h5"
    r = CliRunner().invoke(cli, ["labels", "import", "--format", "dlc", str(proj), "-o", str(out)])
    assert r.exit_code == 0, r.output
    lab = read_labels_h5(out)
    assert lab.keypoints == ("snout", "leftear", "rightear", "tailbase")
    assert lab.cameras == ("m4s1",) and len(lab) == 116
    np.testing.assert_array_equal(lab.frame_index, [int(p.split("img")[1][:4]) for p in ref.index])
    for k, bp in enumerate(lab.keypoints):
        np.testing.assert_array_equal(lab.points2d[:, 0, k, 0], ref[("Pranav", bp, "x")].to_numpy())
        np.testing.assert_array_equal(lab.points2d[:, 0, k, 1], ref[("Pranav", bp, "y")].to_numpy())
    np.testing.assert_allclose(lab.points2d[0, 0, 0], [21.521, 265.428])
    assert np.isnan(lab.points3d).all()  # one camera, no calibration: 2D only


@pytest.mark.parametrize("which", ["markerless_mouse_1", "markerless_mouse_2"])
def test_dannce_exact_and_reprojects_with_skew(shared_data, which):
    from freipose.io.matlab import load_mat

    path = shared_data / "dannce-markerless-mouse" / which / "label3d_dannce.mat"
    srcs = IMPORTERS["dannce"]([path], None, NameMapping(), None)
    lab = build_labelset(srcs, ImportOptions(), path.parent / "labels.h5")
    mat = load_mat(path)
    for c, d in enumerate(mat["labelData"]):
        n = d["data_2d"].shape[0]
        np.testing.assert_array_equal(lab.points2d[:, c], d["data_2d"].reshape(n, 22, 2))
        np.testing.assert_array_equal(lab.points3d, d["data_3d"].reshape(n, 22, 3))
        np.testing.assert_array_equal(lab.frame_index, d["data_frame"].ravel())
    rig = lab.rig_for(which)
    assert abs(rig["Camera1"].K[0, 1]) > 1  # the skew term is kept
    err = reprojection_errors(lab.points3d, np.moveaxis(lab.points2d, 1, 2), rig)
    assert np.isfinite(err).sum() == 6 * np.isfinite(lab.points3d).all(-1).sum()
    assert np.nanmax(err) < 1e-6


def test_dannce_names_from_mapping_file(shared_data, tmp_path):
    path = shared_data / "dannce-markerless-mouse" / "markerless_mouse_1" / "label3d_dannce.mat"
    mf = tmp_path / "m.toml"
    mf.write_text('[keypoints]\njoint1 = "EarL"\njoint2 = "EarR"\njoint3 = "Snout"\n')
    out = tmp_path / "l.h5"
    r = CliRunner().invoke(
        cli,
        ["labels", "import", "--format", "dannce", str(path), "--mapping", str(mf), "-o", str(out)],
    )
    assert r.exit_code == 0, r.output
    lab = read_labels_h5(out)
    assert lab.keypoints[:4] == ("EarL", "EarR", "Snout", "joint4")


def test_sleap_multiview_session_exact(shared_data, tmp_path):
    sio = pytest.importorskip("sleap_io")
    d = shared_data / "sleap-8cam-2mice"
    slp = d / "min_session_frame_groups.slp"
    out = tmp_path / "labels.h5"
    r = CliRunner().invoke(cli, ["labels", "import", "--format", "sleap", str(slp), "-o", str(out)])
    assert r.exit_code == 0, r.output
    lab = read_labels_h5(out)
    assert len(lab) == 6 and sorted(lab.cameras) == sorted(
        ["back", "backL", "mid", "midL", "side", "sideL", "top", "topL"]
    )
    # every user point, compared camera by camera (the video order is reversed in the file)
    src = sio.load_slp(str(slp))
    sess = src.sessions[0]
    n_checked = 0
    for lf in src.labeled_frames:
        cam = sess.get_camera(lf.video).name
        assert cam in lf.video.filename
        for inst in lf.instances:
            if type(inst).__name__ != "Instance":
                continue
            pts = inst.numpy()
            rows = np.flatnonzero(lab.frame_index == lf.frame_idx)
            hit = [
                i
                for i in rows
                if np.array_equal(lab.points2d[i, lab.cameras.index(cam)], pts, equal_nan=True)
            ]
            assert len(hit) == 1
            n_checked += 1
    assert n_checked == 42
    # videos resolved by base name, calibration from the session
    assert set(lab.sessions[lab.session[0]].videos) == set(lab.cameras)
    rig = lab.rig_for(lab.session[0])
    err = reprojection_errors(lab.points3d, np.moveaxis(lab.points2d, 1, 2), rig)
    print(
        f"SLEAP 8-cam: reprojection mean {np.nanmean(err):.2f} px, "
        f"median {np.nanmedian(err):.2f} px over {np.isfinite(err).sum()} point-views"
    )
    assert np.isfinite(err).sum() == 504
    assert 3.5 < np.nanmean(err) < 5.0 and 2.5 < np.nanmedian(err) < 3.5  # reference 4.35 / 3.02
    # the training reader opens those videos
    from freipose.nn.dataset import MultiViewDataset

    s = MultiViewDataset(out, cache_size=2)[0]
    assert len(s["images"]) == 8 and s["images"][0].shape == (1024, 1280, 3)


def test_jarvis_coco_with_yaml_calibration(tmp_path, rng):
    rig = make_circle_rig(3)
    kps = ["Snout", "EarL", "EarR"]
    X = rng.normal(0, 30, (4, 3, 3))
    uv = rig.project(X)
    images, anns = [], []
    for i in range(4):
        for c, cam in enumerate(rig.names):
            iid = len(images) + 1
            images.append(
                {
                    "id": iid,
                    "file_name": f"Rec1/{cam}/Frame_{10 * i}.jpg",
                    "width": 640,
                    "height": 480,
                }
            )
            kp = np.concatenate([uv[i, c], np.full((3, 1), 2.0)], 1)
            if i == 1 and c == 2:
                kp[0] = 0  # unlabeled
            anns.append(
                {
                    "id": iid,
                    "image_id": iid,
                    "category_id": 1,
                    "keypoints": kp.ravel().tolist(),
                    "bbox": [0, 0, 10, 10],
                }
            )
    calib = {}
    for cam in rig.names:
        save_calibration(
            rig.subset([cam]), tmp_path / "calib_params" / "Rec1" / f"{cam}.yaml", "jarvis"
        )
        calib[cam] = f"calib_params/Rec1/{cam}.yaml"
    coco = {
        "images": images,
        "annotations": anns,
        "categories": [{"id": 1, "name": "Mouse", "num_keypoints": 3, "keypoints": kps}],
        "calibrations": {"Rec1": calib},
    }
    (tmp_path / "annotations").mkdir()
    (tmp_path / "annotations" / "instances_train.json").write_text(json.dumps(coco))
    srcs = IMPORTERS["jarvis"]([tmp_path], None, NameMapping(), None)
    lab = build_labelset(srcs, ImportOptions(), tmp_path / "l.h5")
    np.testing.assert_array_equal(lab.frame_index, [0, 10, 20, 30])
    expect = uv.copy()
    expect[1, 2, 0] = np.nan
    np.testing.assert_allclose(lab.points2d, expect, atol=1e-9)
    np.testing.assert_allclose(lab.points3d, X, atol=1e-6)


def test_sleap_multiview_session_keeps_the_animals(shared_data, tmp_path):
    """Both mice triangulated, each row's animal the one of its SLEAP instance group."""
    sio = pytest.importorskip("sleap_io")
    slp = shared_data / "sleap-8cam-2mice" / "min_session_frame_groups.slp"
    out = tmp_path / "labels.h5"
    r = CliRunner().invoke(cli, ["labels", "import", "--format", "sleap", str(slp), "-o", str(out)])
    assert r.exit_code == 0, r.output
    lab = read_labels_h5(out)
    assert lab.individuals == ("track_0", "track_1")
    assert list(lab.individual) == ["track_0", "track_1"] * 3
    assert list(lab.frame_index) == [0, 0, 1, 1, 2, 2]
    rs = sio.load_slp(str(slp)).sessions[0]
    for i in range(len(lab)):
        group = rs.frame_groups[int(lab.frame_index[i])].instance_groups
        mine = [g for g in group if {x.track.name for x in g.instance_by_camera.values()}
                == {lab.individual[i]}]  # fmt: skip
        assert len(mine) == 1
        for cam, inst in mine[0].instance_by_camera.items():
            c = lab.cameras.index(cam.name)
            np.testing.assert_array_equal(lab.points2d[i, c], inst.numpy())
        # both animals triangulated: most keypoints of every row have a 3D point
        assert np.isfinite(lab.points3d[i]).all(-1).sum() >= 12
    # the two animals are apart in 3D (not one animal twice)
    gap = np.nanmedian(np.linalg.norm(lab.points3d[0::2] - lab.points3d[1::2], axis=-1))
    assert gap > 20
    logged = [m for m in r.output.splitlines() if "reprojection error" in m]
    assert any("track_0" in m for m in logged) and any("track_1" in m for m in logged)
    print("\n".join(logged))

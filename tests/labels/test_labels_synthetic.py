"""Synthetic sessions with known cameras: triangulation accuracy, check, round trips,
merge/split and bad inputs (each a clear error, nothing written)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from freipose.cli.main import cli
from freipose.io.calibration_toml import write_calibration_toml
from freipose.io.labels import LabelSet, SessionInfo, read_labels_h5, write_labels_h5
from freipose.io.video import VideoWriter
from freipose.labels.check import check_labels, infer_symmetry
from freipose.labels.dlc import dlc_table_text
from freipose.labels.formats import IMPORTERS
from freipose.labels.importing import (
    ImportOptions,
    LabelImportError,
    SourceLabels,
    build_labelset,
    triangulate_labels,
)
from freipose.labels.mapping import MappingError, NameMapping, load_mapping_file
from freipose.labels.ops import LabelsOpError, export_labels, merge_labels, split_labels
from freipose.testing import make_circle_rig

KPS = ["nose", "ear_left", "ear_right", "paw_left", "paw_right", "tail"]


def _truth(rng: np.random.Generator, n: int) -> np.ndarray:
    centre = rng.uniform(-150, 150, (n, 1, 3)) * [1, 1, 0] + [0, 0, 40]
    body = np.array(
        [[60, 0, 20], [35, 15, 30], [35, -15, 30], [20, 20, 0], [20, -20, 0], [-70, 0, 10]]
    )
    return centre + body + rng.normal(0, 4, (n, len(KPS), 3))


def _session(rng, n=40, planted=5, noise=1.0):
    # a lab-like rig: six 1280x1024 cameras, f = 1000 px, 0.7 m from the arena centre
    rig = make_circle_rig(6, radius=700, height=500, size=(1280, 1024), focal=1000)
    X = _truth(rng, n)
    uv = rig.project(X)  # (n, C, K, 2)
    uv = uv + rng.normal(0, noise, uv.shape)
    spots = set()
    while len(spots) < planted:
        spots.add((int(rng.integers(n)), int(rng.integers(6)), int(rng.integers(len(KPS)))))
    for i, c, k in spots:
        a = rng.uniform(0, 2 * np.pi)
        uv[i, c, k] += 50 * np.array([np.cos(a), np.sin(a)])
    return rig, X, uv, sorted(spots)


def _write_dlc(root: Path, session: str, rig, uv, frames) -> list[Path]:
    folders = []
    for c, cam in enumerate(rig.names):
        d = root / "labeled-data" / f"{session}_{cam}"
        d.mkdir(parents=True)
        index = [f"labeled-data/{d.name}/img{f:04d}.png" for f in frames]
        (d / "CollectedData_Tester.csv").write_text(dlc_table_text("Tester", KPS, index, uv[:, c]))
        folders.append(d)
    return folders


def test_triangulation_accuracy_and_check_finds_planted(tmp_path, rng):
    rig, X, uv, planted = _session(rng)
    frames = np.arange(0, 400, 10)
    _write_dlc(tmp_path, "run1", rig, uv, frames)
    write_calibration_toml(rig, tmp_path / "calibration.toml")
    out = tmp_path / "labels.h5"
    res = CliRunner().invoke(
        cli,
        [
            "labels",
            "import",
            "--format",
            "dlc",
            str(tmp_path),
            "--calibration",
            str(tmp_path / "calibration.toml"),
            "-o",
            str(out),
        ],
    )
    assert res.exit_code == 0, res.output
    lab = read_labels_h5(out)
    assert lab.cameras == tuple(rig.names) and lab.keypoints == tuple(KPS)
    np.testing.assert_array_equal(lab.frame_index, frames)
    np.testing.assert_array_equal(lab.points2d, uv)  # every 2D label exactly
    err = np.linalg.norm(lab.points3d - X, axis=-1)
    print(f"triangulated 3D error: median {np.median(err):.3f} mm, max {err.max():.3f} mm")
    assert np.median(err) < 1.0 and err.max() < 3.0
    result = check_labels(lab)
    top = {
        (s.index, lab.cameras.index(s.camera), lab.keypoints.index(s.keypoint))
        for s in result.suspicious[: len(planted)]
        if s.kind == "reprojection"
    }
    assert top == set(planted)
    assert all(s.severity > 3 for s in result.suspicious[: len(planted)])
    # the CLI writes the report; the planted labels are the first CSV rows
    rep = tmp_path / "report"
    res = CliRunner().invoke(cli, ["labels", "check", str(out), "--report", str(rep)])
    assert res.exit_code == 0, res.output
    rows = (rep / "suspicious.csv").read_text().splitlines()
    assert rows[0].startswith("rank,kind,severity")
    assert len(rows) - 1 >= len(planted)
    assert (rep / "errors_by_keypoint.png").is_file() and (rep / "errors_by_camera.png").is_file()
    n_err = len((rep / "reprojection_errors.csv").read_text().splitlines()) - 1
    assert n_err == np.isfinite(lab.points2d).all(-1).sum()


def test_swapped_left_right_and_limb_length(rng):
    from freipose.skeleton import skeleton_from_dict

    rig, X, uv, _ = _session(rng, n=30, planted=0)
    uv[3, 2, [1, 2]] = uv[3, 2, [2, 1]]  # ears swapped in one view
    X_bad = X.copy()
    p2 = uv.copy()
    p2[7, :, 5] = rig.project(X[7, 5][None] + [0, 0, 200])[:, 0]  # a consistent but absurd tail
    X_bad[7, 5] += [0, 0, 200]
    lab = LabelSet(
        np.array(["s"] * 30, dtype=object),
        np.arange(30),
        p2,
        X_bad,
        rig.names,
        tuple(KPS),
        {"s": SessionInfo(rig)},
    )
    skel = skeleton_from_dict(
        {
            "name": "t",
            "keypoints": KPS,
            "limbs": [["nose", "tail"], ["ear_left", "ear_right"]],
            "symmetry": [["ear_left", "ear_right"], ["paw_left", "paw_right"]],
        }
    )
    assert infer_symmetry(KPS) == [(1, 2), (3, 4)]
    res = check_labels(lab, skel)
    kinds = {(s.kind, s.index) for s in res.suspicious}
    assert ("swapped", 3) in kinds and ("limb_length", 7) in kinds
    assert res.suspicious[0].kind in ("swapped", "limb_length")


def _labelset(rng, sessions=("a", "b", "c"), n=6):
    rig = make_circle_rig(4)
    parts = []
    for s in sessions:
        X = _truth(rng, n)
        uv = rig.project(X) + rng.normal(0, 0.5, (n, 4, len(KPS), 2))
        uv[0, 1, 2] = np.nan
        parts.append(
            LabelSet(
                np.array([s] * n, dtype=object),
                np.arange(n) * 7 + 3,
                uv,
                X,
                rig.names,
                tuple(KPS),
                {s: SessionInfo(rig, {}, 30.0)},
            )
        )
    return merge_labels(parts)


@pytest.mark.parametrize("fmt", ["dlc", "anipose", "freipose"])
def test_export_import_round_trip(tmp_path, rng, fmt):
    lab = _labelset(rng)
    out = tmp_path / "export"
    files = export_labels(lab, out, fmt, tmp_path)
    assert files and all(f.is_file() for f in files)
    rig = lab.rig_for("a")
    if fmt == "dlc":
        srcs = IMPORTERS["dlc"]([out], rig, NameMapping(), None)
        opts = ImportOptions(calibration=rig)
    elif fmt == "anipose":
        srcs = IMPORTERS["anipose"]([out / s / "pose-2d" for s in "abc"], None, NameMapping(), None)
        opts = ImportOptions()
    else:
        srcs = IMPORTERS["freipose"]([out / s for s in "abc"], None, NameMapping(), None)
        opts = ImportOptions(skeleton_keypoints=tuple(KPS))
    back = build_labelset(srcs, opts, tmp_path / "back.h5")
    order = np.lexsort((back.frame_index, back.session))
    back = back.select(order)
    np.testing.assert_array_equal(back.session, lab.session)
    np.testing.assert_array_equal(back.frame_index, lab.frame_index)
    assert back.keypoints == lab.keypoints and tuple(back.cameras) == tuple(lab.cameras)
    if fmt == "dlc":  # CSV text: repr() round trips floats exactly
        np.testing.assert_array_equal(back.points2d, lab.points2d)
    else:
        np.testing.assert_allclose(back.points2d, lab.points2d, rtol=0, atol=1e-9)
    if fmt == "freipose":  # anno.json keeps the 3D labels (in metres)
        np.testing.assert_allclose(back.points3d, lab.points3d, rtol=0, atol=1e-9)
    else:  # 2D-only formats: the 3D labels are the triangulation of the same 2D labels
        expect, _ = triangulate_labels(lab.points2d, rig)
        np.testing.assert_allclose(back.points3d, expect, rtol=0, atol=1e-6)
    for s in "abc":
        b, a = back.rig_for(s), lab.rig_for(s)
        assert all(b[c].allclose(a[c]) for c in a.names)


def test_merge_split_never_share_sessions(tmp_path, rng):
    lab = _labelset(rng, sessions=("m1_a", "m1_b", "m2_a", "m2_b", "m3_a"))
    tr, ev, groups = split_labels(lab, 0.4, seed=1)
    assert not set(tr.session) & set(ev.session)
    assert len(tr) + len(ev) == len(lab) and abs(len(ev) / len(lab) - 0.4) <= 0.1
    tr, ev, groups = split_labels(lab, 0.3, group_pattern=r"^m\d")
    assert not {s[:2] for s in tr.session} & {s[:2] for s in ev.session}
    with pytest.raises(LabelsOpError, match="at least two sessions"):
        split_labels(lab.select(lab.session == "m1_a"), 0.3)
    with pytest.raises(LabelsOpError, match="labeled in both"):
        merge_labels([lab, lab])
    # CLI: merge rebases video paths, split writes both files
    vid = tmp_path / "v" / "cam0.mkv"
    with VideoWriter(vid, 5, (32, 24)) as w:
        for _ in range(40):
            w.write(np.zeros((24, 32, 3), np.uint8))
    a = lab.select(lab.session == "m1_a")
    a = LabelSet(
        a.session,
        a.frame_index,
        a.points2d,
        a.points3d,
        a.cameras,
        a.keypoints,
        {"m1_a": SessionInfo(a.rig_for("m1_a"), {"cam0": "v/cam0.mkv"})},
    )
    write_labels_h5(a, tmp_path / "a.h5")
    write_labels_h5(lab.select(lab.session != "m1_a"), tmp_path / "b.h5")
    out = tmp_path / "sub" / "all.h5"
    r = CliRunner().invoke(
        cli, ["labels", "merge", str(tmp_path / "a.h5"), str(tmp_path / "b.h5"), "-o", str(out)]
    )
    assert r.exit_code == 0, r.output
    merged = read_labels_h5(out)
    assert merged.sessions["m1_a"].videos["cam0"] == "../v/cam0.mkv"
    assert len(merged) == len(lab)
    r = CliRunner().invoke(
        cli,
        [
            "labels",
            "split",
            str(out),
            "--eval",
            "0.3",
            "--eval-sessions",
            "m1_a,m3_a",
            "-o",
            str(tmp_path / "tr.h5"),
            str(tmp_path / "ev.h5"),
        ],
    )
    assert r.exit_code == 0, r.output
    ev = read_labels_h5(tmp_path / "ev.h5")
    assert sorted(set(ev.session)) == ["m1_a", "m3_a"]
    assert ev.sessions["m1_a"].videos["cam0"] == "v/cam0.mkv"


def test_mapping_file_and_options(tmp_path, rng):
    rig, X, uv, _ = _session(rng, n=5, planted=0)
    _write_dlc(tmp_path, "r", rig, uv, range(5))
    mf = tmp_path / "map.toml"
    mf.write_text('[keypoints]\nnose = "Nose"\ntail = ""\n[cameras]\n')
    m = load_mapping_file(mf)
    assert m.keypoint("nose") == "Nose" and m.keypoint("tail") == ""
    write_calibration_toml(rig, tmp_path / "calibration.toml")
    out = tmp_path / "l.h5"
    r = CliRunner().invoke(
        cli,
        [
            "labels",
            "import",
            "--format",
            "dlc",
            str(tmp_path),
            "--calibration",
            str(tmp_path / "calibration.toml"),
            "--mapping",
            str(mf),
            "--map",
            "paw_left=PawL",
            "-o",
            str(out),
        ],
    )
    assert r.exit_code == 0, r.output
    lab = read_labels_h5(out)
    assert lab.keypoints == ("Nose", "ear_left", "ear_right", "PawL", "paw_right")
    np.testing.assert_array_equal(lab.points2d[:, :, 3], uv[:, :, 3])
    bad = tmp_path / "bad.toml"
    bad.write_text("[points]\na = 'b'\n")
    with pytest.raises(MappingError, match="unknown tables"):
        load_mapping_file(bad)


def _invoke_import(args, out):
    r = CliRunner().invoke(cli, ["labels", "import", *args, "-o", str(out)])
    assert r.exit_code != 0
    assert not out.exists()  # nothing written on error
    return r.output


def test_bad_inputs_clear_errors_nothing_written(tmp_path, rng):
    rig, X, uv, _ = _session(rng, n=5, planted=0)
    folders = _write_dlc(tmp_path / "p", "r", rig, uv, range(5))
    cal = tmp_path / "calibration.toml"
    write_calibration_toml(rig, cal)
    out = tmp_path / "out" / "labels.h5"
    # body parts that do not match the skeleton
    msg = _invoke_import(
        ["--format", "dlc", str(tmp_path / "p"), "--calibration", str(cal), "--skeleton", "rat"],
        out,
    )
    assert "none of the source keypoints" in msg and "nose" in msg
    msg = _invoke_import(
        [
            "--format",
            "dlc",
            str(tmp_path / "p"),
            "--calibration",
            str(cal),
            "--skeleton",
            "rat",
            "--map",
            "nose=Nose",
        ],
        out,
    )
    assert "are not in the skeleton" in msg and "'ear_left'" in msg and "CollectedData" in msg
    # camera missing from the calibration
    small = tmp_path / "small.toml"
    write_calibration_toml(rig.subset(["cam0", "cam1"]), small)
    msg = _invoke_import(["--format", "dlc", *map(str, folders), "--calibration", str(small)], out)
    assert "r_cam2" in msg and "none of the calibration cameras" in msg
    msg = _invoke_import(
        [
            "--format",
            "dlc",
            *map(str, folders[:3]),
            "--camera-map",
            "r_cam2=cam2",
            "--calibration",
            str(small),
        ],
        out,
    )
    assert "cam2" in msg and "not in the calibration" in msg and "small.toml" in msg
    # truncated .h5
    h5 = folders[0] / "CollectedData_Tester.h5"
    src = Path("/work/shared/data/dlc-openfield-pranav/labeled-data/m4s1/CollectedData_Pranav.h5")
    raw = src.read_bytes() if src.is_file() else b"\x89HDF\r\n\x1a\n" + bytes(5000)
    h5.write_bytes(raw[: len(raw) // 3])
    msg = _invoke_import(["--format", "dlc", str(h5)], out)
    assert "CollectedData_Tester.h5" in msg and "truncated" in msg
    h5.unlink()
    # NaN-only rows
    uv2 = uv.copy()
    uv2[2] = np.nan
    d = tmp_path / "nan" / "labeled-data" / "r_cam0"
    d.mkdir(parents=True)
    (d / "CollectedData_T.csv").write_text(
        dlc_table_text(
            "T", KPS, [f"labeled-data/r_cam0/img{f:04d}.png" for f in range(5)], uv2[:, 0]
        )
    )
    msg = _invoke_import(["--format", "dlc", str(d)], out)
    assert "CollectedData_T.csv" in msg and "no labeled keypoint" in msg and "img0002" in msg
    r = CliRunner().invoke(
        cli, ["labels", "import", "--format", "dlc", str(d), "--skip-empty", "-o", str(out)]
    )
    assert r.exit_code == 0 and len(read_labels_h5(out)) == 4
    out.unlink()
    # frame index past the video's end
    vids = tmp_path / "p" / "videos"
    with VideoWriter(vids / "r_cam0.mkv", 5, (32, 24)) as w:
        for _ in range(3):
            w.write(np.zeros((24, 32, 3), np.uint8))
    msg = _invoke_import(["--format", "dlc", str(folders[0]), "--camera-map", "r_cam0=cam0"], out)
    assert "r_cam0.mkv" in msg and "frame 4" in msg and "3 frames" in msg
    # export into a non-empty folder fails without touching it
    lab = _labelset(rng)
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "keep.txt").write_text("x")
    with pytest.raises(LabelsOpError, match="new or empty"):
        export_labels(lab, tmp_path / "full", "dlc", tmp_path)
    assert [p.name for p in (tmp_path / "full").iterdir()] == ["keep.txt"]


def test_freipose_json_metres_and_visibility(tmp_path, rng):
    from freipose.io.calibration import save_calibration

    rig = make_circle_rig(3)
    X = _truth(rng, 2)
    uv = rig.project(X)
    anno = {}
    for i, f in enumerate([12, 40]):
        e = {
            c: {"kp_uv": uv[i, j].tolist(), "vis": [1.0] * len(KPS)}
            for j, c in enumerate(rig.names)
        }
        e["cam1"]["vis"][0] = 0.0
        e["xyz"] = (X[i] / 1000).tolist()
        e["vis3d"] = [1.0] * len(KPS)
        anno[f"{f:08d}.png"] = e
    d = tmp_path / "labeled_set0"
    d.mkdir()
    (d / "anno.json").write_text(json.dumps(anno))
    save_calibration(rig, tmp_path / "M.json", "mjson")
    srcs = IMPORTERS["freipose"]([d], None, NameMapping(), None)
    lab = build_labelset(srcs, ImportOptions(), tmp_path / "l.h5")
    np.testing.assert_array_equal(lab.frame_index, [12, 40])
    np.testing.assert_allclose(lab.points3d, X, atol=1e-9)
    assert np.isnan(lab.points2d[:, 1, 0]).all() and not lab.visible2d[:, 1, 0].any()
    with pytest.raises(LabelImportError, match="unnamed keypoints but the skeleton has 12"):
        build_labelset(
            srcs,
            ImportOptions(skeleton_keypoints=tuple(f"k{i}" for i in range(12))),
            tmp_path / "l.h5",
        )


def test_dlc_multi_animal_rows_per_individual(tmp_path):
    d = tmp_path / "labeled-data" / "r_cam0"
    d.mkdir(parents=True)
    (d / "CollectedData_T.csv").write_text(
        "scorer,T,T,T,T,T,T,T,T\n"
        "individuals,m1,m1,m1,m1,m2,m2,m2,m2\n"
        "bodyparts,nose,nose,tail,tail,nose,nose,tail,tail\n"
        "coords,x,y,x,y,x,y,x,y\n"
        "labeled-data/r_cam0/img007.png,1.5,2.5,3,4,,,,\n"
        "labeled-data/r_cam0/img009.png,5,6,7,8,9.25,10,11,12\n"
    )
    srcs = IMPORTERS["dlc"]([d], None, NameMapping(), None)
    lab = build_labelset(srcs, ImportOptions(), tmp_path / "l.h5")
    assert lab.keypoints == ("nose", "tail") and len(lab) == 3
    np.testing.assert_array_equal(lab.frame_index, [7, 9, 9])
    np.testing.assert_array_equal(
        lab.points2d[:, 0], [[[1.5, 2.5], [3, 4]], [[5, 6], [7, 8]], [[9.25, 10], [11, 12]]]
    )


def test_dlc_export_import_cli_gives_usable_training_set(tmp_path, rng):
    # labels.h5 with videos -> export --format dlc -> import the labeled-data folders without
    # videos: the image folders become the cameras' frame sources (frame = image position)
    from freipose.nn.dataset import MultiViewDataset

    rig = make_circle_rig(3, size=(64, 48), focal=60)
    n_frames, fi = 12, np.array([2, 5, 9])
    uv = rig.project(_truth(rng, len(fi)) * 0.2)
    uv[1, 2] = np.nan  # camera 2 has no label in frame 5: its folder still gets that image
    videos = {}
    frames = rng.integers(0, 256, (len(rig.names), n_frames, 48, 64, 3), dtype=np.uint8)
    for c, cam in enumerate(rig.names):
        with VideoWriter(tmp_path / f"{cam}.mkv", 30.0, (64, 48)) as w:
            for img in frames[c]:
                w.write(img)
        videos[cam] = f"{cam}.mkv"
    lab = LabelSet(
        np.array(["s"] * len(fi), dtype=object),
        fi,
        uv,
        np.full((len(fi), len(KPS), 3), np.nan),
        rig.names,
        tuple(KPS),
        {"s": SessionInfo(rig, videos, 30.0)},
    )
    write_labels_h5(lab, tmp_path / "x.h5")
    write_calibration_toml(rig, tmp_path / "cal.toml")
    run = CliRunner().invoke
    r = run(cli, ["labels", "export", str(tmp_path / "x.h5"), "--format", "dlc", "-o",
                  str(tmp_path / "dlc")])  # fmt: skip
    assert r.exit_code == 0, r.output
    folders = sorted(str(p) for p in (tmp_path / "dlc" / "labeled-data").iterdir())
    assert len(folders) == 3
    args = ["labels", "import", "--format", "dlc", *folders, "--calibration",
            str(tmp_path / "cal.toml"), "-o", str(tmp_path / "y.h5")]  # fmt: skip
    r = run(cli, args)
    assert r.exit_code == 0, r.output
    back = read_labels_h5(tmp_path / "y.h5")
    assert set(back.sessions["s"].videos) == set(rig.names)
    np.testing.assert_array_equal(back.frame_index, np.arange(len(fi)))  # image positions
    np.testing.assert_array_equal(back.points2d, uv)
    ds = MultiViewDataset(tmp_path / "y.h5")
    ds.validate()
    for i in range(len(fi)):
        sample = ds[i]
        assert list(sample["camera_names"]) == list(rig.names)
        for c in range(len(rig.names)):  # lossless video -> PNG: the very same pixels
            np.testing.assert_array_equal(sample["images"][c], frames[c, fi[i]])
    ds.close()


def test_build_labelset_leaves_its_sources_unchanged(tmp_path, rng):
    # positional keypoints named by the skeleton: the names go on a copy, not the caller's source
    rig = make_circle_rig(3)
    uv = rig.project(_truth(rng, 4))
    src = SourceLabels(
        "s.json", "s", list(rig.names), [f"kp{i}" for i in range(len(KPS))], np.arange(4),
        uv, calibration=rig, positional=True,
    )  # fmt: skip
    lab = build_labelset([src], ImportOptions(skeleton_keypoints=tuple(KPS)), tmp_path / "l.h5")
    assert lab.keypoints == tuple(KPS)
    assert src.keypoints == [f"kp{i}" for i in range(len(KPS))]

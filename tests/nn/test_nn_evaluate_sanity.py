"""freipose eval's failure modes (collapsed and swapped pairs, bone lengths) and references."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from click.testing import CliRunner
from nn_toydata import toy_samples, write_toy_labels

from freipose.io.labels import read_labels_h5, write_labels_h5
from freipose.nn.evaluate import jpe
from freipose.nn.failure_modes import failure_modes, format_failure_modes
from freipose.nn.references import (
    AT_HELD_OUT,
    AT_TRAINING,
    beats_reference_warnings,
    median_pose,
    reference_predictions,
    reference_summary,
)
from freipose.skeleton import Skeleton, infer_symmetry, left_right_pairs, load_skeleton

RAT = load_skeleton("rat")


def _rat_poses(n: int, seed: int = 0) -> np.ndarray:
    """(n, 12, 3) rat-like poses: a fixed shape, mirrored left/right, moved and turned."""
    rng = np.random.default_rng(seed)
    base = rng.normal(0, 40, (RAT.num_keypoints, 3))
    for a, b in left_right_pairs(RAT):  # mirror pairs over 30 mm apart across x = 0
        base[a, 0] = -15 - abs(base[a, 0])
        base[b] = base[a] * [-1, 1, 1]
    out = []
    for _ in range(n):
        t = rng.uniform(-np.pi, np.pi)
        R = np.array([[np.cos(t), -np.sin(t), 0], [np.sin(t), np.cos(t), 0], [0, 0, 1]])
        out.append(base @ R.T + rng.uniform(-200, 200, 3))
    return np.array(out)


def test_left_right_pairs_order_left_first_and_inferred_from_names():
    pairs = left_right_pairs(RAT)
    assert len(pairs) == 5
    assert all("Left" in RAT.keypoints[a] and "Right" in RAT.keypoints[b] for a, b in pairs)
    sk = Skeleton("s", ("nose", "EarL", "EarR", "left_paw", "right_paw"))
    assert left_right_pairs(sk) == ((1, 2), (3, 4)) == tuple(infer_symmetry(sk.keypoints))


def test_collapsed_pairs_are_warned_and_exact_poses_are_not():
    gt = _rat_poses(30)
    collapsed = gt.copy()
    for a, b in left_right_pairs(RAT):
        mid = (gt[:, a] + gt[:, b]) / 2
        collapsed[:, a], collapsed[:, b] = mid - 1.0, mid + 1.0
    bad = failure_modes(collapsed, gt, RAT, "net")
    assert [p["collapsed"] for p in bad["pairs"]] == [True] * 5
    assert len(bad["warnings"]) == 5 and all(
        w.startswith("WARNING: net: ") for w in bad["warnings"]
    )
    assert "collapse" in bad["warnings"][0] and "Ear Left and Ear Right" in bad["warnings"][0]
    for p in bad["pairs"]:
        assert p["predicted_mm"] == pytest.approx(np.sqrt(12), abs=1e-6)
        assert p["true_mm"] > 30
    rng = np.random.default_rng(1)
    good = failure_modes(gt + rng.normal(0, 2.0, gt.shape), gt, RAT, "net")
    assert good["warnings"] == []
    assert not any(p["collapsed"] for p in good["pairs"])
    assert all(p["swap_rate"] == 0 for p in good["pairs"])
    lines = format_failure_modes(bad)
    assert any("COLLAPSED" in ln for ln in lines) and lines[-1] == bad["warnings"][-1]


def test_swap_rate_and_bone_lengths():
    gt = _rat_poses(20, seed=2)
    swapped = gt.copy()
    swapped[:10] = gt[:10][:, RAT.mirror_permutation()]  # half of the instants swapped
    res = failure_modes(swapped, gt, RAT)
    assert [p["swap_rate"] for p in res["pairs"]] == [0.5] * 5
    assert sum("swapped" in w for w in res["warnings"]) == 5
    c = gt.mean(1, keepdims=True)
    big = failure_modes(c + 1.2 * (gt - c), gt, RAT)
    assert len(big["bones"]) == len(RAT.limbs)
    assert big["bones"][6]["bone"] == "mean(Ear Right, Ear Left) - Tail"
    for b in big["bones"]:
        assert b["predicted_mm"] == pytest.approx(1.2 * b["true_mm"], rel=1e-9)
    missing = gt.copy()
    missing[:, 0] = np.nan  # Ear Right never predicted: its pair has no instant
    p0 = failure_modes(missing, gt, RAT)["pairs"][0]
    assert p0["instants"] == 0 and p0["predicted_mm"] is None and not p0["collapsed"]
    assert p0["missing"] == "not predicted"


def test_pairs_bones_and_keypoints_never_labeled_say_so(tmp_path):
    gt = _rat_poses(12, seed=4)
    pred = gt + np.random.default_rng(5).normal(0, 1.0, gt.shape)
    paws = [RAT.keypoints.index(k) for k in ("Paw Front Left", "Paw Front Right")]
    gt[:, paws] = np.nan  # the front paws never labeled
    modes = failure_modes(pred, gt, RAT, "net")
    lines = format_failure_modes(modes)
    assert "    Paw Front Left / Paw Front Right: not labeled" in lines
    assert "    mean(Ear Right, Ear Left) - Paw Front Right: not labeled" in lines
    assert "    Ear Left / Ear Right: not labeled" not in lines
    assert not any("nan" in ln.lower() for ln in lines), lines
    assert modes["warnings"] == []
    from freipose.nn.evaluate import Sanity, write_report

    sanity = Sanity({"net": modes}, {}, {}, [])
    write_report(tmp_path, {"net": jpe(pred, gt)}, RAT.keypoints, sanity)
    text = (tmp_path / "metrics.json").read_text()
    assert "NaN" not in text
    m = json.loads(text)["net"]
    pair = next(p for p in m["failure_modes"]["pairs"] if p["left"] == "Paw Front Left")
    assert pair["predicted_mm"] is None and pair["true_mm"] is None and pair["swap_rate"] is None
    assert pair["missing"] == "not labeled"
    assert m["per_keypoint"]["Paw Front Left"] == {
        "median": None, "p30": None, "p70": None, "n": 0, "note": "not labeled"
    }  # fmt: skip
    csv = (tmp_path / "jpe_per_keypoint.csv").read_text()
    assert "net,Paw Front Left,,,,0\n" in csv and "nan" not in csv


def test_references_place_the_median_pose_at_the_centres():
    rng = np.random.default_rng(3)
    shape = rng.normal(0, 30, (5, 3))
    train = shape + rng.uniform(-100, 100, (40, 1, 3))
    train[::3, 1] = np.nan  # unlabeled keypoints shift the centre of those instants
    pose, centre = median_pose(train)
    full = ~np.isnan(train).any((1, 2))
    np.testing.assert_allclose(pose, shape - shape.mean(0), atol=1e-9)
    held = shape + rng.uniform(-100, 100, (6, 1, 3))
    refs = reference_predictions(train, held)
    np.testing.assert_allclose(jpe(refs[AT_HELD_OUT], held), 0, atol=1e-9)
    want = np.linalg.norm(held.mean(1) - centre, axis=-1)
    np.testing.assert_allclose(jpe(refs[AT_TRAINING], held), np.repeat(want[:, None], 5, 1))
    assert full.sum() < len(train)
    summary = reference_summary({n: jpe(p, held) for n, p in refs.items()})
    assert summary[AT_HELD_OUT]["median_mm"] == pytest.approx(0, abs=1e-9)
    assert summary[AT_HELD_OUT]["n"] == 30
    warn = beats_reference_warnings(
        {"voxel_P1": 5.0, "baseline": 0.0}, {AT_HELD_OUT: {"median_mm": 2.0}}
    )
    assert len(warn) == 1 and "voxel_P1" in warn[0] and "does not beat" in warn[0]
    with pytest.raises(ValueError):
        reference_predictions(train, held[:, :4])


def test_eval_command_prints_references_and_failure_modes(tmp_path):
    from freipose.cli.main import cli

    write_toy_labels(tmp_path / "train", toy_samples(4, seed=1))
    write_toy_labels(tmp_path / "eval", toy_samples(3, seed=5))
    cfg = tmp_path / "cfg.toml"
    cfg.write_text(
        '[data]\nlabels = "train/labels.h5"\n[model]\npreset = "tiny"\n[schedule]\nsteps = 1\n'
    )
    runner = CliRunner()
    r = runner.invoke(cli, ["-q", "train", str(cfg), "--out", str(tmp_path / "run")])
    assert r.exit_code == 0, r.output
    ev = ["-q", "eval", str(tmp_path / "run" / "model.pt"), str(tmp_path / "eval" / "labels.h5")]
    r = runner.invoke(cli, [*ev, "-o", str(tmp_path / "ev")])
    assert r.exit_code == 0, r.output
    assert f"{tmp_path / 'train' / 'labels.h5'} (the labels" in r.output
    assert f"reference, {AT_HELD_OUT} (no network): median JPE" in r.output
    m = json.loads((tmp_path / "ev" / "metrics.json").read_text())
    assert set(m["references"]) == {AT_HELD_OUT, AT_TRAINING}
    assert m["voxel_P1"]["failure_modes"] == {"pairs": [], "bones": [], "warnings": []}
    # one network: P0 and P1 are not compared with each other, each with the reference
    assert [(c["a"], c["b"]) for c in m["comparisons"]] == [
        ("voxel_P0", AT_HELD_OUT),
        ("voxel_P1", AT_HELD_OUT),
    ]
    assert "paired comparisons on the same 3 held-out instants" in r.output
    ref = m["references"][AT_HELD_OUT]["median_mm"]
    beaten = m["voxel_P1"]["overall"]["median"] < ref
    assert ("WARNING: voxel_P1" in r.output) != beaten
    # an explicit --train-labels wins; without any, eval says there are no references
    r = runner.invoke(cli, [*ev, "-o", str(tmp_path / "ev2"), "--train-labels",
                            str(tmp_path / "eval" / "labels.h5")])  # fmt: skip
    assert r.exit_code == 0 and "(given with --train-labels)" in r.output, r.output
    other = read_labels_h5(tmp_path / "eval" / "labels.h5")
    write_labels_h5(
        dataclasses.replace(other, keypoints=("a", "b", "c", "d", "e")), tmp_path / "o.h5"
    )
    r = runner.invoke(
        cli, [*ev, "-o", str(tmp_path / "ev4"), "--train-labels", str(tmp_path / "o.h5")]
    )
    assert r.exit_code != 0 and "the training labels have keypoints ['a'" in r.output, r.output
    assert "Traceback" not in r.output
    (tmp_path / "train" / "labels.h5").rename(tmp_path / "moved.h5")
    r = runner.invoke(cli, [*ev, "-o", str(tmp_path / "ev3")])
    assert r.exit_code == 0 and "no sanity references" in r.output, r.output
    assert "references" not in json.loads((tmp_path / "ev3" / "metrics.json").read_text())

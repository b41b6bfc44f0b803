"""Frame selection for labeling: least confident first, diverse, gaps, exclusions, CLI."""

from __future__ import annotations

import csv
import sys
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from freipose.cli.labels_select import select as select_cmd
from freipose.io.poses import PoseData
from freipose.io.session import discover_sessions
from freipose.labels.select import read_selection_csv, select_frames
from freipose.predict.run import predict_session

# the synthetic two-blob session and its estimator are the prediction tests' helpers
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "predict"))
from predict_helpers import BlobEstimator, make_session  # noqa: E402


def _data(rng, T=200):
    """Two postures (A for t < 100, B after), the animal moving around; confidence dips."""
    a = rng.normal(0, 30, (4, 3))
    b = rng.normal(0, 30, (4, 3))
    poses = np.where(np.arange(T)[:, None, None] < 100, a, b) + rng.normal(0, 1, (T, 4, 3))
    poses = poses + rng.uniform(-300, 300, (T, 1, 3))  # position must not matter
    conf = np.full((T, 4), 0.9)
    conf[40:45] = 0.2  # uncertain stretch in posture A
    conf[150] = 0.5  # uncertain frame in posture B
    conf[170:172] = 0.3
    poses[60] = np.nan
    conf[60] = 0
    return PoseData(poses, conf, ("a", "b", "c", "d"), np.arange(T) + 1000, 30.0)


def test_select_least_confident_diverse_with_gaps(rng):
    d = _data(rng)
    sel = select_frames(d, 4, min_gap=10, session="s")
    fi = sel.frame_index - 1000
    assert fi[0] == 60 and not sel.found[0]  # not found = most uncertain
    assert 40 <= fi[1] < 45  # the uncertain stretch
    assert np.any((fi == 170) | (fi == 171))  # the uncertain frame of the other posture
    assert np.all(np.diff(np.sort(fi)) > 10)
    assert sel.confidence[0] == 0
    # exclusion: frames near already labeled ones are not proposed
    sel2 = select_frames(d, 3, min_gap=10, exclude=[1000 + 42, 1060])
    f2 = sel2.frame_index - 1000
    assert not np.any(np.abs(f2 - 42) <= 10) and not np.any(np.abs(f2 - 60) <= 10)
    with pytest.raises(ValueError, match="at least 1"):
        select_frames(d, 0)


def test_select_several_animals_by_the_least_confident_animal(rng):
    """Poses with an animal axis: a frame is as uncertain as its least confident animal,
    and a frame where one animal was not found comes first."""
    one = _data(rng)
    other = _data(rng)
    poses = np.stack([one.poses, other.poses], axis=1)  # (T, 2, K, 3)
    conf = np.stack([one.confidence, other.confidence], axis=1)
    conf[:, 1] = 0.9  # the second animal is sure everywhere ...
    conf[120:123, 1] = 0.1  # ... except here, where the first one is sure
    poses[:, 1][60] = other.poses[61]  # the second animal found where the first is not
    conf[60, 1] = 0.9
    d = PoseData(poses.astype(np.float32), conf.astype(np.float32), one.keypoints,
                 one.frame_index, 30.0, individuals=("a0", "a1"))  # fmt: skip
    sel = select_frames(d, 3, min_gap=10, session="s")
    fi = sel.frame_index - 1000
    assert fi[0] == 60 and not sel.found[0]  # one animal missing: not found
    assert 120 <= fi[1] < 123 and sel.confidence[1] == pytest.approx(0.1)
    assert 40 <= fi[2] < 45  # the first animal's uncertain stretch


def test_select_caps_at_available_frames(rng, caplog):
    T = 30
    d = PoseData(rng.normal(0, 30, (T, 2, 3)), np.full((T, 2), 0.5), ("a", "b"), np.arange(T), 30)
    sel = select_frames(d, 10, min_gap=10)
    assert 2 <= len(sel) <= 3 and np.all(np.diff(np.sort(sel.frame_index)) > 10)
    assert "only" in caplog.text


def test_labels_select_command(tmp_path):
    folder = tmp_path / "rec"
    make_session(folder, 40, absent=(7, 8))
    (s,) = discover_sessions([folder])
    predict_session(s, BlobEstimator(), tmp_path / "poses", batch_size=8, progress=False)
    out = tmp_path / "sel.csv"
    args = [str(folder), "--poses-dir", str(tmp_path / "poses"), "--n", "3", "--min-gap", "5",
            "-o", str(out), "--extract", str(tmp_path / "png")]  # fmt: skip
    res = CliRunner().invoke(select_cmd, args, catch_exceptions=False)
    assert res.exit_code == 0, res.output
    rows = read_selection_csv(out)
    assert len(rows) == 3 and rows[0][0] == "rec" and rows[0][1] in (7, 8)
    with open(out) as f:
        assert next(csv.reader(f)) == ["session", "frame_index", "rank", "mean_confidence", "found"]
    pngs = sorted((tmp_path / "png" / "rec" / "cam1").glob("*.png"))
    assert [int(p.stem) for p in pngs] == sorted(i for _, i in rows)
    # no predictions and no model: a clear error
    res = CliRunner().invoke(select_cmd, [str(folder), "--poses-dir", str(tmp_path / "none")])
    assert res.exit_code != 0 and "--model" in res.output

"""``freipose labels split --by time``: contiguous held-out blocks with a gap, one recording."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

from freipose.cli.main import cli
from freipose.io.labels import LabelSet, SessionInfo, read_labels_h5, write_labels_h5
from freipose.labels.ops import LabelsOpError, split_by_time


def _labels(frames_by_session: dict[str, np.ndarray]) -> LabelSet:
    sess = np.concatenate([[s] * len(f) for s, f in frames_by_session.items()])
    fi = np.concatenate(list(frames_by_session.values()))
    n = len(fi)
    p3 = np.zeros((n, 2, 3)) + fi[:, None, None]
    return LabelSet(
        sess, fi, np.zeros((n, 1, 2, 2)), p3, ("cam0",), ("a", "b"),
        {s: SessionInfo(None, {"cam0": f"{s}/cam0.mp4"}, 50.0) for s in frames_by_session},
    )  # fmt: skip


def _check_gap(tr: LabelSet, ev: LabelSet, gap: int) -> None:
    for s in set(ev.session):
        a = tr.frame_index[tr.session == s]
        b = ev.frame_index[ev.session == s]
        if len(a) and len(b):
            assert np.abs(a[:, None] - b[None]).min() >= gap


def test_one_recording_blocks_and_gap():
    lab = _labels({"rec": np.arange(0, 1200, 10)})  # 120 instants, every 10th frame
    tr, ev, blocks = split_by_time(lab, eval_fraction=0.25, gap=50, blocks=1, seed=3)
    assert len(ev) == 30
    fe = np.sort(ev.frame_index)
    assert np.all(np.diff(fe) == 10)  # one contiguous block of labeled instants
    _check_gap(tr, ev, 50)
    # the instants within 50 frames of the block (4 or 5 on each side) are in neither part
    assert len(tr) + len(ev) < len(lab) and len(lab) - len(tr) - len(ev) <= 10
    assert blocks == [f"rec frames {fe[0]}-{fe[-1]}"]
    tr2, ev2, _ = split_by_time(lab, 0.25, 50, blocks=3, seed=3)
    starts = np.flatnonzero(np.diff(np.sort(ev2.frame_index)) > 10)
    assert len(starts) == 2  # three separate blocks
    _check_gap(tr2, ev2, 50)


def test_every_session_split_and_errors():
    lab = _labels({"a": np.arange(0, 200, 2), "b": np.arange(0, 100, 1)})
    tr, ev, blocks = split_by_time(lab, 0.2, 10, 1, 0)
    assert set(ev.session) == {"a", "b"} and len(blocks) == 2
    assert (ev.session == "a").sum() == 20 and (ev.session == "b").sum() == 20
    _check_gap(tr, ev, 10)
    with pytest.raises(LabelsOpError, match="--gap"):
        split_by_time(lab, 0.5, 1000, 1, 0)
    with pytest.raises(LabelsOpError, match="--eval"):
        split_by_time(lab, 1.5, 10, 1, 0)


def test_cli_split_by_time(tmp_path):
    lab = _labels({"rec": np.arange(0, 600, 5)})
    write_labels_h5(lab, tmp_path / "labels.h5")
    (tmp_path / "out").mkdir()
    res = CliRunner().invoke(
        cli,
        ["labels", "split", str(tmp_path / "labels.h5"), "--by", "time", "--gap", "25",
         "--eval", "0.3", "-o", str(tmp_path / "out" / "train.h5"), str(tmp_path / "ev.h5")],
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    assert "dropped" in res.output and "rec frames" in res.output
    tr = read_labels_h5(tmp_path / "out" / "train.h5")
    ev = read_labels_h5(tmp_path / "ev.h5")
    _check_gap(tr, ev, 25)
    assert tr.sessions["rec"].videos["cam0"] == "../rec/cam0.mp4"  # rebased
    assert tr.sessions["rec"].fps == 50.0
    help_text = CliRunner().invoke(cli, ["labels", "split", "--help"]).output
    assert "near-copies" in help_text and "--by time" in help_text


def test_several_animals_per_frame_stay_together():
    # two animals per labeled frame: a held-out block takes whole frames, never one animal
    lab = _labels({"rec": np.repeat(np.arange(3), 2)})
    for frac in (0.34, 0.5, 0.67):
        for seed in range(4):
            tr, ev, _ = split_by_time(lab, frac, gap=1, blocks=1, seed=seed)
            assert not set(tr.frame_index) & set(ev.frame_index)
            assert len(ev) == 2 * len(set(ev.frame_index))
            assert len(ev) == 2 * int(round(frac * 3))

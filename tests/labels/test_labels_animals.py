"""Labels of several animals: identities of SLEAP instance groups, merging by animal."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

from freipose.io.labels import LabelSet, read_labels_h5, write_labels_h5
from freipose.labels.importing import LabelImportError
from freipose.labels.ops import LabelsOpError, merge_labels
from freipose.labels.sleap import group_identity


@dataclass
class _Named:
    name: str


@dataclass
class _Inst:
    track: _Named | None


@dataclass
class _Group:
    instance_by_camera: dict
    identity: _Named | None = None
    metadata: dict = field(default_factory=dict)


def test_group_identity_identity_then_track_then_name():
    where = Path("x.slp")
    tracked = {"cam0": _Inst(_Named("mouse_a")), "cam1": _Inst(_Named("mouse_a"))}
    assert group_identity(_Group(tracked, _Named("Alice")), 0, where, 3) == "Alice"
    assert group_identity(_Group(tracked), 0, where, 3) == "mouse_a"
    loose = {"cam0": _Inst(None)}
    assert group_identity(_Group(loose, metadata={"name": "g7"}), 1, where, 3) == "g7"
    assert group_identity(_Group(loose), 1, where, 3) == "instance_group_1"
    mixed = {"cam0": _Inst(_Named("a")), "cam1": _Inst(_Named("b"))}
    with pytest.raises(LabelImportError, match="one group is one animal"):
        group_identity(_Group(mixed), 2, where, 3)


def _labels(frames, individual) -> LabelSet:
    n = len(frames)
    return LabelSet(
        np.array(["s"] * n, dtype=object), np.asarray(frames), np.zeros((n, 1, 2, 2)),
        np.full((n, 2, 3), np.nan), ("cam0",), ("nose", "tail"), individual=individual,
    )  # fmt: skip


def test_individual_written_read_selected_and_merged(tmp_path):
    a = _labels([0, 0, 1], np.array(["m1", "m2", "m1"], dtype=object))
    write_labels_h5(a, tmp_path / "a.h5")
    back = read_labels_h5(tmp_path / "a.h5")
    assert list(back.individual) == ["m1", "m2", "m1"] and back.individuals == ("m1", "m2")
    assert list(back.select([1, 2]).individual) == ["m2", "m1"]
    b = _labels([1], np.array(["m2"], dtype=object))
    merged = merge_labels([a, b])
    assert list(merged.individual) == ["m1", "m2", "m1", "m2"]
    with pytest.raises(LabelsOpError, match="animal 'm1'"):
        merge_labels([a, _labels([1], np.array(["m1"], dtype=object))])
    single = _labels([5], None)
    assert list(merge_labels([a, single]).individual) == ["m1", "m2", "m1", ""]
    assert merge_labels([single, _labels([6], None)]).individual is None

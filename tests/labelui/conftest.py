"""Fixtures of the labeling tool's tests: a small synthetic session with known truth."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np
import pytest

from freipose.io.labels import LabelSet, read_labels_h5
from freipose.io.poses import PoseData, write_poses_h5
from freipose.labelui.startup import open_store
from freipose.labelui.store import LabelStore
from freipose.synth import SceneConfig, generate_session


@dataclass(frozen=True)
class SynthSession:
    """A rendered synthetic session: its folder, calibration and true labels (every frame)."""

    folder: Path
    calibration: Path
    truth: LabelSet


@pytest.fixture(scope="session")
def synth_session(tmp_path_factory: pytest.TempPathFactory) -> SynthSession:
    """Three 320x256 cameras (with lens distortion), 12 frames."""
    out = tmp_path_factory.mktemp("labelui") / "rat1"
    cfg = SceneConfig(n_cameras=3, frames=12, size=(320, 256), seed=3, motion_blur=False)
    paths = generate_session(out, cfg, workers=1, progress=False)
    return SynthSession(out, paths.calibration, read_labels_h5(paths.labels))


@pytest.fixture(scope="session")
def pair(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, LabelSet]:
    """Two rats, three 320x256 cameras, 6 frames: folder, calibration, true labels."""
    out = tmp_path_factory.mktemp("animals") / "pair"
    cfg = SceneConfig(n_cameras=3, frames=6, size=(320, 256), seed=3, animals=2,
                      motion_blur=False)  # fmt: skip
    paths = generate_session(out, cfg, workers=1, progress=False)
    return out, paths.calibration, read_labels_h5(paths.labels)


@pytest.fixture
def store(synth_session: SynthSession, tmp_path: Path) -> Iterator[LabelStore]:
    """A store over four evenly spread instants, writing tmp_path/labels.h5."""
    yield open_store([synth_session.folder], synth_session.calibration, "rat",
                     tmp_path / "labels.h5", per_session=4)  # fmt: skip


@pytest.fixture
def poses_dir(synth_session: SynthSession, tmp_path: Path) -> Path:
    """``rat1.poses.h5``: the truth + 2 mm, confidence 0.9 (frame 6: 0.1, frame 2: 0.4)."""
    t = synth_session.truth
    folder = tmp_path / "poses"
    conf = np.full((12, 12), 0.9, np.float32)
    conf[6], conf[2] = 0.1, 0.4
    poses = t.points3d.astype(np.float32) + 2.0
    path = folder / "rat1.poses.h5"
    write_poses_h5(PoseData(poses, conf, t.keypoints, np.arange(12), 25.0), path)
    with h5py.File(path, "a") as f:  # as `freipose predict` marks a finished file
        f.attrs["complete"] = True
    return folder

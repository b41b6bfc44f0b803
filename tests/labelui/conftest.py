"""Fixtures of the labeling tool's tests: a small synthetic session with known truth."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from freipose.io.labels import LabelSet, read_labels_h5
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


@pytest.fixture
def store(synth_session: SynthSession, tmp_path: Path) -> Iterator[LabelStore]:
    """A store over four evenly spread instants, writing tmp_path/labels.h5."""
    yield open_store([synth_session.folder], synth_session.calibration, "rat",
                     tmp_path / "labels.h5", per_session=4)  # fmt: skip

"""The prediction loop of several animals: each animal's cube at its own centre, frames
missing in some cameras, and a killed run resumed to the same file."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from predict_helpers import h5_equal, small_rig

from freipose.geometry import CameraRig
from freipose.predict.estimator import Estimate

BASE = Path(__file__).parents[2] / "freipose" / "models" / "voxel_small.pt"


@dataclass
class _CentreNetwork:
    """Stands in for the network: every keypoint at the cube centre, one call recorded."""

    keypoints: tuple[str, ...] = ("a", "b")
    provenance: dict | None = None

    def __post_init__(self) -> None:
        self.calls: list[tuple[int, tuple[str, ...]]] = []
        self.animals: list = []

    def predict_at(self, frames, rig: CameraRig, centers: np.ndarray, animals=None) -> Estimate:
        b, c = len(frames), len(rig)
        assert all(len(f) == c for f in frames)
        self.calls.append((b, tuple(rig.names)))
        self.animals.append(animals)
        # each pass moves the poses by 1 mm, so that a pass's input tells which pass made it
        shift = 0.0 if animals is None else animals[0][:, :1, :] + 1.0 - centers[:, None]
        poses = np.repeat(np.asarray(centers, np.float64)[:, None], 2, axis=1) + shift
        found = np.isfinite(centers).all(-1)
        return Estimate(poses, np.where(found[:, None], 1.0, 0.0) * np.ones((b, 2)),
                        np.zeros((b, c, 2, 2)), np.ones((b, c, 2)), np.zeros((b, c, 4)),
                        centers)  # fmt: skip


def test_each_animal_gets_its_own_centre_and_missing_views_their_own_call() -> None:
    from freipose.predict.animals_run import estimate_animals

    rig = small_rig(3)
    b_n, a_n = 4, 2
    images = [np.zeros((b_n, 8, 8, 3), np.uint8) for _ in range(3)]
    valid = np.ones((b_n, 3), bool)
    valid[1, 2] = False  # frame 1: camera 2 not decoded
    valid[3, 1:] = False  # frame 3: one camera left
    centres = np.arange(b_n * a_n * 3, dtype=np.float64).reshape(b_n, a_n, 3)
    centres[2, 1] = np.nan  # animal 1 not tracked in frame 2
    net = _CentreNetwork()
    ests, ran = estimate_animals(net, images, valid, rig, centres)  # type: ignore[arg-type]
    assert len(ests) == a_n and ran.tolist() == [True, True, True, False]
    for a in range(a_n):
        for b in range(3):
            expect = centres[b, a]
            np.testing.assert_array_equal(ests[a].center[b], expect.astype(np.float32))
        assert np.isnan(ests[a].poses[3]).all()  # too few views: not run
    assert np.isnan(ests[1].poses[2]).all() and (ests[1].confidence[2] == 0).all()
    assert np.isfinite(ests[0].poses[2]).all()
    # one call with all cameras (frames 0 and 2 of both animals), one without camera 2
    assert sorted(net.calls) == [(2, ("cam0", "cam1")), (4, ("cam0", "cam1", "cam2"))]
    assert np.isnan(ests[0].points2d[1, 2]).all() and (ests[0].confidence2d[1, 2] == 0).all()


def test_painted_passes_get_the_previous_pass_poses() -> None:
    """model.mask_others: the network again mask_passes times, each animal's views painted at
    the previous pass's poses of itself and of the other animals of its frame."""
    from types import SimpleNamespace

    from freipose.predict.animals_run import estimate_animals

    rig = small_rig(3)
    b_n, a_n = 3, 2
    images = [np.zeros((b_n, 8, 8, 3), np.uint8) for _ in range(3)]
    centres = np.arange(b_n * a_n * 3, dtype=np.float64).reshape(b_n, a_n, 3)
    net = _CentreNetwork()
    net.model = SimpleNamespace(cfg=SimpleNamespace(mask_others=True, mask_passes=2))  # type: ignore[attr-defined]
    ests, _ = estimate_animals(net, images, np.ones((b_n, 3), bool), rig, centres)  # type: ignore[arg-type]
    assert len(net.calls) == 3 and net.animals[0] is None
    for p, (own, others) in enumerate(net.animals[1:], start=1):
        for a in range(a_n):
            for b in range(b_n):
                row = a * b_n + b
                np.testing.assert_allclose(own[row, 0], centres[b, a] + (p - 1))
                np.testing.assert_allclose(others[row, 0, 0], centres[b, 1 - a] + (p - 1))
    np.testing.assert_allclose(ests[1].poses[2, 0], centres[2, 1] + 2)  # the last pass's


@pytest.mark.slow
def test_a_killed_run_of_several_animals_resumes_to_the_same_file(tmp_path, monkeypatch, caplog):
    from freipose.io.poses import resume_command, run_state
    from freipose.io.session import discover_sessions
    from freipose.predict.animals_run import predict_animal_sessions
    from freipose.predict.network import DetectorSpec
    from freipose.predict.writer import IncrementalPosesWriter, partial_path
    from freipose.synth import SceneConfig, generate_session

    if not BASE.is_file():
        pytest.skip(f"the shipped base model {BASE} is not in this checkout")
    cfg = SceneConfig(frames=16, fps=6, seed=6, n_cameras=4, size=(256, 208), animals=2,
                      coat_mix="different")  # fmt: skip
    paths = generate_session(tmp_path / "pair", cfg, workers=1, progress=False)
    (session,) = discover_sessions([paths.folder], paths.calibration)
    spec = DetectorSpec("bgsub", bg_samples=16)

    def run(out: Path) -> Path:
        (res,) = predict_animal_sessions([session], BASE, spec, out, 2, batch_size=4,
                                         device="cpu", chunk_frames=8, progress=False)  # fmt: skip
        return res.path

    reference = run(tmp_path / "whole")
    real_add = IncrementalPosesWriter.add_animals
    calls = []

    def killed_after_two(self, *args, **kwargs):
        if len(calls) == 3:
            raise KeyboardInterrupt
        calls.append(1)
        real_add(self, *args, **kwargs)

    monkeypatch.setattr(IncrementalPosesWriter, "add_animals", killed_after_two)
    with pytest.raises(KeyboardInterrupt):
        run(tmp_path / "killed")
    monkeypatch.undo()
    part = partial_path(tmp_path / "killed" / "pair.poses.h5")
    import h5py

    with h5py.File(part, "r") as f:
        assert int(f.attrs["completed_frames"]) == 8
    command = resume_command(part, run_state(part))
    assert "--method bgsub --bg-samples 16" in command and "--animals 2" in command, command
    with caplog.at_level("INFO", logger="freipose.predict.writer"):
        resumed = run(tmp_path / "killed")
    assert "resuming after 8 of 16 frames" in caplog.text
    assert h5_equal(resumed, reference) == []


def test_tracking_leaves_out_views_whose_frame_is_missing() -> None:
    from freipose.detect.base import Candidates
    from freipose.predict.animals import track_recording

    rig = small_rig(3)
    seen: list[str] = []

    class OneBox:
        def propose(self, images, cameras):
            seen.extend(cameras)
            assert all(isinstance(im, np.ndarray) for im in images)
            return [Candidates(np.array([[60.0, 40, 100, 80]]), np.ones(1)) for _ in images]

    img = np.zeros((120, 160, 3), np.uint8)
    frames = [[img, img, img], [img, None, img], [None, None, img]]
    res = track_recording(frames, rig, OneBox(), 1, 10.0, chunk=2)
    assert seen == ["cam0", "cam1", "cam2", "cam0", "cam2", "cam2"]
    assert [len(c[1].boxes) for c in res.candidates] == [1, 0, 0]
    assert [len(c[0].boxes) for c in res.candidates] == [1, 1, 0]
    assert res.tracks.centers.shape == (3, 1, 3)

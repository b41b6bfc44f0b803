"""Box sources without training: background subtraction and fixed boxes."""

import numpy as np
import pytest

from freipose.detect import (
    BackgroundSubtractor,
    ConsistencyConfig,
    FixedBoxes,
    detect_multiview_batch,
)
from freipose.detect.boxes import box_centers, box_iou
from freipose.geometry import triangulate


def test_bgsub_finds_the_animal_without_training(scene, scene_rig):
    frames = scene["frames"]
    sources = {n: [frames[t][i] for t in range(len(frames))] for i, n in enumerate(scene_rig.names)}
    bg = BackgroundSubtractor.fit(sources, n_samples=12, margin=0.0)  # vs tight silhouettes
    # The median over frames in which the animal moves is the empty background.
    for i, n in enumerate(scene_rig.names):
        diff = np.abs(bg._bg[n] - bg._prep(scene["backgrounds"][i])[0])
        assert np.median(diff) < 2.0
    dets = detect_multiview_batch(frames, scene_rig, bg, ConsistencyConfig(cube_size=300.0))
    gt = scene["silhouettes"]
    ious = np.array([box_iou(d.boxes, g) for d, g in zip(dets, gt)])
    assert np.mean(ious > 0.5) >= 0.95, ious
    for d, g in zip(dets, gt):
        assert d.n_agree == len(scene_rig)
        assert np.linalg.norm(d.center - triangulate(box_centers(g), scene_rig)) < 10.0


def test_bgsub_empty_frame_and_errors(scene, scene_rig):
    names = scene_rig.names
    bg = BackgroundSubtractor({n: scene["backgrounds"][i] for i, n in enumerate(names)})
    empty = bg.propose([scene["backgrounds"][0]], [names[0]])
    assert len(empty[0]) == 0
    found = bg.propose([scene["frames"][0][0]], [names[0]])[0]
    assert len(found) >= 1 and found.scores[0] == 1.0
    with pytest.raises(KeyError, match="no background"):
        bg.propose([scene["frames"][0][0]], ["nope"])
    with pytest.raises(ValueError, match="does not match"):
        bg.propose([np.zeros((10, 10, 3), np.uint8)], [names[0]])
    with pytest.raises(ValueError, match="no frames"):
        BackgroundSubtractor.fit({"cam0": [scene["backgrounds"][0]]}, frames=range(5, 9))


def test_fixed_boxes_toml(tmp_path):
    p = tmp_path / "boxes.toml"
    p.write_text("[boxes]\ncam0 = [10, 20, 110, 90]\ncam1 = [0, 0, 50.5, 40]\n")
    fb = FixedBoxes.from_toml(p)
    out = fb.propose([None, None, None], ["cam0", "cam1", "cam9"])
    np.testing.assert_allclose(out[0].boxes[0], [10, 20, 110, 90])
    assert out[0].scores[0] == 1.0 and len(out[2]) == 0
    fb.check_cameras(["cam1", "x"])
    with pytest.raises(ValueError, match="none of the session"):
        fb.check_cameras(["a", "b"])
    p.write_text("[boxes]\ncam0 = [10, 20, 5, 90]\n")
    with pytest.raises(ValueError, match="x1 > x0"):
        FixedBoxes.from_toml(p)
    p.write_text("cam0 = [1, 2, 3, 4]\n")
    with pytest.raises(ValueError, match=r"\[boxes\] table"):
        FixedBoxes.from_toml(p)
    p.write_text("[boxes\n")
    with pytest.raises(ValueError, match="not valid TOML"):
        FixedBoxes.from_toml(p)
    with pytest.raises(FileNotFoundError):
        FixedBoxes.from_toml(tmp_path / "missing.toml")


def test_bgsub_on_a_synthetic_session(tmp_path):
    """The rendered rat (fur, shadow, motion blur, noise) is found without any training."""
    synth = pytest.importorskip("freipose.synth")
    from freipose.detect.evaluate import evaluate_source
    from freipose.nn.dataset import MultiViewDataset

    cfg = synth.SceneConfig(frames=32, fps=8, seed=4, n_cameras=4, size=(192, 160),
                            video_format=".mkv")  # fmt: skip
    paths = synth.generate_session(tmp_path / "s", cfg, workers=1, progress=False)
    ds = MultiViewDataset(paths.labels)
    samples = [ds[i] for i in range(len(ds))]
    names = list(samples[0]["camera_names"])
    frames = {n: [s["images"][i] for s in samples] for i, n in enumerate(names)}
    bg = BackgroundSubtractor.fit(frames)
    m = evaluate_source(bg, samples, consistency=ConsistencyConfig(cube_size=400.0))
    assert m.n_views > 100
    assert m.recall >= 0.7, m.summary()
    assert m.center_rate >= 0.95 and m.median_center_error < 25.0, m.summary()


def test_automatic_threshold_is_numpys_median_plus_six_mad():
    """The histogram median and MAD of the grey difference equal np.median's, even or odd."""
    from freipose.detect.fallback import _median_and_mad

    rng = np.random.default_rng(0)
    for n in range(100):
        h, w = rng.integers(1, 40, 2)
        grey = (rng.random((h, w)) ** rng.uniform(0.2, 5) * 255).astype(np.uint8)
        if n % 4 == 0:
            grey[:] = rng.integers(0, 256)  # one level: MAD 0
        d = grey.astype(np.float32)
        med = float(np.median(d))
        mad = float(np.median(np.abs(d - med)))
        assert _median_and_mad(grey, 6 * 1.4826) == med + 6 * 1.4826 * mad, (h, w)

"""Crops, crop cameras and augmentation compensation (freipose.nn.data)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from nn_toydata import COLORS, toy_samples

from freipose.nn.config import AugmentConfig, ConfigError, config_from_dict
from freipose.nn.data import SampleError, StepBatchSampler, collate_prepared, prepare_sample
from freipose.nn.geometry import project_affine

GEOMETRIC_ONLY = AugmentConfig(
    rotation=25.0,
    zoom=(0.8, 1.2),
    shift=6.0,
    hue=0.0,
    brightness=0.0,
    contrast=0.0,
    blur_sigma=0.0,
    noise=0.0,
    salt_pepper=0.0,
    center_jitter=15.0,
)


def test_augmented_crop_cameras_match_warped_images_and_labels():
    cfg = config_from_dict({"model": {"preset": "small", "crop_size": 64}}).model
    s = toy_samples(1, cams=3)[0]
    rng = np.random.default_rng(3)
    p = prepare_sample(s, cfg, GEOMETRIC_ONLY, rng)
    b = collate_prepared([p])
    uv, front = project_affine(
        torch.tensor(s["points3d"][None], dtype=torch.float32), b["K"], b["R"], b["t"], b["dist"]
    )
    # the crop cameras (rotation/zoom folded in) reproduce the warped 2D labels ...
    np.testing.assert_allclose(uv[0].numpy(), p["points2d"], atol=1e-2)
    # ... and the warped images: the disc colour lies under the projected nearest keypoint
    hits = 0
    for v in range(3):
        img = ((p["images"][v].transpose(1, 2, 0) + 0.5) * 255).round()
        depth = (s["points3d"] @ s["rig"][v].R.T + s["rig"][v].t)[:, 2]
        k = int(np.argmin(depth))
        x, y = np.round(p["points2d"][v, k]).astype(int)
        if 0 <= x < 64 and 0 <= y < 64:
            np.testing.assert_allclose(img[y, x], COLORS[k], atol=40)
            hits += 1
    assert hits >= 2
    assert p["visible2d"].any() and np.isfinite(p["center"]).all()
    # the voxel grid turns about the world z axis; unaugmented samples keep it upright
    rz = p["grid_rotation"]
    np.testing.assert_allclose(rz @ rz.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(rz[2], [0, 0, 1])
    assert not np.allclose(rz, np.eye(3))
    np.testing.assert_array_equal(b["grid_rotation"][0].numpy(), rz.astype(np.float32))
    np.testing.assert_array_equal(prepare_sample(s, cfg)["grid_rotation"], np.eye(3))


def test_crop_fraction_crops_the_middle_of_the_cube():
    from dataclasses import replace

    from freipose.nn.geometry import voxel_offsets

    cfg = config_from_dict({"model": {"preset": "small", "crop_size": 64}}).model
    s = toy_samples(1, cams=3)[0]
    # (the baseline always crops the whole cube: it has no other view for a keypoint outside)
    for frac, kind, cube in ((1.0, "voxel", 1.0), (0.6, "voxel", 0.6), (0.6, "baseline", 1.0)):
        p = prepare_sample(s, replace(cfg, crop_fraction=frac, kind=kind))
        b = collate_prepared([p])
        # the corners of the crop_fraction cube project onto the crop's edges
        corners = torch.tensor(
            [[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=torch.float32
        ) * (0.5 * cube * cfg.cube_size) + torch.tensor(p["center"], dtype=torch.float32)
        pts = torch.cat([corners, torch.tensor(p["center"], dtype=torch.float32)[None]])
        uv, _ = project_affine(pts[None], b["K"], b["R"], b["t"], b["dist"])
        half = (uv[0, :, :8] - uv[0, :, 8:]).abs().amax(dim=(1, 2))  # (V,)
        torch.testing.assert_close(half, torch.full((3,), 32.0), atol=0.05, rtol=0)
    # with 0.6 the whole cube's corner voxels fall outside the voxel network's crops
    p = prepare_sample(s, replace(cfg, crop_fraction=0.6))
    b = collate_prepared([p])
    outer = voxel_offsets(8, cfg.cube_size)[:1] + torch.tensor(p["center"], dtype=torch.float32)
    uv, _ = project_affine(outer[None], b["K"], b["R"], b["t"], b["dist"])
    assert not torch.all((uv >= -0.5) & (uv <= 63.5))


def test_sample_errors_and_padding():
    cfg = config_from_dict({"model": {"preset": "tiny"}}).model
    s = toy_samples(2, cams=3)
    bad = dict(s[0], points3d=np.full((5, 3), np.nan), mask3d=np.zeros(5, bool))
    with pytest.raises(SampleError, match="no 3D label"):
        prepare_sample(bad, cfg)
    with pytest.raises(SampleError, match="no calibration"):
        prepare_sample(dict(s[0], rig=None), cfg)
    two = dict(
        s[1],
        rig=s[1]["rig"].subset([0, 1]),
        images=s[1]["images"][:2],
        points2d=s[1]["points2d"][:2],
        visible2d=s[1]["visible2d"][:2],
    )
    b = collate_prepared([prepare_sample(s[0], cfg), prepare_sample(two, cfg)])
    assert b["images"].shape[:2] == (2, 3)
    assert b["view_mask"].tolist() == [[True, True, True], [True, True, False]]
    assert not b["visible2d"][1, 2].any()


def test_step_sampler_is_deterministic_and_splits_batches():
    full = StepBatchSampler(range(7), 4, 6, seed=1)
    batches = list(full)
    assert [len(b) for b in batches] == [4] * 6
    assert batches == list(StepBatchSampler(range(7), 4, 6, seed=1))
    late = list(StepBatchSampler(range(7), 4, 6, seed=1, start=3))
    assert late == batches[3:]
    r0 = list(StepBatchSampler(range(7), 4, 6, seed=1, rank=0, world=2))
    r1 = list(StepBatchSampler(range(7), 4, 6, seed=1, rank=1, world=2))
    assert [a + b for a, b in zip(r0, r1)] == batches
    # every sample once per epoch
    idx = np.concatenate([full.global_batch(s) for s in range(7)])
    assert sorted(idx[:7]) == list(range(7))
    with pytest.raises(ValueError, match="divisible"):
        StepBatchSampler(range(7), 3, 6, seed=1, world=2)


def test_max_views_keeps_a_random_subset_of_views_with_their_labels():
    cfg = config_from_dict({"model": {"preset": "small", "crop_size": 64}}).model
    s = toy_samples(1, cams=5)[0]
    aug = AugmentConfig(**{**GEOMETRIC_ONLY.__dict__, "max_views": 3, "rotation": 0.0})
    seen = set()
    for seed in range(6):
        p = prepare_sample(s, cfg, aug, np.random.default_rng(seed))
        names = tuple(p["rig"].names)
        assert len(names) == 3 and list(names) == sorted(names, key=s["rig"].names.index)
        seen.add(names)
        # every kept view's crop camera still maps the 3D labels onto its 2D labels
        b = collate_prepared([p])
        uv, _ = project_affine(
            torch.tensor(s["points3d"][None], dtype=torch.float32),
            b["K"], b["R"], b["t"], b["dist"],
        )  # fmt: skip
        np.testing.assert_allclose(uv[0].numpy(), p["points2d"], atol=1e-2)
        assert p["images"].shape[0] == 3 and p["visible2d"].shape[0] == 3
    assert len(seen) > 1  # the subset is drawn anew per sample
    # 0 (the default) keeps every view and draws nothing
    full = prepare_sample(s, cfg, GEOMETRIC_ONLY, np.random.default_rng(0))
    assert len(full["rig"]) == 5
    with pytest.raises(ConfigError, match="max_views"):
        AugmentConfig(max_views=1)

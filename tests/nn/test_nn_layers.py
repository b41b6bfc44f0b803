"""Unit tests of the voxel-network building blocks on random tensors."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from freipose.geometry import project
from freipose.geometry.crops import crop_camera, cube_crop_boxes
from freipose.nn.config import (
    ConfigError,
    InferenceOverrides,
    config_from_dict,
    inference_settings,
)
from freipose.nn.geometry import (
    pixels_to_normalized,
    project_affine,
    ray_distances,
    voxel_offsets,
)
from freipose.nn.layers import (
    Encoder2D,
    FeatureDecoder,
    Head2D,
    decode_head,
    gaussian_heatmaps,
    peak_window,
    refuse_outlier_views,
    softargmax2d,
    softargmax3d,
    triangulate_with_prior,
    unproject,
    volume_confidence,
)
from freipose.nn.model import build_model
from freipose.testing import make_circle_rig


def _bilinear_border(fmap: np.ndarray, fx: float, fy: float) -> np.ndarray:
    """Reference bilinear sample of (C, h, w) at feature coords, border-clamped."""
    C, h, w = fmap.shape
    fx = min(max(fx, 0.0), w - 1.0)
    fy = min(max(fy, 0.0), h - 1.0)
    x0, y0 = int(np.floor(fx)), int(np.floor(fy))
    x1, y1 = min(x0 + 1, w - 1), min(y0 + 1, h - 1)
    ax, ay = fx - x0, fy - y0
    return (
        fmap[:, y0, x0] * (1 - ax) * (1 - ay)
        + fmap[:, y0, x1] * ax * (1 - ay)
        + fmap[:, y1, x0] * (1 - ax) * ay
        + fmap[:, y1, x1] * ax * ay
    )


def test_unproject_matches_slow_loop(rng):
    rig = make_circle_rig(n=3, distortion=True)
    S, stride, C = 32, 4, 5
    h = S // stride
    B = 2
    centers = rng.normal(0, 30, size=(B, 3))
    cams = [
        [crop_camera(cam, box, S) for cam, box in zip(rig, cube_crop_boxes(rig, c, 300.0))]
        for c in centers
    ]
    feats = rng.normal(size=(B, 3, C, h, h)).astype(np.float32)
    view_mask = np.array([[True, True, True], [True, False, True]])
    # points: voxel grid plus some far outside every crop
    offs = voxel_offsets(4, 400.0, dtype=torch.float64).numpy()
    pts = np.stack([c + offs for c in centers])
    pts[:, :5] += np.array([900.0, 0, 0])
    K = torch.tensor(np.array([[c.K for c in row] for row in cams]), dtype=torch.float32)
    R = torch.tensor(np.array([[c.R for c in row] for row in cams]), dtype=torch.float32)
    t = torch.tensor(np.array([[c.t for c in row] for row in cams]), dtype=torch.float32)
    d = torch.tensor(np.array([[c.dist for c in row] for row in cams]), dtype=torch.float32)
    vol, count = unproject(
        torch.from_numpy(feats),
        K,
        R,
        t,
        d,
        torch.from_numpy(view_mask),
        torch.tensor(pts, dtype=torch.float32),
        S,
    )
    ref = np.zeros((B, C, pts.shape[1]))
    ref_count = np.zeros((B, pts.shape[1]))
    for b in range(B):
        for p in range(pts.shape[1]):
            acc = np.zeros(C)
            n = 0
            for v in range(3):
                if not view_mask[b, v]:
                    continue
                u = project(pts[b, p], cams[b][v])
                if not np.all(np.isfinite(u)) or not np.all((u >= -0.5) & (u <= S - 0.5)):
                    continue
                f = (u + 0.5) / stride - 0.5
                acc += _bilinear_border(feats[b, v], f[0], f[1])
                n += 1
            ref[b, :, p] = acc / max(n, 1)
            ref_count[b, p] = n
    np.testing.assert_array_equal(count.numpy(), ref_count)
    assert ref_count.min() == 0 and ref_count.max() == 3  # both cases exercised
    np.testing.assert_allclose(vol.numpy(), ref, atol=2e-4)


def test_unproject_gradients_match_the_masked_mean_over_views(rng):
    """The view-by-view accumulation back-propagates like the plain masked mean over views."""
    rig = make_circle_rig(n=4, distortion=True)
    S, C = 32, 3
    center = np.zeros(3)
    cams = [crop_camera(cam, box, S) for cam, box in zip(rig, cube_crop_boxes(rig, center, 300.0))]

    def stack(attr: str) -> torch.Tensor:
        return torch.tensor(np.array([[getattr(c, attr) for c in cams]]), dtype=torch.float64)

    K, R, t, d = stack("K"), stack("R"), stack("t"), stack("dist")
    view_mask = torch.tensor([[True, True, False, True]])
    pts = (voxel_offsets(4, 500.0, dtype=torch.float64) + 10.0)[None]  # some outside crops
    feats = torch.tensor(rng.normal(size=(1, 4, C, 8, 8)), requires_grad=True)
    weights = torch.tensor(rng.normal(size=(1, C, pts.shape[1])))
    vol, count = unproject(feats, K, R, t, d, view_mask, pts, S)
    (grad,) = torch.autograd.grad((vol * weights).sum(), feats)

    feats_ref = feats.detach().clone().requires_grad_(True)
    uv, front = project_affine(pts, K, R, t, d)
    g = 2.0 * (uv + 0.5) / S - 1.0
    valid = (front & (g.abs() <= 1).all(-1) & view_mask[:, :, None]).to(torch.float64)
    sampled = torch.nn.functional.grid_sample(
        feats_ref.reshape(4, C, 8, 8), g.reshape(4, 1, -1, 2), padding_mode="border",
        align_corners=False,
    ).reshape(1, 4, C, -1)  # fmt: skip
    ref = (sampled * valid[:, :, None]).sum(1) / valid.sum(1).clamp_min(1.0)[:, None]
    (grad_ref,) = torch.autograd.grad((ref * weights).sum(), feats_ref)
    assert count.max() == 3 and count.min() < 3  # points seen by all and by fewer views
    torch.testing.assert_close(vol, ref)
    torch.testing.assert_close(grad, grad_ref)
    assert grad[0, 2].abs().max() == 0 and grad[0, 0].abs().max() > 0  # padding view: none


def test_peaked_volume_decodes_to_voxel_centre():
    G, cube = 8, 400.0
    center = torch.tensor([[10.0, -20.0, 35.0], [0.0, 0.0, 0.0]])
    logits = torch.full((2, 3, G, G, G), -50.0)
    idx = [(1, 2, 3), (7, 0, 4), (3, 3, 3)]
    for k, (i, j, l) in enumerate(idx):
        logits[:, k, i, j, l] = 50.0
    pts, probs = softargmax3d(logits, center, cube)
    s = cube / (G - 1)
    for k, ijk in enumerate(idx):
        expect = center + (torch.tensor(ijk, dtype=torch.float32) - (G - 1) / 2) * s
        torch.testing.assert_close(pts[:, k], expect, atol=1e-3, rtol=0)
    np.testing.assert_allclose(volume_confidence(probs, G).numpy(), 1.0, atol=1e-5)
    flat = volume_confidence(torch.full_like(probs, 1.0 / G**3), G)
    assert float(flat.max()) < 0.1


def test_volume_confidence_is_the_largest_3x3x3_block_mass():
    torch.manual_seed(0)
    G = 6
    probs = torch.softmax(3 * torch.randn(2, 4, G**3), -1)
    probs[1, 0] = 0.0
    probs[1, 0, 0] = 1.0  # a peak in a corner: the block there is cut by the grid
    vol = probs.reshape(8, 1, G, G, G)
    blocks = torch.nn.functional.avg_pool3d(vol, 3, stride=1, padding=1) * 27
    expect = blocks.reshape(2, 4, -1).amax(-1)
    torch.testing.assert_close(volume_confidence(probs, G), expect, atol=1e-6, rtol=0)
    assert float(volume_confidence(probs, G)[1, 0]) == pytest.approx(1.0)
    assert not volume_confidence(probs.requires_grad_(), G).requires_grad


def test_eval_mode_skips_the_deep_supervision_volumes():
    from nn_toydata import toy_batch

    cfg = config_from_dict({"model": {"preset": "tiny"}}).model
    assert cfg.deep_supervision
    torch.manual_seed(0)
    model = build_model(cfg, 3)
    b = toy_batch(cfg, 2, cams=3)
    with torch.no_grad():
        train = model(b)
        model.eval()
        ev = model(b)
    assert len(train["P0_aux"]) == len(cfg.unet_channels) and ev["P0_aux"] == []
    torch.testing.assert_close(ev["P0"], train["P0"])  # group norm: same in both modes


def test_softargmax2d_and_heatmap_round_trip():
    stride, size = 4.0, 16
    uv = torch.tensor([[[10.3, 40.7], [0.0, 63.0]]])
    heat = gaussian_heatmaps(uv, size, stride, sigma=0.6)
    dec, _ = softargmax2d(torch.log(heat + 1e-12) * 1.0, stride)
    # a sampled gaussian's soft-argmax is its centre away from the borders
    torch.testing.assert_close(dec[0, 0], uv[0, 0], atol=0.05, rtol=0)


def test_peak_window_keeps_the_main_mode():
    # two Gaussians on a 16x16 map: the main one at (x 4.3, y 5.0), a weaker one 8 px away
    stride, size = 1.0, 16
    main = torch.tensor([[[4.3, 5.0]]])
    heat = gaussian_heatmaps(main, size, stride, 1.0) + 0.4 * gaussian_heatmaps(
        main + torch.tensor([8.0, 0.0]), size, stride, 1.0
    )
    logits = torch.log(heat + 1e-12)
    whole, probs = softargmax2d(logits, stride)
    local, probs_w = softargmax2d(logits, stride, window=3)
    assert float(whole[0, 0, 0]) > 6.0  # pulled ~2.3 px toward the second mode
    torch.testing.assert_close(local[0, 0], main[0, 0], atol=0.05, rtol=0)
    torch.testing.assert_close(probs_w, probs)  # the distributions returned are whole
    kept = peak_window(probs, (size, size), 3).reshape(size, size)
    rows, cols = torch.nonzero(kept, as_tuple=True)
    assert (int(rows.min()), int(rows.max()), int(cols.min()), int(cols.max())) == (2, 8, 1, 7)
    torch.testing.assert_close(kept.sum(), torch.tensor(1.0))
    assert peak_window(probs, (size, size), 0) is probs


@pytest.mark.parametrize("shape", [(16, 16), (5, 7, 9), (11,)])
def test_peak_window_is_the_box_around_the_peak(shape):
    # reference: every cell's index per axis compared with the peak's, on the flat grid
    torch.manual_seed(0)
    n = int(np.prod(shape))
    probs = torch.softmax(3 * torch.randn(2, 3, n), dim=-1)
    idx = np.stack(np.unravel_index(np.arange(n), shape), -1)  # (n, D)
    for radius in (1, 2, 4):
        peak = idx[probs.argmax(-1).numpy()]  # (2, 3, D)
        keep = (np.abs(idx[None, None] - peak[:, :, None]) <= radius).all(-1)
        expected = probs * torch.from_numpy(keep)
        expected = expected / expected.sum(-1, keepdim=True)
        torch.testing.assert_close(peak_window(probs, shape, radius), expected)


def _twin_outputs(key: str, off: float, on: float) -> tuple[tuple[dict, dict], tuple[dict, dict]]:
    """Outputs of two tiny networks with the same weights that differ in one inference
    setting ``model.<key>`` (``off`` vs ``on``): ``(training mode, eval mode)`` pairs."""
    from nn_toydata import toy_batch

    cfg = config_from_dict({"model": {"preset": "tiny", key: off}}).model
    torch.manual_seed(0)
    a = build_model(cfg, 3)
    b = build_model(replace(cfg, **{key: on}), 3)
    b.load_state_dict(a.state_dict())
    batch = toy_batch(cfg, 2, cams=3)
    with torch.no_grad():
        train = a(batch), b(batch)
        a.eval(), b.eval()
        return train, (a(batch), b(batch))


def test_model_decodes_windows_at_inference_only():
    (train_a, train_b), (eval_a, eval_b) = _twin_outputs("map_window", 0, 1)
    torch.testing.assert_close(train_a["P1"], train_b["P1"])  # training: the whole maps
    torch.testing.assert_close(eval_a["P0"], eval_b["P0"])  # P0 decodes the whole volume
    assert float((eval_a["points2d"] - eval_b["points2d"]).abs().max()) > 1e-3
    torch.testing.assert_close(eval_a["confidence2d"], eval_b["confidence2d"])
    assert float((eval_a["P1"] - eval_b["P1"]).abs().max()) > 1e-3
    with pytest.raises(Exception, match="map_window"):
        config_from_dict({"model": {"preset": "tiny", "map_window": -1}})


def _rig_tensors(n: int) -> tuple[torch.Tensor, ...]:
    rig = make_circle_rig(n=n, distortion=True)
    return tuple(
        torch.tensor(getattr(rig, k), dtype=torch.float32)[None] for k in ("K", "R", "t", "dist")
    )


def test_triangulation_with_prior(circle_rig, rng):
    K, R, t, dist = _rig_tensors(4)
    X = torch.tensor(rng.normal(0, 50, size=(1, 5, 3)), dtype=torch.float32)
    uv, _ = project_affine(X, K, R, t, dist)
    w = torch.ones(1, 4, 5)
    prior = X + 30.0
    Xh = triangulate_with_prior(uv, w, K, R, t, dist, prior)
    torch.testing.assert_close(Xh, X, atol=0.05, rtol=0)
    # a single view: the point on that view's ray nearest the prior
    w1 = torch.zeros(1, 4, 5)
    w1[:, 0] = 1.0
    X1 = triangulate_with_prior(uv, w1, K, R, t, dist, prior)
    uv1, _ = project_affine(X1, K, R, t, dist)
    torch.testing.assert_close(uv1[:, 0], uv[:, 0], atol=0.05, rtol=0)
    assert float((X1 - X).norm(dim=-1).max()) < float((prior - X).norm(dim=-1).max())
    # a per-point prior weight: huge keeps the prior, tiny the triangulation, in between
    # the point lies between the two
    pw = torch.tensor([[1e9, 1e-6, 4.0, 4.0, 4.0]])
    Xp = triangulate_with_prior(uv, w, K, R, t, dist, prior, pw)
    torch.testing.assert_close(Xp[:, 0], prior[:, 0], atol=1e-3, rtol=0)
    torch.testing.assert_close(Xp[:, 1], X[:, 1], atol=0.05, rtol=0)
    d_mid = (Xp[:, 2:] - X[:, 2:]).norm(dim=-1)
    assert bool((d_mid > 0.1).all() and (d_mid < 30.0 * 3**0.5 - 0.1).all())
    # undistortion inverts distortion
    xy = pixels_to_normalized(uv, K, dist)
    Xc = torch.einsum("bcij,bpj->bcpi", R, X) + t[:, :, None]
    torch.testing.assert_close(xy, Xc[..., :2] / Xc[..., 2:], atol=1e-5, rtol=0)


def test_ray_distances_are_lateral_mm_at_the_points_depth(rng):
    K, R, t, dist = _rig_tensors(3)
    X = torch.tensor(rng.normal(0, 50, size=(1, 4, 3)), dtype=torch.float32)
    uv, _ = project_affine(X, K, R, t, dist)
    torch.testing.assert_close(
        ray_distances(X, uv, K, R, t, dist), torch.zeros(1, 3, 4), atol=1e-3, rtol=0
    )
    # moved 7 mm along camera 0's x axis: 7 mm from camera 0's ray
    moved = X + 7.0 * R[0, 0, 0]
    d = ray_distances(moved, uv, K, R, t, dist)
    torch.testing.assert_close(d[:, 0], torch.full((1, 4), 7.0), atol=1e-2, rtol=0)
    # along camera 0's viewing direction the point stays on its ray
    cam = torch.einsum("ij,pj->pi", R[0, 0], X[0]) + t[0, 0]
    ray = X[0] + R[0, 0].T @ t[0, 0]  # from camera 0's centre -R^T t to the points
    along = X + 40.0 * ray / ray.norm(dim=-1, keepdim=True)
    assert float(ray_distances(along, uv, K, R, t, dist)[:, 0].abs().max()) < 1e-2
    assert bool((cam[:, 2] > 0).all())


def test_refuse_outlier_views_ignores_a_view_on_the_wrong_part(rng):
    K, R, t, dist = _rig_tensors(5)
    X = torch.tensor(rng.normal(0, 50, size=(1, 3, 3)), dtype=torch.float32)
    uv, _ = project_affine(X, K, R, t, dist)
    wrong, _ = project_affine(X + torch.tensor([60.0, -40.0, 20.0]), K, R, t, dist)
    uv = uv.clone()
    uv[:, 2, 0] = wrong[:, 2, 0]  # view 2 refined keypoint 0 onto another part, confidently
    conf = torch.ones(1, 5, 3)
    prior = X + 5.0
    scale = torch.full((1, 3), 0.1)
    P1 = triangulate_with_prior(uv, conf, K, R, t, dist, prior, scale * conf.sum(1))
    assert float((P1[:, 0] - X[:, 0]).norm()) > 5.0  # the wrong view pulls the fusion
    fixed = refuse_outlier_views(P1, uv, conf, (K, R, t, dist), prior, scale, 10.0)
    good = conf.clone()
    good[:, 2, 0] = 0.0
    without = triangulate_with_prior(uv, good, K, R, t, dist, prior, scale * good.sum(1) + 1e-3)
    torch.testing.assert_close(fixed[:, 0], without[:, 0], atol=1e-3, rtol=0)
    assert float((fixed[:, 0] - X[:, 0]).norm()) < 1.5  # the prior's pull, 5 mm away
    # the keypoints every view agrees on are fused as before
    torch.testing.assert_close(fixed[:, 1:], P1[:, 1:], atol=5e-3, rtol=0)
    # no view within the distance: the prior
    none = refuse_outlier_views(P1, uv, conf, (K, R, t, dist), prior, scale, 1e-6)
    torch.testing.assert_close(none, prior, atol=1e-3, rtol=0)


def test_model_refuses_outlier_views_at_inference_only():
    (train_a, train_r), (a, r) = _twin_outputs("fusion_reject", 0, 0.05)
    torch.testing.assert_close(train_a["P1"], train_r["P1"])  # training mode
    torch.testing.assert_close(a["points2d"], r["points2d"])
    torch.testing.assert_close(a["confidence"], r["confidence"])
    assert float((a["P1"] - r["P1"]).abs().max()) > 1e-3
    with pytest.raises(Exception, match="fusion_reject"):
        config_from_dict({"model": {"preset": "tiny", "fusion_reject": -1}})


def test_inference_overrides_replace_only_what_they_name():
    model = config_from_dict({"model": {"preset": "tiny", "map_window": 2}}).model
    assert InferenceOverrides().apply(model) is model
    both = InferenceOverrides(fusion_reject=0.0, map_window=0).apply(model)
    assert (both.fusion_reject, both.map_window) == (0.0, 0)
    assert replace(both, fusion_reject=model.fusion_reject, map_window=2) == model
    window = InferenceOverrides(map_window=5).apply(model)
    assert (window.fusion_reject, window.map_window) == (model.fusion_reject, 5)
    with pytest.raises(ConfigError, match="map_window must be >= 0"):
        InferenceOverrides(map_window=-1).apply(model)
    # what a poses file records: what shapes the reported pose
    assert inference_settings(model) == {"map_window": 2, "fusion_reject": model.fusion_reject}
    assert inference_settings(model, refine=False) == {}
    assert inference_settings(replace(model, kind="baseline"), refine=False) == {"map_window": 2}


def _fused_peak(center, grid_rot, shift=0.0):
    """Unproject per-view feature maps that score the distance to a 3D point's projection
    (through the full-image camera and the crop's image warp) into the voxel grid and return
    (point, sub-voxel peak of the fused volume, voxel size)."""
    from freipose.nn.config import AugmentConfig, ModelConfig
    from freipose.nn.data import collate_prepared, prepare_sample

    rig = make_circle_rig(n=4, distortion=True)
    cfg = ModelConfig(
        crop_size=64, encoder_pools=2, grid_size=24, cube_size=120.0, unet_channels=(8,)
    )
    aug = AugmentConfig(grid_rotation=0.0)
    gen = np.random.default_rng(3)
    sample = {"rig": rig, "images": [], "index": 0}
    item = prepare_sample(sample, cfg, aug, gen, center=center)  # random rotation/zoom/shift
    item["grid_rotation"] = grid_rot
    batch = collate_prepared([item])
    X = center + np.array([7.3, -4.1, 5.6])
    uv_full = np.stack([project(X, cam) for cam in rig])  # (V, 2) distorted full-image px
    uv = np.einsum("vij,vj->vi", item["affine"], np.concatenate([uv_full, np.ones((4, 1))], 1))
    h, s = cfg.feature_size, cfg.stride
    f = (uv[:, :2] + 0.5) / s - 0.5 + shift  # feature-pixel coordinates
    # View v's features are its feature-pixel coordinates (channels 2v, 2v+1; bilinear
    # sampling reproduces them exactly): the fused score -sum_v |f_v(p) - f_v(X)|^2 peaks at
    # the point, a smooth bowl whose maximum a parabola fit locates.
    gy, gx = np.meshgrid(np.arange(h), np.arange(h), indexing="ij")
    feats = np.zeros((4, 8, h, h))
    for v in range(4):
        feats[v, 2 * v], feats[v, 2 * v + 1] = gx, gy
    G = cfg.grid_size
    rot = torch.as_tensor(grid_rot, dtype=torch.float32)
    cube = cfg.cube_size / 2  # the grid stays inside every crop
    offs = voxel_offsets(G, cube) @ rot.T
    pts = batch["center"][:, None] + offs[None]
    vol, count = unproject(
        torch.tensor(feats, dtype=torch.float32)[None],
        batch["K"],
        batch["R"],
        batch["t"],
        batch["dist"],
        batch["view_mask"],
        pts,
        cfg.crop_size,
    )
    assert bool((count == 4).all())
    fv = (vol[0].double() * 4).reshape(4, 2, -1).numpy()  # (V, 2, G^3)
    lv = -((fv - f[:, :, None]) ** 2).sum((0, 1)).reshape(G, G, G)
    i = np.array(np.unravel_index(np.argmax(lv), lv.shape))
    sub = np.zeros(3)
    for a in range(3):  # parabola through the peak and its neighbours (log of a Gaussian)
        lo, hi = i.copy(), i.copy()
        lo[a] -= 1
        hi[a] += 1
        y0, y1, y2 = lv[tuple(lo)], lv[tuple(i)], lv[tuple(hi)]
        sub[a] = 0.5 * (y0 - y2) / (y0 - 2 * y1 + y2)
    vs = cube / (G - 1)
    local = (i + sub - (G - 1) / 2) * vs
    found = np.asarray(batch["center"][0], np.float64) + np.asarray(grid_rot) @ local
    return X, found, vs


def test_unprojected_peaks_meet_at_the_3d_point():
    """Alignment: per-view scores peaked at a 3D point's projections (distorted cameras,
    augmented crops) fuse into a volume whose maximum is that point to sub-voxel precision,
    also with a rotated voxel grid; a 0.1 feature-pixel convention error moves it
    measurably."""
    center = np.array([12.0, -8.0, 30.0])
    a = np.radians(37.0)
    rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])
    for rot in (np.eye(3), rz):
        X, found, vs = _fused_peak(center, rot)
        assert np.linalg.norm(found - X) < 0.05 * vs, (found, X, vs)
    X, found, vs = _fused_peak(center, np.eye(3), shift=0.1)
    assert np.linalg.norm(found - X) > 0.2 * vs


def test_volume_loss_is_the_cross_entropy_to_a_dense_gaussian():
    from freipose.nn.config import ModelConfig
    from freipose.nn.losses import volume_cross_entropy

    G, cube, sigma = 10, 300.0, 1.5
    cfg = ModelConfig(grid_size=G, cube_size=cube, unet_channels=(8,), volume_sigma=sigma)
    torch.manual_seed(1)
    probs = torch.softmax(2 * torch.randn(2, 4, G**3), dim=-1)
    gt = 60 * torch.randn(2, 4, 3)
    center = torch.tensor([[5.0, -3.0, 20.0], [0.0, 10.0, -4.0]])
    mask = torch.ones(2, 4, dtype=torch.bool)
    # reference: the Gaussian of every voxel's distance to the label, normalised over the grid
    d2 = ((voxel_offsets(G, cube)[None, None] - (gt - center[:, None])[:, :, None]) ** 2).sum(-1)
    target = torch.softmax(-d2 / (cfg.voxel_size**2 * 2 * sigma**2), dim=-1)
    ce = -(target * probs.log()).sum(-1)
    inside = ((gt - center[:, None]).abs() <= cube / 2).all(-1)
    expected = torch.stack([ce[b][inside[b]].mean() for b in range(2)]).mean()
    torch.testing.assert_close(volume_cross_entropy(probs, gt, mask, center, None, cfg), expected)


def test_rotated_grid_decodes_and_volume_loss_prefers_the_label():
    from freipose.nn.config import ModelConfig
    from freipose.nn.losses import volume_cross_entropy

    G, cube = 8, 400.0
    a = np.radians(-50.0)
    rot = torch.tensor(
        [[[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]]],
        dtype=torch.float32,
    )
    center = torch.tensor([[10.0, -20.0, 35.0]])
    logits = torch.full((1, 2, G, G, G), -50.0)
    logits[0, 0, 1, 6, 3] = 50.0
    logits[0, 1, 4, 4, 4] = 50.0
    pts, probs = softargmax3d(logits, center, cube, rot)
    s = cube / (G - 1)
    for k, ijk in enumerate([(1, 6, 3), (4, 4, 4)]):
        local = (torch.tensor(ijk, dtype=torch.float32) - (G - 1) / 2) * s
        torch.testing.assert_close(pts[0, k], center[0] + rot[0] @ local, atol=1e-3, rtol=0)
    cfg = ModelConfig(grid_size=G, cube_size=cube, unet_channels=(8,), volume_sigma=1.0)
    mask = torch.ones(1, 2, dtype=torch.bool)
    ce_right = volume_cross_entropy(probs, pts, mask, center, rot, cfg)
    ce_wrong = volume_cross_entropy(probs, pts.flip(1), mask, center, rot, cfg)
    assert float(ce_right) < float(ce_wrong)
    # labels outside the cube (or unlabeled) do not count
    far = pts.clone()
    far[0, 1] += 1000.0
    ce_far = volume_cross_entropy(probs, far, mask, center, rot, cfg)
    ce_one = volume_cross_entropy(probs, pts, torch.tensor([[True, False]]), center, rot, cfg)
    torch.testing.assert_close(ce_far, ce_one)


def test_head_levels_refine_the_map_resolution():
    """Each decoder level doubles the map size with the encoder's skip of that scale, and the
    decoded points stay in crop pixels whatever the map stride."""
    torch.manual_seed(0)
    enc = Encoder2D((4, 6, 8), (1, 1, 1), 3, 5, "group")
    assert enc.skip_channels == (8, 6, 4)
    feats, skips = enc(torch.zeros(2, 3, 32, 32))
    assert feats.shape == (2, 5, 4, 4)
    assert [tuple(s.shape[1:]) for s in skips] == [(8, 8, 8), (6, 16, 16), (4, 32, 32)]
    for levels, size in ((1, 8), (2, 16), (3, 32)):
        head = Head2D(5, enc.skip_channels, 2, 8, "group", heat_in=0, levels=levels)
        maps, conf = head(feats, skips)
        assert maps.shape == conf.shape == (2, 2, size, size)
        # a map peaked at one pixel decodes to that pixel's centre in crop pixels
        stride = 32 / size
        peak = torch.full((1, 1, size, size), -50.0)
        peak[0, 0, 3, 5] = 50.0
        uv, c = decode_head(peak, torch.zeros_like(peak), stride)
        np.testing.assert_allclose(uv[0, 0].numpy(), [(5.5) * stride - 0.5, 3.5 * stride - 0.5])
        assert abs(float(c) - 0.5) < 1e-6
    with pytest.raises(ValueError, match="levels must be in 1..3"):
        Head2D(5, enc.skip_channels, 2, 8, "group", heat_in=0, levels=4)


def test_feature_decoder_and_unproject_levels():
    """``unproject_levels`` raises the unprojected features' resolution with the encoder's skip
    maps; the network runs the same with them."""
    torch.manual_seed(0)
    enc = Encoder2D((4, 6, 8), (1, 1, 1), 3, 5, "group")
    feats, skips = enc(torch.zeros(2, 3, 32, 32))
    for levels, size in ((1, 8), (3, 32)):
        out = FeatureDecoder(5, enc.skip_channels, "group", levels)(feats, skips)
        assert out.shape == (2, 5, size, size)
    with pytest.raises(ValueError, match="levels must be in 1..3"):
        FeatureDecoder(5, enc.skip_channels, "group", 4)
    cfg = config_from_dict({"model": {"preset": "tiny", "unproject_levels": 2}}).model
    net = build_model(cfg, 3)
    assert net.lift is not None and build_model(replace(cfg, unproject_levels=0), 3).lift is None
    seen = {}
    net.lift.register_forward_hook(lambda m, i, o: seen.update(shape=tuple(o.shape)))
    from nn_toydata import toy_batch

    b = toy_batch(cfg, 2, cams=3)
    out = net(b)
    s = cfg.crop_size // cfg.stride * 4
    assert seen["shape"] == (2 * 3, cfg.feature_channels, s, s)
    assert out["P0"].shape == (2, 3, 3) and torch.isfinite(out["P1"]).all()


def test_map_loss_prefers_the_label_and_skips_hidden_or_outside_labels():
    from freipose.nn.config import ModelConfig
    from freipose.nn.losses import map_cross_entropy

    cfg = ModelConfig(
        crop_size=32,
        encoder_channels=(8, 8, 16),
        encoder_convs=(1, 1, 1),
        encoder_pools=2,
        head_levels=1,
        grid_size=8,
        unet_channels=(8,),
    )
    ms = cfg.map_stride  # 2 crop px per map px, 16 x 16 maps
    logits = torch.full((1, 1, 2, 16, 16), -20.0)
    logits[0, 0, 0, 4, 10] = 20.0  # keypoint 0 peaked at map (x=10, y=4)
    logits[0, 0, 1, 12, 3] = 20.0
    gt = torch.tensor([[[[10.5 * ms - 0.5, 4.5 * ms - 0.5], [3.5 * ms - 0.5, 12.5 * ms - 0.5]]]])
    vis = torch.ones(1, 1, 2, dtype=torch.bool)
    right = map_cross_entropy(logits, gt, vis, cfg)
    wrong = map_cross_entropy(logits, gt.flip(2), vis, cfg)
    assert float(right) < float(wrong)
    only0 = map_cross_entropy(logits, gt, torch.tensor([[[True, False]]]), cfg)
    outside = gt.clone()
    outside[0, 0, 1] = torch.tensor([100.0, 5.0])
    torch.testing.assert_close(map_cross_entropy(logits, outside, vis, cfg), only0)
    nan = gt.clone()
    nan[0, 0, 1] = float("nan")
    torch.testing.assert_close(map_cross_entropy(logits, nan, vis, cfg), only0)


def test_autocast_runs_the_dense_parts_only():
    """Under bf16 autocast the encoder and the U-Net compute in bfloat16, while the
    decoding stays in float32: a sharp score volume far from the origin decodes to its
    voxel's world position exactly (a bfloat16 product of mm offsets rounds it by up to
    half a mm)."""
    from nn_toydata import toy_batch

    cfg = config_from_dict({"model": {"preset": "tiny"}}).model
    torch.manual_seed(0)
    model = build_model(cfg, 3).eval()
    b = toy_batch(cfg, 2, cams=3)
    b["center"] = b["center"] + torch.tensor([1234.5, -987.25, 2345.75])
    G = cfg.grid_size
    voxels = torch.tensor([[3, G - 2, 1], [G - 4, 2, G - 3], [1, 1, G - 2]])  # (K, 3) i, j, k
    seen = {}

    def sharp(module, inputs, output):
        seen["unet"] = output[-1].dtype
        scores = torch.zeros(2, 3, G, G, G)
        for k, (i, j, m) in enumerate(voxels.tolist()):
            scores[:, k, i, j, m] = 80.0
        return [scores]

    def encoder_dtype(module, inputs, output):
        seen["encoder"] = output[0].dtype

    model.unet.register_forward_hook(sharp)
    model.encoder.register_forward_hook(encoder_dtype)
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
        out = model(b)
    assert seen == {"encoder": torch.bfloat16, "unet": torch.bfloat16}
    offs = voxel_offsets(G, cfg.cube_size)  # (G^3, 3), flat index i*G*G + j*G + k
    flat = voxels[:, 0] * G * G + voxels[:, 1] * G + voxels[:, 2]
    expected = b["center"][:, None, :] + offs[flat][None]
    assert out["P0"].dtype == torch.float32 and out["P1"].dtype == torch.float32
    torch.testing.assert_close(out["P0"], expected, atol=1e-3, rtol=0)

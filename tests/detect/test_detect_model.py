"""The network, its targets and decoding, augmentation, checkpoints and a short training run."""

import cv2
import numpy as np
import pytest
import torch

from freipose.detect import Detector
from freipose.detect.augment import AugmentConfig, augment, make_targets
from freipose.detect.boxes import box_iou
from freipose.detect.detector import (
    DetectorCheckpointError,
    letterbox,
    load_backbone_weights,
    load_checkpoint,
)
from freipose.detect.loss import detection_loss
from freipose.detect.model import DetectorConfig, DetectorNet, decode, letterbox_affine
from freipose.detect.train import DetectorTrainConfig, ViewImages, fit

TINY = DetectorConfig(input_size=64, width=0.25, neck_channels=16)


def test_forward_shapes():
    net = DetectorNet(TINY).eval()
    heat, size, off = net(torch.zeros(2, 3, 64, 64))
    assert (
        heat.shape == (2, 1, 16, 16)
        and size.shape == (2, 2, 16, 16)
        and off.shape == (2, 2, 16, 16)
    )
    with pytest.raises(ValueError, match="multiple of 32"):
        DetectorConfig(input_size=100)


def test_targets_decode_round_trip():
    boxes = np.array([[10.3, 20.7, 40.1, 35.2], [np.nan] * 4, [0.0, 50.0, 12.0, 63.5]])
    heat, index, size, offset, mask = make_targets(boxes, 64)
    assert heat.shape == (3, 1, 16, 16) and list(mask) == [1, 0, 1]
    assert heat[1].max() == 0 and heat[0].max() == pytest.approx(1.0)
    # Network outputs equal to the targets everywhere decode to the boxes.
    logits = torch.logit(torch.from_numpy(heat).clamp(1e-4, 1 - 1e-4))
    sz = torch.from_numpy(np.broadcast_to(size[:, :, None, None], (3, 2, 16, 16)).copy())
    of = torch.from_numpy(np.broadcast_to(offset[:, :, None, None], (3, 2, 16, 16)).copy())
    out = decode(logits, sz, of, top_k=3, min_score=0.5)
    np.testing.assert_allclose(out[0][0][0], boxes[0], atol=1e-4)
    np.testing.assert_allclose(out[2][0][0], boxes[2], atol=1e-4)
    assert len(out[1][0]) == 0


def test_letterbox_matches_its_affine():
    img = np.zeros((120, 200, 3), np.uint8)
    img[60:76, 140:156] = 255  # a square centred at (147.5, 67.5)
    lb = letterbox(img, 64)
    A = letterbox_affine((200, 120), 64)
    ys, xs = np.nonzero(lb[:38, :, 0] > 20)  # the image part (the padding is grey 114)
    w = lb[ys, xs, 0].astype(float)
    centroid = [np.average(xs, weights=w), np.average(ys, weights=w)]
    np.testing.assert_allclose(centroid, (A @ [147.5, 67.5, 1])[:2], atol=0.3)
    assert (lb[40:, :, 0] == 114).all()  # padding below the 200x120 -> 64x38 image


def test_augment_moves_the_box_with_the_image():
    rng = np.random.default_rng(0)
    img = np.full((48, 64, 3), 30, np.uint8)
    img[10:30, 20:50] = (250, 0, 250)
    box = np.array([19.5, 9.5, 49.5, 29.5])  # pixel edges of the bright rectangle
    cfg = AugmentConfig(color=0.0, blur=0.0, noise=0.0, hue=0.0, random_fill=0.0, gray=0.0)
    for _ in range(20):
        out, b = augment(img, box, 64, cfg, rng)
        assert out.shape == (64, 64, 3)
        ys, xs = np.nonzero((out[..., 0] > 140) & (out[..., 1] < 60) & (out[..., 2] > 140))
        found = np.array([xs.min() - 0.5, ys.min() - 0.5, xs.max() + 0.5, ys.max() + 0.5])
        assert box_iou(found, b) > 0.85
    out, b = augment(img, np.full(4, np.nan), 64, AugmentConfig(), rng)
    assert np.isnan(b).all() and out.dtype == np.uint8
    with pytest.raises(ValueError, match="scale"):
        AugmentConfig(scale=(1.5, 0.5))


def _ellipse_views(n: int, rng: np.random.Generator) -> ViewImages:
    imgs, boxes = [], []
    for _ in range(n):
        img = rng.integers(0, 100, (48, 64, 3)).astype(np.uint8)
        cx, cy = rng.uniform(12, 52), rng.uniform(10, 38)
        ax, ay = rng.uniform(5, 10), rng.uniform(3, 7)
        cv2.ellipse(
            img, (round(cx), round(cy)), (round(ax), round(ay)), 0, 0, 360, (230, 240, 250), -1
        )
        imgs.append(img)
        boxes.append([round(cx) - round(ax) - 0.5, round(cy) - round(ay) - 0.5,
                      round(cx) + round(ax) + 0.5, round(cy) + round(ay) + 0.5])  # fmt: skip
    return ViewImages(imgs, np.array(boxes))


def test_short_training_reduces_loss_and_checkpoints_round_trip(tmp_path):
    torch.set_num_threads(1)
    views = _ellipse_views(24, np.random.default_rng(1))
    cfg = DetectorTrainConfig(
        input_size=64, width=0.25, neck_channels=16, steps=60, batch_size=8, lr=3e-3,
        warmup_steps=5, checkpoint_every=30, log_every=30,
    )  # fmt: skip
    net, losses = fit(views, cfg, "cpu", out_dir=tmp_path, progress=False)
    assert np.mean(losses[-10:]) < 0.5 * np.mean(losses[:5])
    ckpt = load_checkpoint(tmp_path / "detector_last.pt")
    assert ckpt["step"] == 60 and "optimizer" in ckpt

    # Resuming at the last step trains nothing more and keeps the weights.
    net2, more = fit(views, cfg, "cpu", out_dir=tmp_path, resume=True, progress=False)
    assert more == []
    det = Detector(net, "cpu")
    det.save(tmp_path / "d.pt")
    again = Detector.load(tmp_path / "d.pt", "cpu")
    imgs = [cv2.resize(v, (128, 96)) for v in views.images[:3]]
    a, b = det.propose(imgs), again.propose(imgs)
    for x, y in zip(a, b):
        np.testing.assert_allclose(x.boxes, y.boxes)
        np.testing.assert_allclose(x.scores, y.scores)
    for x, y in zip(b, Detector(net2, "cpu").propose(imgs)):
        np.testing.assert_allclose(x.boxes, y.boxes)
    # A config with another architecture cannot resume this run.
    with pytest.raises(ValueError, match="trained with"):
        fit(views, DetectorTrainConfig(input_size=96, width=0.25, neck_channels=16, steps=61),
            "cpu", out_dir=tmp_path, resume=True, progress=False)  # fmt: skip


def test_checkpoint_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="not found"):
        Detector.load(tmp_path / "none.pt")
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(DetectorCheckpointError, match="junk.pt is not a FreiPose checkpoint"):
        Detector.load(tmp_path / "junk.pt")
    torch.save({"format": "something.else"}, tmp_path / "other.pt")
    with pytest.raises(DetectorCheckpointError, match="other.pt is not a FreiPose checkpoint"):
        Detector.load(tmp_path / "other.pt")


def test_backbone_weights_from_a_local_file(tmp_path):
    src = DetectorNet(TINY)
    torch.save(
        {f"backbone.{k}": v for k, v in src.backbone.state_dict().items()}, tmp_path / "bb.pt"
    )
    dst = DetectorNet(TINY)
    loaded, skipped = load_backbone_weights(dst, tmp_path / "bb.pt")
    assert loaded == len(src.backbone.state_dict()) and skipped == 0
    for k, v in src.backbone.state_dict().items():
        torch.testing.assert_close(dst.backbone.state_dict()[k], v)
    torch.save({"x": torch.zeros(3)}, tmp_path / "bad.pt")
    with pytest.raises(ValueError, match="none of its"):
        load_backbone_weights(dst, tmp_path / "bad.pt")


def test_train_crop_gives_smaller_training_inputs_at_the_same_scale():
    from freipose.detect.train import AugmentedBatches

    views = _ellipse_views(4, np.random.default_rng(2))
    cfg = DetectorTrainConfig(input_size=96, train_crop=64, scale=(1.0, 1.0))
    img, box = AugmentedBatches(views, cfg, 8)[3]
    assert img.shape == (64, 64, 3) and np.isfinite(box).all()
    i = int(np.random.default_rng((cfg.seed, 3)).integers(4))
    # Zoom 1 at input_size 96: the 64-px-wide cached image is scaled by 1.5.
    w0 = views.boxes[i, 2] - views.boxes[i, 0]
    assert box[2] - box[0] == pytest.approx(1.5 * w0, abs=0.6) or box[0] <= 0 or box[2] >= 63
    with pytest.raises(ValueError, match="train_crop"):
        DetectorTrainConfig(input_size=96, train_crop=128)


@pytest.mark.gpu
def test_training_and_inference_on_gpu(tmp_path):
    views = _ellipse_views(8, np.random.default_rng(3))
    cfg = DetectorTrainConfig(input_size=64, width=0.25, neck_channels=16, steps=5, batch_size=4,
                              warmup_steps=1)  # fmt: skip
    net, losses = fit(views, cfg, "cuda", progress=False)
    assert len(losses) == 5 and np.isfinite(losses).all()
    imgs = [cv2.resize(v, (128, 96)) for v in views.images[:4]]
    gpu = Detector(net, "cuda").propose(imgs)
    cpu = Detector(net.to("cpu"), "cpu").propose(imgs)
    for a, b in zip(gpu, cpu):
        assert len(a) == len(b)
        np.testing.assert_allclose(a.boxes, b.boxes, atol=1e-2)


def test_targets_of_several_animals_decode_to_every_box():
    boxes = np.array([[[4.0, 6.0, 20.0, 18.0], [36.0, 30.0, 58.0, 50.0], [np.nan] * 4],
                      [[np.nan] * 4, [np.nan] * 4, [np.nan] * 4]])  # fmt: skip
    heat, index, size, offset, mask = make_targets(boxes, 64)
    assert heat.shape == (2, 1, 16, 16) and index.shape == (2, 3) and size.shape == (2, 3, 2)
    assert mask.tolist() == [[1, 1, 0], [0, 0, 0]]
    assert (heat[0] >= 0.999).sum() == 2 and heat[1].max() == 0
    sz, of = np.zeros((2, 2, 16 * 16), np.float32), np.zeros((2, 2, 16 * 16), np.float32)
    for j in range(2):
        sz[0, :, index[0, j]], of[0, :, index[0, j]] = size[0, j], offset[0, j]
    logits = torch.logit(torch.from_numpy(heat).clamp(1e-4, 1 - 1e-4))
    out = decode(logits, torch.from_numpy(sz.reshape(2, 2, 16, 16)),
                 torch.from_numpy(of.reshape(2, 2, 16, 16)), top_k=3, min_score=0.5)  # fmt: skip
    found = out[0][0]
    assert len(found) == 2
    for b in boxes[0, :2]:
        assert np.abs(found - b).max(1).min() < 1e-4


def test_loss_with_padding_rows_equals_the_one_box_loss():
    torch.manual_seed(0)
    outs = (torch.randn(2, 1, 16, 16), torch.randn(2, 2, 16, 16), torch.rand(2, 2, 16, 16))
    one = np.array([[4.0, 6.0, 20.0, 18.0], [np.nan] * 4])
    padded = np.concatenate([one[:, None], np.full((2, 1, 4), np.nan)], axis=1)
    a, pa = detection_loss(outs, one, 64)
    b, pb = detection_loss(outs, padded, 64)
    assert float(a) == pytest.approx(float(b)) and pa == pytest.approx(pb)
    two = padded.copy()
    two[0, 1] = [36.0, 30.0, 58.0, 50.0]
    c, _ = detection_loss(outs, two, 64)
    assert float(c) != pytest.approx(float(a))


def test_augment_moves_several_boxes_with_the_image():
    rng = np.random.default_rng(1)
    img = np.full((48, 64, 3), 30, np.uint8)
    img[5:15, 4:20] = (250, 0, 250)
    img[28:44, 36:60] = (0, 250, 0)
    boxes = np.array([[3.5, 4.5, 19.5, 14.5], [35.5, 27.5, 59.5, 43.5], [np.nan] * 4])
    cfg = AugmentConfig(color=0.0, blur=0.0, noise=0.0, hue=0.0, random_fill=0.0, gray=0.0,
                        scale=(1.0, 1.3))  # fmt: skip
    for _ in range(20):
        out, b = augment(img, boxes, 64, cfg, rng)
        assert b.shape == (3, 4) and np.isnan(b[2]).all()
        for j, colour in enumerate(((250, 0, 250), (0, 250, 0))):
            ys, xs = np.nonzero((np.abs(out.astype(int) - colour) < 60).all(-1))
            if len(xs) < 20 or np.ptp(xs) < 6 or np.ptp(ys) < 6:  # (nearly) cropped away
                continue
            found = np.array([xs.min() - 0.5, ys.min() - 0.5, xs.max() + 0.5, ys.max() + 0.5])
            assert box_iou(found, b[j]) > 0.8


def test_training_on_two_animals_per_image_finds_both():
    """Every view holds two animals that look different (a white and a green ellipse), both
    labeled: the detector's two best peaks are them (trained on the white one alone, it
    finds the green one in about a third of the views)."""
    torch.set_num_threads(1)
    rng = np.random.default_rng(2)
    imgs, boxes = [], []
    for _ in range(24):
        img = rng.integers(0, 100, (48, 64, 3)).astype(np.uint8)
        rows = []
        for cx in (rng.uniform(10, 24), rng.uniform(40, 54)):
            cy, ax, ay = (
                round(rng.uniform(10, 38)),
                round(rng.uniform(5, 8)),
                round(rng.uniform(3, 6)),
            )
            colour = (230, 240, 250) if cx < 32 else (40, 200, 60)
            cv2.ellipse(img, (round(cx), cy), (ax, ay), 0, 0, 360, colour, -1)
            rows.append([round(cx) - ax - 0.5, cy - ay - 0.5, round(cx) + ax + 0.5, cy + ay + 0.5])
        imgs.append(img)
        boxes.append(rows)
    views = ViewImages(imgs, np.array(boxes))
    cfg = DetectorTrainConfig(
        input_size=64, width=0.25, neck_channels=16, steps=150, batch_size=8, lr=3e-3,
        warmup_steps=5, checkpoint_every=1000, log_every=1000,
    )  # fmt: skip
    net, _ = fit(views, cfg, "cpu", progress=False)
    det = Detector(net, "cpu", top_k=2)
    hits = 0
    for cd, truth in zip(det.propose(imgs), boxes):
        iou = box_iou(np.asarray(cd.boxes)[:, None], np.asarray(truth)[None])  # (2, 2)
        hits += int((iou >= 0.5).any(0).sum())
    assert hits >= 0.75 * 2 * len(imgs), hits

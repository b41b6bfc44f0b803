"""Training the detector from ``labels.h5`` (``freipose train CONFIG --stage detector``).

The training TOML's ``[data]`` table names the data (paths relative to the TOML file)::

    [data]
    labels = "labels.h5"            # or a list of files
    eval_labels = "eval/labels.h5"  # optional; else a held-out fraction of `labels`
    root = "."                      # optional: folder the labels' video paths are relative to

and its ``[detector]`` table the training (every key optional; defaults below)::

    [detector]
    input_size = 256        # network input side (px, multiple of 32); frames are letterboxed
    width = 0.5             # backbone width multiplier
    neck_channels = 48
    steps = 3000            # optimizer steps
    batch_size = 16
    lr = 2e-3               # AdamW peak learning rate (linear warm-up, cosine decay)
    weight_decay = 1e-4
    warmup_steps = 100
    box_margin = 0.1        # ground-truth box = label bbox + this fraction of its longer side
    min_visible = 0.5       # views with less of the box inside the image are not scored
    scale = [0.7, 1.5]      # augmentation: zoom range (random crops)
    hflip = 0.5             # flip probabilities
    vflip = 0.5
    color = 0.3             # brightness/contrast/saturation jitter
    hue = 8.0
    blur = 0.3              # blur probability
    noise = 6.0             # max pixel noise std
    eval_fraction = 0.1     # held out when there is no eval_labels
    max_images = 4000       # most training views kept in memory (evenly subsampled)
    max_eval_instants = 200 # most time instants evaluated
    backbone_weights = ""   # optional backbone weights (state dict or detector checkpoint)
    init = "base"           # starting weights: "base", "scratch" or a detector.pt (relative
                            # to the TOML, as backbone_weights; see freipose.detect.init)
    checkpoint_every = 500
    log_every = 100
    seed = 0
    cube_size = 400.0       # mm, multi-view step during evaluation
    num_workers = 0         # DataLoader workers preparing augmented batches
    train_crop = 0          # train on random crops of this side at the input scale (0: whole
                            # input); e.g. 128 with input_size 192 halves the training cost

Writes ``detector_last.pt`` (resumable: weights, optimizer, step) every
``checkpoint_every`` steps, ``log.csv`` (the loss history, a row every ``log_every`` steps)
and ``detector.pt`` (weights and metrics) at the end, and prints recall at IoU 0.5, the
median 3D centre error and CPU frames per second.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from freipose.detect.augment import AugmentConfig, augment
from freipose.detect.detector import (
    Detector,
    load_backbone_weights,
    load_checkpoint,
    resolve_device,
    save_checkpoint,
)
from freipose.detect.evaluate import DetectionMetrics, evaluate_source, measure_speed
from freipose.detect.init import initialize_detector
from freipose.detect.loss import detection_loss
from freipose.detect.model import DetectorConfig, DetectorNet, to_tensor
from freipose.detect.multiview import ConsistencyConfig
from freipose.detect.ranges import DETECTOR_RANGES
from freipose.detect.train_log import LOG, log_row, read_log, write_log
from freipose.detect.train_views import ViewImages, collect_views, stack_boxes
from freipose.errors import FreiPoseError, InputFileError
from freipose.io.checkpoints import DETECTOR_TRAINING_STATE
from freipose.io.lock import output_lock
from freipose.io.toml import check_numbers, did_you_mean
from freipose.progress import progress_bar

log = logging.getLogger(__name__)

LAST = "detector_last.pt"
FINAL = "detector.pt"


class DetectorTrainError(FreiPoseError):
    """A detector training that cannot run as configured (bad table, no training data)."""


@dataclass(frozen=True)
class DetectorTrainConfig:
    """The ``[detector]`` table of the training TOML (see the module docstring)."""

    input_size: int = 256
    width: float = 0.5
    neck_channels: int = 48
    steps: int = 3000
    batch_size: int = 16
    lr: float = 2e-3
    weight_decay: float = 1e-4
    warmup_steps: int = 100
    box_margin: float = 0.1
    min_visible: float = 0.5
    scale: tuple[float, float] = (0.7, 1.5)
    hflip: float = 0.5
    vflip: float = 0.5
    color: float = 0.3
    hue: float = 8.0
    blur: float = 0.3
    noise: float = 6.0
    eval_fraction: float = 0.1
    max_images: int = 4000
    max_eval_instants: int = 200
    backbone_weights: str = ""
    init: str = "base"
    checkpoint_every: int = 500
    log_every: int = 100
    seed: int = 0
    cube_size: float = 400.0
    num_workers: int = 0
    train_crop: int = 0

    def __post_init__(self) -> None:
        check_numbers(self, "detector", DETECTOR_RANGES, DetectorTrainError)
        object.__setattr__(self, "scale", tuple(float(v) for v in self.scale))
        for name in ("steps", "batch_size", "max_images", "checkpoint_every", "log_every"):
            if (v := getattr(self, name)) < 1:
                raise DetectorTrainError(f"[detector] {name} must be >= 1, got {v}")
        if self.train_crop and (
            self.train_crop % 32 or not 64 <= self.train_crop <= self.input_size
        ):
            raise DetectorTrainError(
                f"[detector] train_crop must be 0 (whole input) or a multiple of 32 between 64 "
                f"and input_size {self.input_size}, got {self.train_crop}"
            )
        self.model_config()  # validates input_size etc.
        self.augment_config()

    @classmethod
    def from_dict(cls, table: dict[str, Any] | None) -> DetectorTrainConfig:
        """Build from the ``[detector]`` table; unknown keys are an error (typos)."""
        table = dict(table or {})
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(table) - known)
        if unknown:
            hint = did_you_mean(unknown[0], known)
            raise DetectorTrainError(
                f"[detector] has unknown keys {unknown}{hint} (known keys: {sorted(known)})"
            )
        try:
            return cls(**table)
        except TypeError as exc:
            raise DetectorTrainError(f"[detector]: {exc}") from exc

    def model_config(self) -> DetectorConfig:
        """The network architecture (input size, width, neck channels)."""
        return DetectorConfig(self.input_size, self.width, self.neck_channels)

    def augment_config(self) -> AugmentConfig:
        """The augmentation settings (zoom, flips, colour, blur, noise)."""
        return AugmentConfig(
            self.scale, self.hflip, self.vflip, self.color, self.hue, self.blur, self.noise
        )


def _data_paths(config: dict, config_path: Path) -> tuple[list[Path], list[Path], Path | None]:
    data = config.get("data")
    if not isinstance(data, dict) or "labels" not in data:
        raise DetectorTrainError(
            f"{config_path}: the training config needs a [data] table with `labels = "
            f'"labels.h5"` (a path or a list of paths, relative to the config file)'
        )
    base = Path(config_path).resolve().parent

    def paths(v: Any, key: str) -> list[Path]:
        vs = [v] if isinstance(v, (str, Path)) else list(v)
        if not vs or not all(isinstance(x, (str, Path)) for x in vs):
            raise DetectorTrainError(
                f"{config_path}: [data] {key} must be a path or a list of paths"
            )
        out = [p if p.is_absolute() else base / p for p in map(Path, vs)]
        for p in out:
            if not p.is_file():
                raise InputFileError(f"{config_path}: [data] {key}: {p} does not exist")
        return out

    train = paths(data["labels"], "labels")
    ev = paths(data["eval_labels"], "eval_labels") if data.get("eval_labels") else []
    root = data.get("root")
    root_p = None if root is None else (Path(root) if Path(root).is_absolute() else base / root)
    return train, ev, root_p


def _datasets(paths: Sequence[Path], root: Path | None) -> list:
    from freipose.nn.dataset import MultiViewDataset

    return [MultiViewDataset(p, root=root) for p in paths]


class AugmentedBatches(torch.utils.data.Dataset):
    """Item ``k`` is augmented view number ``k`` of the training stream (deterministic)."""

    def __init__(self, views: ViewImages, cfg: DetectorTrainConfig, length: int):
        self.views = views
        self.cfg = cfg
        self.aug = cfg.augment_config()
        self.length = length

    def __len__(self) -> int:
        return self.length

    def __getitem__(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        rng = np.random.default_rng((self.cfg.seed, int(k)))
        i = int(rng.integers(len(self.views.images)))
        v = self.views
        crop = self.cfg.train_crop or self.cfg.input_size
        return augment(v.images[i], v.boxes[i], self.cfg.input_size, self.aug, rng, crop)


def _collate(batch: list[tuple[np.ndarray, np.ndarray]]) -> tuple[torch.Tensor, np.ndarray]:
    imgs = np.stack([b[0] for b in batch])
    return to_tensor(imgs), np.stack([b[1] for b in batch])


def _lr_factor(step: int, cfg: DetectorTrainConfig) -> float:
    if step < cfg.warmup_steps:
        return (step + 1) / cfg.warmup_steps
    t = (step - cfg.warmup_steps) / max(1, cfg.steps - cfg.warmup_steps)
    return 0.02 + 0.98 * 0.5 * (1 + math.cos(math.pi * min(1.0, t)))


@dataclass(frozen=True)
class _Training:
    """A training run ready to take its first step: network, optimizer, schedule, position."""

    net: DetectorNet
    opt: torch.optim.Optimizer
    sched: torch.optim.lr_scheduler.LambdaLR
    start: int  # optimizer steps already done (resumed runs)
    last: Path | None  # the resumable checkpoint, None without an output folder


def _start_training(
    cfg: DetectorTrainConfig, dev: torch.device, out_dir: Path | None, resume: bool
) -> _Training:
    """Build the network and optimizer (seeded), resuming from ``detector_last.pt`` if asked.

    Raises:
        DetectorTrainError: the checkpoint to resume was trained with another architecture.
    """
    torch.manual_seed(cfg.seed)
    net = DetectorNet(cfg.model_config())
    if cfg.backbone_weights:
        load_backbone_weights(net, cfg.backbone_weights)
    last = None if out_dir is None else Path(out_dir) / LAST
    if not (resume and last is not None and last.is_file()):
        initialize_detector(net, cfg.init, cfg.backbone_weights)
    net.to(dev)
    opt = torch.optim.AdamW(net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: _lr_factor(s, cfg))
    start = 0
    if resume and last is not None and last.is_file():
        ckpt = load_checkpoint(last, DETECTOR_TRAINING_STATE, "--resume")
        if ckpt["config"] != cfg.model_config().to_dict():
            raise DetectorTrainError(
                f"{last}: was trained with {ckpt['config']}, the config asks for "
                f"{cfg.model_config().to_dict()}; use another output folder or drop --resume"
            )
        net.load_state_dict(ckpt["model"])
        opt.load_state_dict(ckpt["optimizer"])
        sched.load_state_dict(ckpt["scheduler"])
        start = int(ckpt["step"])
        log.info("resuming detector training from %s at step %d", last, start)
    return _Training(net, opt, sched, start, last)


def fit(
    views: ViewImages,
    cfg: DetectorTrainConfig,
    device: str | torch.device = "cpu",
    out_dir: Path | None = None,
    resume: bool = False,
    progress: bool = True,
    stop_after: int | None = None,
) -> tuple[DetectorNet, list[float]]:
    """Train a detector on cached views; returns the network and the per-step losses.

    With ``out_dir``, writes ``detector_last.pt`` every ``checkpoint_every`` steps (and at
    the end) and ``log.csv`` (:data:`LOG_COLUMNS`, a row every ``log_every`` steps and at
    the end); with ``resume``, continues from ``detector_last.pt`` and keeps the log rows
    up to its step.

    Args:
        views: the training views.
        cfg: the training settings.
        device: torch device.
        out_dir: the run folder (None: no checkpoints, no log).
        resume: continue from ``out_dir/detector_last.pt`` when it exists.
        progress: show a progress bar (on a terminal).
        stop_after: stop (resumable, with ``detector_last.pt``) after this many steps.

    Returns:
        The trained network (in eval mode) and the losses of the steps run by this call.

    Raises:
        DetectorTrainError: no training views, or a checkpoint of another architecture.
    """
    dev = resolve_device(device)
    if not views.images:
        raise DetectorTrainError("no training views: the labels have no labeled views with images")
    run = _start_training(cfg, dev, out_dir, resume)
    net, opt, sched, start, last = run.net, run.opt, run.sched, run.start, run.last
    log_path = None if out_dir is None else Path(out_dir) / LOG
    rows: list[dict[str, Any]] = []
    if log_path is not None:
        rows = read_log(log_path, start)
        write_log(log_path, rows)
    data = AugmentedBatches(views, cfg, cfg.steps * cfg.batch_size)
    end = cfg.steps if stop_after is None else max(start, min(cfg.steps, stop_after))
    sampler = range(start * cfg.batch_size, end * cfg.batch_size)
    loader = torch.utils.data.DataLoader(
        data,
        batch_size=cfg.batch_size,
        sampler=sampler,
        collate_fn=_collate,
        num_workers=cfg.num_workers,
    )
    net.train()
    losses: list[float] = []
    bar = progress_bar(
        total=cfg.steps, initial=start, desc="detector", unit="step", disable=not progress
    )
    step = start
    window: list[float] = []
    window_parts: list[dict[str, float]] = []
    t0 = time.perf_counter()
    for x, boxes in loader:
        out = net(x.to(dev, non_blocking=True))
        loss, parts = detection_loss(out, boxes, cfg.train_crop or cfg.input_size)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(net.parameters(), 10.0)
        opt.step()
        sched.step()
        step += 1
        lv = loss.item()
        losses.append(lv)
        window.append(lv)
        window_parts.append(parts)
        bar.update(1)
        if step % cfg.log_every == 0 or step == end:
            log.info(
                "step %d/%d loss %.4f (heat %.4f size %.4f offset %.4f) lr %.2e",
                step, cfg.steps, np.mean(window), parts["heat"], parts["size"],
                parts["offset"], sched.get_last_lr()[0],
            )  # fmt: skip
            if log_path is not None:
                lr = float(sched.get_last_lr()[0])
                rows.append(log_row(step, lr, window, window_parts, time.perf_counter() - t0))
                write_log(log_path, rows)
            window, window_parts = [], []
        if last is not None and (step % cfg.checkpoint_every == 0 or step == end):
            save_checkpoint(
                last,
                net,
                extra={
                    "optimizer": opt.state_dict(),
                    "scheduler": sched.state_dict(),
                    "step": step,
                    "box_margin": cfg.box_margin,
                },
            )
    bar.close()
    net.eval()
    return net, losses


@dataclass(frozen=True)
class _Split:
    """Training and evaluation time instants as (dataset index, sample index) pairs."""

    train: list[tuple[int, int]]
    eval: list[tuple[int, int]]


def _split_items(train_sets: list, eval_sets: list, cfg: DetectorTrainConfig) -> _Split:
    """Every labeled instant of ``train_sets`` for training, minus held-out blocks.

    Without ``eval_sets``, ``cfg.eval_fraction`` of each training set is held out as one
    contiguous block (seeded) so neighbouring frames do not leak into the evaluation.
    """
    rng = np.random.default_rng(cfg.seed)
    train_items: list[tuple[int, int]] = []
    eval_items: list[tuple[int, int]] = []
    for d, ds in enumerate(train_sets):
        idx = np.arange(len(ds))
        if not eval_sets and cfg.eval_fraction > 0 and len(idx) > 1:
            n_ev = max(1, round(cfg.eval_fraction * len(idx)))
            start = int(rng.integers(0, len(idx) - n_ev + 1))
            ev = idx[start : start + n_ev]
            eval_items += [(d, int(i)) for i in ev]
            idx = np.setdiff1d(idx, ev)
        train_items += [(d, int(i)) for i in idx]
    for d, ds in enumerate(eval_sets):
        eval_items += [(d, int(i)) for i in range(len(ds))]
    return _Split(train_items, eval_items)


def _training_views(
    train_sets: list, items: list[tuple[int, int]], cfg: DetectorTrainConfig, n_eval: int
) -> ViewImages:
    """Cache the training views of ``items``, evenly subsampled to ``cfg.max_images``."""
    n_views_est = sum(len(train_sets[d].labels.cameras) for d, _ in items[:1]) or 1
    keep = min(len(items), max(1, cfg.max_images // n_views_est))
    sel = np.unique(np.linspace(0, len(items) - 1, keep).round().astype(int))
    views = _collect_items(train_sets, [items[i] for i in sel], cfg)
    boxed = np.isfinite(views.boxes).all(-1).reshape(len(views.images), -1)  # (N, M)
    n_neg = int((~boxed.any(1)).sum())  # views with no animal at all
    used = min(n_eval, cfg.max_eval_instants)  # [detector] max_eval_instants
    log.info(
        "detector: %d training views from %d time instants (%d without the animal); %d of "
        "%d held-out time instants evaluated", len(views.images), len(sel), n_neg, used, n_eval,
    )  # fmt: skip
    return views


def _evaluate(
    det: Detector, sets: list, items: list[tuple[int, int]], cfg: DetectorTrainConfig
) -> DetectionMetrics | None:
    """Detection metrics on (at most ``cfg.max_eval_instants``, evenly picked) ``items``."""
    if not items:
        return None
    if len(items) > cfg.max_eval_instants:
        pick = np.linspace(0, len(items) - 1, cfg.max_eval_instants).round().astype(int)
        items = [items[i] for i in np.unique(pick)]
    return evaluate_source(
        det,
        (sets[d][i] for d, i in items),
        margin=cfg.box_margin,
        consistency=ConsistencyConfig(cube_size=cfg.cube_size),
        min_visible=cfg.min_visible,
    )


def _final_extra(
    cfg: DetectorTrainConfig,
    metrics: DetectionMetrics | None,
    fps: float,
    train_s: float,
    losses: list[float],
) -> dict[str, Any]:
    """What ``detector.pt`` stores next to the weights: step, config and metrics."""
    extra: dict[str, Any] = {
        "step": cfg.steps,
        "box_margin": cfg.box_margin,
        "train_config": {
            k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(cfg).items()
        },
        "metrics": {
            "cpu_fps": fps,
            "train_seconds": train_s,
            "final_loss": float(np.mean(losses[-20:])) if losses else float("nan"),
        },
    }
    if metrics is not None:
        extra["metrics"].update(dataclasses.asdict(metrics))
    return extra


def train_detector(
    config: dict, config_path: Path, out_dir: Path, resume: bool, device: str
) -> Path:
    """Train the detector as the training TOML says; returns the checkpoint path.

    Writes ``detector_last.pt``, ``log.csv`` (see :func:`fit`) and ``detector.pt`` into
    ``out_dir``. Prints the evaluation metrics and the CPU speed at the end.

    Args:
        config: the parsed training TOML (``[data]`` and ``[detector]`` tables are used).
        config_path: the TOML's path (relative data paths are relative to its folder).
        out_dir: where ``detector_last.pt``, ``log.csv`` and ``detector.pt`` go.
        resume: continue from ``out_dir/detector_last.pt`` when it exists.
        device: ``"cpu"``, ``"cuda"``, ``"cuda:1"`` or ``"auto"``.

    Returns:
        The path of ``detector.pt``.

    Raises:
        DetectorTrainError: a bad ``[data]`` or ``[detector]`` table, or no labeled instants.
        InputFileError: a labels file does not exist.
        OutputLockedError: another run is training into ``out_dir`` (nothing is touched).
    """
    cfg = DetectorTrainConfig.from_dict(config.get("detector"))
    train_paths, eval_paths, root = _data_paths(config, Path(config_path))
    for key in ("backbone_weights", "init"):  # files relative to the TOML
        v = getattr(cfg, key)
        if v and v not in ("base", "scratch") and not Path(v).is_absolute():
            cfg = dataclasses.replace(cfg, **{key: str(Path(config_path).resolve().parent / v)})
    out_dir = Path(out_dir)
    dev = resolve_device(device)
    with output_lock(out_dir / LAST, "detector run folder", option="--out"):
        return _train_into(cfg, (train_paths, eval_paths, root), out_dir, resume, dev)


def _train_into(
    cfg: DetectorTrainConfig,
    data: tuple[list[Path], list[Path], Path | None],
    out_dir: Path,
    resume: bool,
    dev: torch.device,
) -> Path:
    """The body of :func:`train_detector`, run while it holds the run folder's lock."""
    train_paths, eval_paths, root = data
    out_dir.mkdir(parents=True, exist_ok=True)
    train_sets = _datasets(train_paths, root)
    eval_sets = _datasets(eval_paths, root) if eval_paths else []
    split = _split_items(train_sets, eval_sets, cfg)
    if not split.train:
        raise DetectorTrainError(f"{train_paths}: no labeled time instants to train on")
    views = _training_views(train_sets, split.train, cfg, len(split.eval))
    t0 = time.perf_counter()
    net, losses = fit(views, cfg, dev, out_dir, resume)
    train_s = time.perf_counter() - t0
    del views
    metrics = _evaluate(Detector(net, dev), eval_sets or train_sets, split.eval, cfg)
    cpu = Detector(net.to("cpu"), "cpu")
    fps, speed_at = measure_speed(cpu, train_sets)
    net.to(dev)
    final = out_dir / FINAL
    save_checkpoint(final, net, extra=_final_extra(cfg, metrics, fps, train_s, losses))
    print(f"detector: trained {cfg.steps} steps in {train_s:.0f} s; checkpoint {final}")
    if metrics is not None:
        print(f"detector eval: {metrics.summary()}")
    else:
        print("detector eval: no evaluation data (set [data] eval_labels or eval_fraction > 0)")
    print(f"detector speed: {fps:.1f} frames/s on CPU ({speed_at})")
    return final


def _collect_items(
    sets: list, items: list[tuple[int, int]], cfg: DetectorTrainConfig
) -> ViewImages:
    parts = []
    for d, ds in enumerate(sets):
        idx = [i for dd, i in items if dd == d]
        if idx:
            parts.append(collect_views(ds, idx, cfg))
    images = [im for p in parts for im in p.images]
    return ViewImages(images, stack_boxes([b for p in parts for b in p.boxes]))

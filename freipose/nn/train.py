"""Training of the voxel network and of the triangulation baseline (``freipose train``).

Outputs in the run folder (see docs/formats.md): ``config.toml`` (the complete resolved
config), ``checkpoint.pt`` (latest state, written atomically every
``schedule.checkpoint_every`` steps), ``model.pt`` (the final checkpoint), ``log.csv``
(losses and validation metrics) and ``log.png`` (their plot).

Resuming (``resume=True``) restores the weights, the optimizer, the step and the RNG
states; the data of every step is a function of (seed, step) only, so a resumed run
continues exactly as the uninterrupted run would have. With ``torchrun`` (environment
``WORLD_SIZE`` > 1) the global batch is split over the processes and gradients are
averaged by DistributedDataParallel (gloo on CPU, NCCL on GPU).
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.distributed as dist

from freipose.errors import FreiPoseError, InputFileError
from freipose.io.atomic import atomic_path, atomic_write_text
from freipose.io.labels import read_labels_h5
from freipose.io.lock import output_lock
from freipose.nn.checkpoint import (
    read_checkpoint,
    rng_state,
    serialize_checkpoint,
    set_rng_state,
    training_checkpoint,
)
from freipose.nn.config import TrainConfig, config_to_dict, load_config
from freipose.nn.data import StepBatchSampler, TrainSamples, collate_prepared, to_device
from freipose.nn.dataset import MultiViewDataset
from freipose.nn.evaluate import jpe, predict_dataset, usable_indices
from freipose.nn.fast import bf16_support
from freipose.nn.init import initialize
from freipose.nn.instances import warn_if_one_animal
from freipose.nn.losses import baseline_losses, voxel_losses
from freipose.nn.model import build_model, optimizer_groups
from freipose.nn.sizing import resolve_cube
from freipose.nn.train_log import append_log, plot_log, read_log, write_log
from freipose.nn.types import Batch, SampleSource
from freipose.nn.unlabeled_losses import UnlabeledTraining, unlabeled_training
from freipose.nn.validation import with_validation
from freipose.skeleton import Skeleton, load_skeleton

log = logging.getLogger(__name__)


class TrainError(FreiPoseError):
    """A training run cannot start or continue (the message says why and what to do)."""


class DivergedError(TrainError, FloatingPointError):
    """The training loss is not finite (the message suggests a lower learning rate)."""


def _toml_text(data: dict[str, Any]) -> str:
    """``data`` as TOML text."""
    import tomli_w

    return tomli_w.dumps(data)


@dataclass(frozen=True)
class Processes:
    """This process's place in a (possibly distributed) run.

    Attributes:
        rank: this process's rank (0 writes the outputs).
        world: the number of processes.
        device: the device this process trains on.
    """

    rank: int
    world: int
    device: torch.device


def _distributed(device: str) -> Processes:
    """Join the process group when launched by torchrun.

    Args:
        device: ``cpu``, ``cuda`` or ``cuda:N``.

    Returns:
        The rank, the world size and this process's device.

    Raises:
        TrainError: CUDA was asked for but there is none.
    """
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise TrainError(
            "--device cuda was asked for but no CUDA GPU is available; use --device cpu"
        )
    if world <= 1:
        return Processes(0, 1, torch.device(device))
    if not dist.is_initialized():
        dist.init_process_group(backend="nccl" if device.startswith("cuda") else "gloo")
    rank = dist.get_rank()
    if device.startswith("cuda"):
        local = int(os.environ.get("LOCAL_RANK", "0"))
        torch.cuda.set_device(local)
        return Processes(rank, world, torch.device("cuda", local))
    return Processes(rank, world, torch.device(device))


def validate(
    model: torch.nn.Module, source: SampleSource, indices: np.ndarray, batch_size: int
) -> dict[str, float]:
    """Median JPE (mm) of P0 and P1 on the given samples.

    Args:
        model: the network.
        source: labeled samples.
        indices: (N,) the samples to evaluate.
        batch_size: samples per forward pass (at least 1).

    Returns:
        ``val_jpe_p0`` and ``val_jpe_p1``.
    """
    pred = predict_dataset(model, source, indices, batch_size=max(batch_size, 1))
    return {
        "val_jpe_p0": float(np.nanmedian(jpe(pred["P0"], pred["gt"]))),
        "val_jpe_p1": float(np.nanmedian(jpe(pred["P1"], pred["gt"]))),
    }


@dataclass(frozen=True)
class RunFiles:
    """The files of a run folder.

    Attributes:
        out: the run folder.
        checkpoint: ``checkpoint.pt``, the latest state.
        log: ``log.csv``.
    """

    out: Path

    @property
    def checkpoint(self) -> Path:
        """The latest state (``checkpoint.pt``)."""
        return self.out / "checkpoint.pt"

    @property
    def log(self) -> Path:
        """The losses and validation metrics (``log.csv``)."""
        return self.out / "log.csv"


def _check_run_folder(files: RunFiles, resume: bool) -> None:
    """A new run needs a folder without a checkpoint, a resumed one a checkpoint.

    Raises:
        TrainError: a new run in a folder that holds a checkpoint.
        InputFileError: ``resume`` without a checkpoint.
    """
    if not resume and files.checkpoint.exists():
        raise TrainError(
            f"{files.out} already holds a training run (checkpoint.pt); pass --resume to "
            "continue it or choose another output folder with --out"
        )
    if resume and not files.checkpoint.exists():
        raise InputFileError(f"nothing to resume: {files.checkpoint} does not exist")


@dataclass(frozen=True)
class SampleSelection:
    """The samples a run trains and validates on.

    Attributes:
        train: (N,) indices of the training samples.
        eval: (M,) indices of the validation samples (empty without validation data).
    """

    train: np.ndarray
    eval: np.ndarray


def select_samples(
    train_source: SampleSource,
    eval_source: SampleSource | None,
    train_indices: Sequence[int] | None,
    eval_indices: Sequence[int] | None,
    eval_samples: int,
) -> SampleSelection:
    """The training samples and up to ``eval_samples`` evenly spread validation samples.

    Args:
        train_source: the training samples.
        eval_source: the validation samples (or None).
        train_indices: restrict training to these (default: every sample with 3D labels).
        eval_indices: restrict validation to these (default: every sample with 3D labels).
        eval_samples: the most validation samples.

    Returns:
        The selected indices.
    """
    idx = usable_indices(train_source) if train_indices is None else np.asarray(train_indices)
    ev = np.zeros(0, np.int64)
    if eval_source is not None:
        ev = usable_indices(eval_source) if eval_indices is None else np.asarray(eval_indices)
        if len(ev) > eval_samples:
            ev = ev[np.linspace(0, len(ev) - 1, eval_samples).round().astype(int)]
    return SampleSelection(idx, ev)


def _resume(
    files: RunFiles, config: TrainConfig, model: torch.nn.Module, opt: torch.optim.Optimizer
) -> int:
    """Restore the weights, the optimizer and the random generators of ``checkpoint.pt``.

    Returns:
        The step the run continues at.

    Raises:
        TrainError: the checkpoint was trained with another model config, seed or batch
            size, or its optimizer state is of an older FreiPose.
    """
    path = files.checkpoint
    ckpt = read_checkpoint(path, "--resume")
    stored = ckpt["config"]
    mine = config_to_dict(config)
    sched = config.schedule
    # model.init only chose the starting weights (checkpoints before it have none)
    theirs = {k: v for k, v in stored["model"].items() if k != "init"}
    ours = {k: v for k, v in mine["model"].items() if k != "init"}
    if theirs != ours:
        raise TrainError(
            f"{path}: the checkpoint was trained with another [model] config; "
            f"stored {theirs}, now {ours}"
        )
    if (
        stored["schedule"]["seed"] != sched.seed
        or stored["schedule"]["batch_size"] != sched.batch_size
    ):
        raise TrainError(f"{path}: schedule.seed and schedule.batch_size must not change on resume")
    model.load_state_dict(ckpt["model"])
    groups = ckpt["optimizer"]["param_groups"]
    if len(groups) != len(opt.param_groups) or any("lr_scale" not in g for g in groups):
        raise TrainError(
            f"{path}: the checkpoint was written by an older FreiPose (its optimizer "
            f"has {len(groups)} parameter group(s) without learning-rate scales, this "
            f"version uses {len(opt.param_groups)}); it cannot be resumed: start a new run "
            "in another folder (its model.pt still works for eval and predict)"
        )
    opt.load_state_dict(ckpt["optimizer"])
    start = int(ckpt["step"])
    set_rng_state(ckpt["rng"])
    log.info("resuming %s at step %d of %d", files.out, start, sched.steps)
    return start


def _start_outputs(files: RunFiles, config: TrainConfig, start: int) -> None:
    """Write ``config.toml`` and the log of the steps before ``start``."""
    files.out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(files.out / "config.toml", _toml_text(config_to_dict(config)))
    write_log(files.log, read_log(files.log, start))


def _loader(
    source: SampleSource,
    config: TrainConfig,
    indices: np.ndarray,
    start: int,
    procs: Processes,
) -> torch.utils.data.DataLoader:
    """The batches of steps ``start ..`` for this process (deterministic in seed and step)."""
    sched = config.schedule
    sampler = StepBatchSampler(
        indices, sched.batch_size, sched.steps, sched.seed, start, procs.rank, procs.world
    )
    aug = config.augment if config.augment.enabled else None
    return torch.utils.data.DataLoader(
        TrainSamples(source, config.model, aug, sched.seed),
        batch_sampler=sampler,
        collate_fn=collate_prepared,
        num_workers=sched.num_workers,
    )


@dataclass(frozen=True)
class TrainRun:
    """Everything the steps of a run use.

    Attributes:
        config: the resolved config.
        skeleton: the keypoints (stored in the checkpoints).
        model: the network.
        net: the network as trained (``model`` wrapped by DDP with several processes).
        opt: the optimizer.
        procs: this process's rank, world and device.
        files: the run folder.
        eval_source: the validation samples (or None).
        eval_indices: the validation samples used.
        unlabeled: the unlabeled part of each step (:mod:`freipose.nn.unlabeled_losses`).
    """

    config: TrainConfig
    skeleton: Skeleton
    model: torch.nn.Module
    net: torch.nn.Module
    opt: torch.optim.Optimizer
    procs: Processes
    files: RunFiles
    eval_source: SampleSource | None
    eval_indices: np.ndarray
    unlabeled: UnlabeledTraining | None = None


def _optimizer_step(run: TrainRun, batch: Batch, step: int) -> dict[str, float]:
    """One optimizer step on ``batch``.

    Returns:
        The loss parts of the step and their weighted sum ``loss``.

    Raises:
        DivergedError: the loss is not finite.
    """
    sched, mcfg, dev = run.config.schedule, run.config.model, run.procs.device
    lr = sched.lr_at(step)
    for g in run.opt.param_groups:
        g["lr"] = lr * g["lr_scale"]
    run.net.train()
    b = to_device(batch, dev)
    amp = sched.amp and dev.type == "cuda" and bf16_support(dev)[0]
    with torch.autocast(device_type=dev.type, dtype=torch.bfloat16, enabled=amp):
        out = run.net(b)
    if mcfg.kind == "voxel":
        loss, parts = voxel_losses(out, b, mcfg, sched, sched.refine_active(step))
    else:
        loss, parts = baseline_losses(out, b, mcfg, sched)
    if run.unlabeled is not None and run.unlabeled.active(step):
        u_loss, u_parts = run.unlabeled.loss(run.net, step, dev, amp)
        loss, parts = loss + u_loss, {**parts, **u_parts}
    if not torch.isfinite(loss):
        raise DivergedError(
            f"training diverged at step {step} (loss {float(loss)}); lower schedule.lr"
        )
    run.opt.zero_grad(set_to_none=True)
    loss.backward()
    run.opt.step()
    if run.unlabeled is not None:
        run.unlabeled.after_step(run.model)
    parts["loss"] = float(loss.detach())
    return parts


def _save(run: TrainRun, step: int, final: bool) -> None:
    """Write ``checkpoint.pt`` (and ``model.pt`` when ``final``) and replot the log."""
    ckpt = training_checkpoint(
        run.model, run.config, run.skeleton, run.opt, rng_state(), step, final
    )
    data = serialize_checkpoint(ckpt)
    with atomic_path(run.files.checkpoint) as tmp:
        tmp.write_bytes(data)
    if final:
        with atomic_path(run.files.out / "model.pt") as tmp:  # settings chosen on validation
            tmp.write_bytes(serialize_checkpoint(with_validation(ckpt, run.model, run.config)))
    plot_log(run.files.log, run.files.out / "log.png", run.config.model.kind)


def _step_row(done: int, lr: float, t0: float) -> dict[str, Any]:
    """The start of a log row: step, learning rate and seconds since ``t0``."""
    return {"step": done, "lr": f"{lr:.3g}", "seconds": f"{time.perf_counter() - t0:.1f}"}


def _train_steps(
    run: TrainRun,
    loader: torch.utils.data.DataLoader,
    start: int,
    stop_after: int | None,
    progress: bool,
) -> int:
    """Train from step ``start`` to the schedule's end or ``stop_after``.

    On the way, rank 0 logs, validates and writes checkpoints as the schedule says.

    Returns:
        The number of steps done.
    """
    from freipose.progress import progress_bar

    sched, rank = run.config.schedule, run.procs.rank
    pbar = progress_bar(
        total=sched.steps, initial=start, desc=f"train {run.config.model.kind}", unit="step",
        disable=(rank != 0 or not progress) or None,
    )  # fmt: skip
    acc: dict[str, float] = {}
    nacc = 0
    t0 = time.perf_counter()
    done = start
    for step, batch in zip(range(start, sched.steps), loader):
        for k, v in _optimizer_step(run, batch, step).items():
            acc[k] = acc.get(k, 0.0) + v
        nacc += 1
        done = step + 1
        lr = sched.lr_at(step)
        last = done == sched.steps or (stop_after is not None and done >= stop_after)
        row: dict[str, Any] | None = None
        if done % sched.log_every == 0 or last:
            row = _step_row(done, lr, t0)
            row.update({k: f"{v / nacc:.6g}" for k, v in acc.items()})
            acc, nacc = {}, 0
        if (
            rank == 0
            and run.eval_source is not None
            and len(run.eval_indices)
            and (done % sched.eval_every == 0 or last)
        ):
            metrics = validate(run.model, run.eval_source, run.eval_indices, sched.batch_size)
            row = row or _step_row(done, lr, t0)
            row.update({k: f"{v:.4f}" for k, v in metrics.items()})
            pbar.set_postfix(jpe=f"{metrics['val_jpe_p1']:.1f}mm")
        if rank == 0 and row is not None:
            append_log(run.files.log, row)
            pbar.set_postfix(loss=row.get("loss"), refresh=False)
        if rank == 0 and (done % sched.checkpoint_every == 0 or last):
            _save(run, done, done == sched.steps)
        pbar.update(1)
        if last:
            break
    pbar.close()
    return done


def _run_lock(files: RunFiles, procs: Processes) -> contextlib.AbstractContextManager[Any]:
    """The lock of the run folder's ``checkpoint.pt``, held by the process that writes (rank 0).

    Raises:
        OutputLockedError: another run is writing into the folder (on entering).
    """
    if procs.rank != 0:
        return contextlib.nullcontext()
    return output_lock(files.checkpoint, "training run folder", option="--out")


def train_pose(
    config: TrainConfig,
    out_dir: str | Path,
    train_source: SampleSource,
    skeleton: Skeleton,
    eval_source: SampleSource | None = None,
    *,
    train_indices: Sequence[int] | None = None,
    eval_indices: Sequence[int] | None = None,
    resume: bool = False,
    device: str = "cpu",
    progress: bool = True,
    stop_after: int | None = None,
    unlabeled: UnlabeledTraining | None = None,
) -> Path:
    """Train the network of ``config.model.kind`` on multi-view samples.

    Args:
        config: the resolved training config.
        out_dir: the run folder (created; must not hold a checkpoint unless ``resume``).
        train_source: samples as ``MultiViewDataset`` gives them.
        skeleton: the :class:`freipose.skeleton.Skeleton` (stored in the checkpoints).
        eval_source: optional validation samples (median JPE every ``eval_every`` steps).
        train_indices: restrict training to these samples (default: all with 3D labels).
        eval_indices: restrict validation to these samples (default: all with 3D labels).
        resume: continue from ``out_dir/checkpoint.pt``.
        device: ``cpu``, ``cuda`` or ``cuda:N``.
        progress: show a progress bar with ETA.
        stop_after: stop (with a checkpoint) after this many steps, leaving the run resumable.
        unlabeled: train on unlabeled clips too (:mod:`freipose.nn.unlabeled_losses`).

    Returns:
        The path of the newest checkpoint (``model.pt`` once the run is complete).

    Raises:
        TrainError: the run folder, the device or the checkpoint to resume does not fit.
        DivergedError: the loss became infinite or NaN.
        OutputLockedError: another run is training into ``out_dir`` (nothing is touched).
    """
    files = RunFiles(Path(out_dir))
    procs = _distributed(device)
    with _run_lock(files, procs):
        sched = config.schedule
        _check_run_folder(files, resume)
        samples = select_samples(
            train_source, eval_source, train_indices, eval_indices, sched.eval_samples
        )
        torch.manual_seed(sched.seed)
        model = build_model(config.model, len(skeleton.keypoints))
        if not resume:
            initialize(model, config.model, skeleton)
        model.to(procs.device)
        opt = torch.optim.Adam(optimizer_groups(model), lr=sched.lr)
        start = _resume(files, config, model, opt) if resume else 0
        if procs.rank == 0:
            _start_outputs(files, config, start)
        net = model
        if procs.world > 1:
            dev = procs.device
            net = torch.nn.parallel.DistributedDataParallel(
                model, device_ids=[dev.index] if dev.type == "cuda" else None
            )
        run = TrainRun(
            config, skeleton, model, net, opt, procs, files, eval_source, samples.eval, unlabeled
        )
        loader = _loader(train_source, config, samples.train, start, procs)
        done = _train_steps(run, loader, start, stop_after, progress)
        if procs.world > 1:
            dist.barrier()
        return files.out / ("model.pt" if done >= sched.steps else "checkpoint.pt")


def train_from_config(
    config_path: str | Path,
    out_dir: str | Path | None = None,
    resume: bool = False,
    device: str = "cpu",
    kind: str | None = None,
    progress: bool = True,
    init: str | None = None,
) -> Path:
    """``freipose train CONFIG``: resolve the data of a config file and train.

    Relative paths in ``[data]`` and ``model.init`` are relative to the config file. ``kind``
    overrides ``model.kind`` (``voxel`` or ``baseline``), ``init`` ``model.init``. The
    default run folder is the config file's name without suffix, next to it.
    """
    config_path = Path(config_path)
    config = load_config(config_path)
    over = {k: v for k, v in (("kind", kind), ("init", init)) if v is not None}
    if over:
        config = dataclasses.replace(config, model=dataclasses.replace(config.model, **over))
    base = config_path.resolve().parent

    def rel(p: str) -> Path:
        q = Path(p).expanduser()
        return q if q.is_absolute() else base / q

    if not config.data.labels:
        raise TrainError(f"{config_path}: [data] labels is required (path of a labels.h5 file)")
    if config.model.pretrained:
        config = dataclasses.replace(
            config,
            model=dataclasses.replace(config.model, pretrained=str(rel(config.model.pretrained))),
        )
    if config.model.init not in ("base", "scratch"):
        config = dataclasses.replace(
            config, model=dataclasses.replace(config.model, init=str(rel(config.model.init)))
        )
    # the checkpoint records its data's absolute paths (freipose eval finds the training labels)
    config = dataclasses.replace(
        config,
        data=dataclasses.replace(
            config.data,
            **{k: str(rel(v).resolve()) for k in config.data.PATH_KEYS
               if (v := getattr(config.data, k))},
        ),
    )  # fmt: skip
    root = rel(config.data.root) if config.data.root else None
    cams = list(config.data.cameras) or None
    labels = read_labels_h5(rel(config.data.labels))
    config = resolve_cube(config, labels)  # model.cube_size "auto": from the labels' extent
    train_ds = MultiViewDataset(labels, root=root or rel(config.data.labels).parent, cameras=cams)
    warn_if_one_animal(config.model.mask_others, labels.individuals)
    eval_ds = None
    if config.data.eval_labels:
        ev_path = rel(config.data.eval_labels)
        eval_ds = MultiViewDataset(
            read_labels_h5(ev_path), root=root or ev_path.parent, cameras=cams
        )
        if eval_ds.labels.keypoints != labels.keypoints:
            raise TrainError(
                f"eval labels keypoints {list(eval_ds.labels.keypoints)} differ from the training "
                f"labels keypoints {list(labels.keypoints)}"
            )
    if config.data.skeleton:
        sk_src = config.data.skeleton
        skeleton = load_skeleton(sk_src if sk_src in ("rat", "mouse", "paw") else rel(sk_src))
        if tuple(skeleton.keypoints) != tuple(labels.keypoints):
            raise TrainError(
                f"skeleton {skeleton.name!r} keypoints {list(skeleton.keypoints)} do not match the "
                f"labels keypoints {list(labels.keypoints)} (same names, same order needed)"
            )
    else:
        skeleton = Skeleton(name="labels", keypoints=tuple(labels.keypoints))
    out = Path(out_dir) if out_dir is not None else config_path.with_suffix("")
    return train_pose(
        config, out, train_ds, skeleton, eval_ds, resume=resume, device=device, progress=progress,
        unlabeled=unlabeled_training(config, base, labels, cams),  # None without [unlabeled]
    )  # fmt: skip

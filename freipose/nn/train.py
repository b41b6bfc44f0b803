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

import csv
import logging
import os
import random
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.distributed as dist

from freipose import __version__
from freipose.io.atomic import atomic_path, atomic_write_text
from freipose.nn.config import TrainConfig, config_to_dict
from freipose.nn.data import StepBatchSampler, TrainSamples, collate_prepared, to_device
from freipose.nn.evaluate import jpe, predict_dataset, usable_indices
from freipose.nn.losses import baseline_losses, voxel_losses
from freipose.nn.model import (
    CHECKPOINT_FORMAT,
    CHECKPOINT_VERSION,
    build_model,
    optimizer_groups,
    read_checkpoint,
    serialize_checkpoint,
    state_hash,
)

log = logging.getLogger(__name__)

LOG_COLUMNS = [
    "step",
    "lr",
    "loss",
    "p0",
    "aux",
    "vol",
    "2d",
    "conf",
    "p1",
    "val_jpe_p0",
    "val_jpe_p1",
    "seconds",
]


def _toml_text(data: dict[str, Any]) -> str:
    import tomli_w

    return tomli_w.dumps(data)


def _distributed(device: str) -> tuple[int, int, torch.device]:
    """Join the process group when launched by torchrun; returns (rank, world, device)."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise ValueError(
            "--device cuda was asked for but no CUDA GPU is available; use --device cpu"
        )
    if world <= 1:
        return 0, 1, torch.device(device)
    if not dist.is_initialized():
        dist.init_process_group(backend="nccl" if device.startswith("cuda") else "gloo")
    rank = dist.get_rank()
    if device.startswith("cuda"):
        local = int(os.environ.get("LOCAL_RANK", "0"))
        torch.cuda.set_device(local)
        return rank, world, torch.device("cuda", local)
    return rank, world, torch.device(device)


def _read_log(path: Path, upto: int) -> list[dict[str, str]]:
    if not path.exists():
        return []
    with path.open(newline="") as f:
        return [r for r in csv.DictReader(f) if r.get("step") and int(r["step"]) <= upto]


def _write_log(path: Path, rows: list[dict[str, Any]]) -> None:
    lines = [",".join(LOG_COLUMNS)]
    for r in rows:
        lines.append(",".join(str(r.get(c, "")) for c in LOG_COLUMNS))
    atomic_write_text(path, "\n".join(lines) + "\n")


def plot_log(csv_path: str | Path, png_path: str | Path) -> None:
    """Plot the training log: losses (log scale) and validation JPE against the step."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = _read_log(Path(csv_path), 1 << 62)
    if not rows:
        return
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 4))
    steps = np.array([int(r["step"]) for r in rows])
    for c in ("loss", "p0", "aux", "vol", "2d", "conf", "p1"):
        v = np.array([float(r[c]) if r.get(c) not in (None, "") else np.nan for r in rows])
        if np.isfinite(v).any():
            a1.plot(steps, v, label=c)
    a1.set_yscale("log")
    a1.set_xlabel("step")
    a1.set_title("training losses")
    a1.legend(fontsize=8)
    for c in ("val_jpe_p0", "val_jpe_p1"):
        v = np.array([float(r[c]) if r.get(c) not in (None, "") else np.nan for r in rows])
        ok = np.isfinite(v)
        if ok.any():
            a2.plot(steps[ok], v[ok], "o-", label=c)
    a2.set_xlabel("step")
    a2.set_ylabel("median JPE (mm)")
    a2.set_title("validation")
    if a2.get_legend_handles_labels()[0]:
        a2.legend(fontsize=8)
    fig.tight_layout()
    with atomic_path(png_path) as tmp:
        fig.savefig(tmp, format="png", dpi=100)
    plt.close(fig)


def _rng_state() -> dict[str, Any]:
    st = {
        "torch": torch.get_rng_state(),
        "numpy": np.random.get_state(),
        "python": random.getstate(),
    }
    if torch.cuda.is_available():
        st["cuda"] = torch.cuda.get_rng_state_all()
    return st


def _set_rng_state(st: dict[str, Any]) -> None:
    torch.set_rng_state(st["torch"])
    np.random.set_state(st["numpy"])
    random.setstate(st["python"])
    if "cuda" in st and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(st["cuda"])


def validate(
    model: torch.nn.Module, source: Sequence[dict[str, Any]], indices: np.ndarray, batch_size: int
) -> dict[str, float]:
    """Median JPE (mm) of P0 and P1 on the given samples."""
    pred = predict_dataset(model, source, indices, batch_size=max(batch_size, 1))
    return {
        "val_jpe_p0": float(np.nanmedian(jpe(pred["P0"], pred["gt"]))),
        "val_jpe_p1": float(np.nanmedian(jpe(pred["P1"], pred["gt"]))),
    }


def train_pose(
    config: TrainConfig,
    out_dir: str | Path,
    train_source: Sequence[dict[str, Any]],
    skeleton: Any,
    eval_source: Sequence[dict[str, Any]] | None = None,
    *,
    train_indices: Sequence[int] | None = None,
    eval_indices: Sequence[int] | None = None,
    resume: bool = False,
    device: str = "cpu",
    progress: bool = True,
    stop_after: int | None = None,
) -> Path:
    """Train the network of ``config.model.kind`` on multi-view samples.

    Args:
        config: the resolved training config.
        out_dir: the run folder (created; must not hold a checkpoint unless ``resume``).
        train_source: samples as ``MultiViewDataset`` gives them.
        skeleton: the :class:`freipose.skeleton.Skeleton` (stored in the checkpoints).
        eval_source: optional validation samples (median JPE every ``eval_every`` steps).
        train_indices / eval_indices: restrict to these samples (default: all with 3D labels).
        resume: continue from ``out_dir/checkpoint.pt``.
        device: ``cpu``, ``cuda`` or ``cuda:N``.
        progress: show a progress bar with ETA.
        stop_after: stop (with a checkpoint) after this many steps, leaving the run resumable.

    Returns:
        The path of the newest checkpoint (``model.pt`` once the run is complete).
    """
    from tqdm import tqdm

    out = Path(out_dir)
    sched, mcfg = config.schedule, config.model
    nk = len(skeleton.keypoints)
    rank, world, dev = _distributed(device)
    ckpt_path, log_path = out / "checkpoint.pt", out / "log.csv"
    if not resume and ckpt_path.exists():
        raise ValueError(
            f"{out} already holds a training run (checkpoint.pt); pass --resume to continue it "
            "or choose another output folder with --out"
        )
    if resume and not ckpt_path.exists():
        raise FileNotFoundError(f"nothing to resume: {ckpt_path} does not exist")
    idx = usable_indices(train_source) if train_indices is None else np.asarray(train_indices)
    if eval_source is not None:
        ev = usable_indices(eval_source) if eval_indices is None else np.asarray(eval_indices)
        if len(ev) > sched.eval_samples:
            ev = ev[np.linspace(0, len(ev) - 1, sched.eval_samples).round().astype(int)]
    torch.manual_seed(sched.seed)
    model = build_model(mcfg, nk).to(dev)
    opt = torch.optim.Adam(optimizer_groups(model), lr=sched.lr)
    start = 0
    if resume:
        ckpt = read_checkpoint(ckpt_path)
        stored = ckpt["config"]
        mine = config_to_dict(config)
        for table in ("model",):
            if stored[table] != mine[table]:
                raise ValueError(
                    f"{ckpt_path}: the checkpoint was trained with another [{table}] config; "
                    f"stored {stored[table]}, now {mine[table]}"
                )
        if (
            stored["schedule"]["seed"] != sched.seed
            or stored["schedule"]["batch_size"] != sched.batch_size
        ):
            raise ValueError(
                f"{ckpt_path}: schedule.seed and schedule.batch_size must not change on resume"
            )
        model.load_state_dict(ckpt["model"])
        groups = ckpt["optimizer"]["param_groups"]
        if len(groups) != len(opt.param_groups) or any("lr_scale" not in g for g in groups):
            raise ValueError(
                f"{ckpt_path}: the checkpoint was written by an older FreiPose (its optimizer "
                f"has {len(groups)} parameter group(s) without learning-rate scales, this "
                f"version uses {len(opt.param_groups)}); it cannot be resumed: start a new run "
                "in another folder (its model.pt still works for eval and predict)"
            )
        opt.load_state_dict(ckpt["optimizer"])
        start = int(ckpt["step"])
        _set_rng_state(ckpt["rng"])
        log.info("resuming %s at step %d of %d", out, start, sched.steps)
    rows: list[dict[str, Any]] = []
    if rank == 0:
        out.mkdir(parents=True, exist_ok=True)
        atomic_write_text(out / "config.toml", _toml_text(config_to_dict(config)))
        rows = _read_log(log_path, start)
        _write_log(log_path, rows)
    net = model
    if world > 1:
        net = torch.nn.parallel.DistributedDataParallel(
            model, device_ids=[dev.index] if dev.type == "cuda" else None
        )
    sampler = StepBatchSampler(idx, sched.batch_size, sched.steps, sched.seed, start, rank, world)
    aug = config.augment if config.augment.enabled else None
    loader = torch.utils.data.DataLoader(
        TrainSamples(train_source, mcfg, aug, sched.seed),
        batch_sampler=sampler,
        collate_fn=collate_prepared,
        num_workers=sched.num_workers,
    )
    amp = sched.amp and dev.type == "cuda"

    def save(step: int, final: bool) -> None:
        state = {k: v.detach().cpu() for k, v in model.state_dict().items()}
        ckpt = {
            "format": CHECKPOINT_FORMAT,
            "version": CHECKPOINT_VERSION,
            "freipose_version": __version__,
            "kind": mcfg.kind,
            "step": step,
            "complete": final,
            "config": config_to_dict(config),
            "skeleton": skeleton.to_dict(),
            "model": state,
            "weights_sha256": state_hash(state),
            "optimizer": opt.state_dict(),
            "rng": _rng_state(),
        }
        data = serialize_checkpoint(ckpt)
        with atomic_path(ckpt_path) as tmp:
            tmp.write_bytes(data)
        if final:
            with atomic_path(out / "model.pt") as tmp:
                tmp.write_bytes(data)
        plot_log(log_path, out / "log.png")

    pbar = tqdm(
        total=sched.steps,
        initial=start,
        desc=f"train {mcfg.kind}",
        unit="step",
        disable=(rank != 0 or not progress) or None,
        dynamic_ncols=True,
    )
    acc: dict[str, float] = {}
    nacc = 0
    t0 = time.perf_counter()
    done = start
    for step, batch in zip(range(start, sched.steps), loader):
        lr = sched.lr_at(step)
        for g in opt.param_groups:
            g["lr"] = lr * g["lr_scale"]
        net.train()
        b = to_device(batch, dev)
        with torch.autocast(device_type=dev.type, dtype=torch.bfloat16, enabled=amp):
            out_ = net(b)
        if mcfg.kind == "voxel":
            loss, parts = voxel_losses(out_, b, mcfg, sched, sched.refine_active(step))
        else:
            loss, parts = baseline_losses(out_, b, mcfg, sched)
        if not torch.isfinite(loss):
            raise FloatingPointError(
                f"training diverged at step {step} (loss {float(loss)}); lower schedule.lr"
            )
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        parts["loss"] = float(loss.detach())
        for k, v in parts.items():
            acc[k] = acc.get(k, 0.0) + v
        nacc += 1
        done = step + 1
        last = done == sched.steps or (stop_after is not None and done >= stop_after)
        row: dict[str, Any] | None = None
        if done % sched.log_every == 0 or last:
            row = {"step": done, "lr": f"{lr:.3g}", "seconds": f"{time.perf_counter() - t0:.1f}"}
            row.update({k: f"{v / nacc:.6g}" for k, v in acc.items()})
            acc, nacc = {}, 0
        if (
            rank == 0
            and eval_source is not None
            and len(ev)
            and (done % sched.eval_every == 0 or last)
        ):
            metrics = validate(model, eval_source, ev, sched.batch_size)
            row = row or {
                "step": done,
                "lr": f"{lr:.3g}",
                "seconds": f"{time.perf_counter() - t0:.1f}",
            }
            row.update({k: f"{v:.4f}" for k, v in metrics.items()})
            pbar.set_postfix(jpe=f"{metrics['val_jpe_p1']:.1f}mm")
        if rank == 0 and row is not None:
            rows.append(row)
            with log_path.open("a") as f:
                f.write(",".join(str(row.get(c, "")) for c in LOG_COLUMNS) + "\n")
            pbar.set_postfix(loss=row.get("loss"), refresh=False)
        if rank == 0 and (done % sched.checkpoint_every == 0 or last):
            save(done, done == sched.steps)
        pbar.update(1)
        if last:
            break
    pbar.close()
    if world > 1:
        dist.barrier()
    return out / ("model.pt" if done >= sched.steps else "checkpoint.pt")


def train_from_config(
    config_path: str | Path,
    out_dir: str | Path | None = None,
    resume: bool = False,
    device: str = "cpu",
    kind: str | None = None,
    progress: bool = True,
) -> Path:
    """``freipose train CONFIG``: resolve the data of a config file and train.

    Relative paths in ``[data]`` are relative to the config file. ``kind`` overrides
    ``model.kind`` (``voxel`` or ``baseline``). The default run folder is the config file's
    name without suffix, next to it.
    """
    import dataclasses

    from freipose.io.labels import read_labels_h5
    from freipose.labels.dataset import MultiViewDataset
    from freipose.nn.config import load_config
    from freipose.skeleton import Skeleton, load_skeleton

    config_path = Path(config_path)
    config = load_config(config_path)
    if kind is not None:
        config = dataclasses.replace(config, model=dataclasses.replace(config.model, kind=kind))
    base = config_path.resolve().parent

    def rel(p: str) -> Path:
        q = Path(p).expanduser()
        return q if q.is_absolute() else base / q

    if not config.data.labels:
        raise ValueError(f"{config_path}: [data] labels is required (path of a labels.h5 file)")
    if config.model.pretrained:
        config = dataclasses.replace(
            config,
            model=dataclasses.replace(config.model, pretrained=str(rel(config.model.pretrained))),
        )
    root = rel(config.data.root) if config.data.root else None
    cams = list(config.data.cameras) or None
    labels = read_labels_h5(rel(config.data.labels))
    train_ds = MultiViewDataset(labels, root=root or rel(config.data.labels).parent, cameras=cams)
    eval_ds = None
    if config.data.eval_labels:
        ev_path = rel(config.data.eval_labels)
        eval_ds = MultiViewDataset(
            read_labels_h5(ev_path), root=root or ev_path.parent, cameras=cams
        )
        if eval_ds.labels.keypoints != labels.keypoints:
            raise ValueError(
                f"eval labels keypoints {list(eval_ds.labels.keypoints)} differ from the training "
                f"labels keypoints {list(labels.keypoints)}"
            )
    if config.data.skeleton:
        sk_src = config.data.skeleton
        skeleton = load_skeleton(sk_src if sk_src in ("rat", "mouse", "paw") else rel(sk_src))
        if tuple(skeleton.keypoints) != tuple(labels.keypoints):
            raise ValueError(
                f"skeleton {skeleton.name!r} keypoints {list(skeleton.keypoints)} do not match the "
                f"labels keypoints {list(labels.keypoints)} (same names, same order needed)"
            )
    else:
        skeleton = Skeleton(name="labels", keypoints=tuple(labels.keypoints))
    out = Path(out_dir) if out_dir is not None else config_path.with_suffix("")
    return train_pose(
        config, out, train_ds, skeleton, eval_ds, resume=resume, device=device, progress=progress
    )

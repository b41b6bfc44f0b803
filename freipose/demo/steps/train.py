"""Step 4, ``train``: the detector, the voxel network and the baseline (``freipose train``)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from freipose.demo.context import DemoContext, save_png
from freipose.io.atomic import atomic_write_text


def _write_if_changed(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` (atomically) unless the file already holds it."""
    if not path.is_file() or path.read_text(encoding="utf-8") != text:
        atomic_write_text(path, text)


def _train_config(ctx: DemoContext) -> Path:
    """Write ``train/config.toml``: the preset's data, model, schedule and detector tables."""
    import tomli_w

    p = ctx.preset
    pose = dict(p.pose)
    augment = dict(pose.pop("augment", {}))
    doc = {
        "data": {
            "labels": "../labels/train.h5",
            "eval_labels": "../labels/eval.h5",
            "skeleton": "rat",
        },
        "model": {"preset": pose.pop("preset"), "init": p.init},
        "schedule": pose,
        **({"augment": augment} if augment else {}),
        "detector": {**p.detector, "init": p.init},
    }
    path = ctx.train_dir / "config.toml"
    text = (
        f"# written by freipose demo (preset {p.name}); train with\n"
        "#   freipose train config.toml --stage detector --out detector\n"
        "#   freipose train config.toml --out pose\n"
        "#   freipose train config.toml --stage baseline --out baseline\n"
    ) + tomli_w.dumps(doc)
    path.parent.mkdir(parents=True, exist_ok=True)
    _write_if_changed(path, text)
    return path


def _plot_detector_curve(rows: list[tuple[int, float]], path: Path) -> None:
    """The detector's training loss (log scale) against the step."""
    from freipose.io.figures import new_figure

    fig = new_figure(figsize=(5, 3))
    ax = fig.add_subplot()
    if rows:
        s, v = zip(*rows)
        ax.plot(s, v, "-o", ms=3)
    ax.set_xlabel("step")
    ax.set_ylabel("detection loss")
    ax.set_yscale("log")
    ax.grid(alpha=0.3)
    ax.set_title("detector training", fontsize=10)
    save_png(fig, path)


def _train_detector(ctx: DemoContext, data: dict[str, Any], cfg_path: Path) -> dict[str, Any]:
    """Train the detector into ``train/detector`` (unless done) and plot its ``log.csv``."""
    import torch

    from freipose.detect.train import train_detector
    from freipose.detect.train_log import LOG, read_log

    det_dir = ctx.train_dir / "detector"
    ctx.say("  detector (CenterNet-style boxes in every view, made consistent in 3D)")
    det_ckpt = det_dir / "detector.pt"
    if not det_ckpt.is_file():
        det_ckpt = train_detector(
            data, cfg_path, det_dir, (det_dir / "detector_last.pt").is_file(), ctx.device
        )
    rows = [(int(r["step"]), float(r["loss"])) for r in read_log(det_dir / LOG)]
    _plot_detector_curve(rows, det_dir / "losses.png")
    metrics = torch.load(det_ckpt, map_location="cpu", weights_only=False).get("metrics", {})
    return {"checkpoint": str(det_ckpt), "metrics": metrics}


def _last_log_row(path: Path) -> dict[str, str]:
    """The newest non-empty value of every column of a pose trainer's ``log.csv``."""
    if not path.is_file():
        return {}
    lines = [ln for ln in path.read_text().splitlines() if ln.strip()]
    if len(lines) < 2:
        return {}
    head = lines[0].split(",")
    best: dict[str, str] = {}
    for ln in lines[1:]:
        row = dict(zip(head, ln.split(",")))
        for k, v in row.items():
            if v != "":
                best[k] = v
    return best


def _train_network(ctx: DemoContext, kind: str | None, sub: str, path_cfg: Path) -> dict[str, Any]:
    """Train the voxel network (``kind`` None) or the baseline into ``train/<sub>``."""
    from freipose.nn.train import train_from_config

    run = ctx.train_dir / sub
    model = run / "model.pt"
    if not model.is_file():
        model = train_from_config(
            path_cfg,
            run,
            resume=(run / "checkpoint.pt").is_file(),
            device=ctx.device,
            kind=kind,
            progress=ctx.progress is not False,
        )
    out: dict[str, Any] = {"checkpoint": str(model), "log": str(run / "log.csv")}
    last = _last_log_row(run / "log.csv")
    if last:
        out["last_log"] = last
        v = last.get("val_jpe_p1") or last.get("val_jpe_p0")
        ctx.say(f"    final loss {last.get('loss')}, validation JPE {v or 'n/a'} mm")
    return out


def run(ctx: DemoContext) -> dict[str, Any]:
    """Train the detector, the voxel network and the triangulation baseline (or keep them).

    Args:
        ctx: the demo run.

    Returns:
        ``config`` (the training TOML), ``detector`` (checkpoint and metrics), ``pose`` and
        ``baseline`` (checkpoint, log and its last values).
    """
    from freipose.io.toml import read_toml

    cfg_path = _train_config(ctx)
    data = read_toml(cfg_path, "training config")
    steps = int(data["schedule"]["steps"])
    views = int(data.get("augment", {}).get("max_views", 0))
    if 0 < views < ctx.preset.n_cameras:
        steps_text = f"{steps} steps of {views} random views of {ctx.preset.n_cameras} per sample"
    else:
        steps_text = f"{steps} steps"
    out: dict[str, Any] = {"config": str(cfg_path), "init": ctx.preset.init}
    ctx.say(
        "  fine-tuning the base models shipped with FreiPose (freipose/models)"
        if ctx.preset.init == "base"
        else '  from random weights (init = "scratch")'
    )
    out["detector"] = _train_detector(ctx, data, cfg_path)
    ctx.say(f"  voxel network (2D encoder, unprojection, 3D U-Net, refinement), {steps_text}")
    out["pose"] = _train_network(ctx, None, "pose", cfg_path)
    ctx.say(f"  triangulation baseline (per-view 2D + robust triangulation), {steps_text}")
    # equal budgets: the baseline trains with the voxel network's schedule
    out["baseline"] = _train_network(ctx, "baseline", "baseline", cfg_path)
    out["budgets"] = {
        "voxel_steps": steps,
        "baseline_steps": steps,
        "detector_steps": int(data["detector"]["steps"]),
        "views_per_sample": views or ctx.preset.n_cameras,
    }
    return out

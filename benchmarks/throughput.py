"""Inference throughput and training step time of the pose networks, per backend, same run.

For each backend of :mod:`freipose.nn.fast` (``--backends``, default ``eager optimized
bf16``) times :func:`freipose.nn.inference.predict_batch` (crops from full frames + network,
inference mode) and the network's forward pass alone, for the voxel network and for the
triangulation baseline of the same preset (whose 3D step is the robust triangulation on the
CPU); prints each forward pass's achieved GFLOP/s (``FlopCounterMode``: convolutions and
matrix products), the fp32 2048 x 2048 matmul roofline of the same threads and their ratio.
Then times training steps (forward, losses, backward, Adam) of the voxel network on
rendered frames of the synthetic rat with the demo's settings (4 views per sample, the
preset's batch size), ``eager`` against ``optimized``. Every figure is the median of
``--repeats`` runs alternated between the backends (shared machines are noisy). Weights are
random unless ``--ckpt`` is given (speed does not depend on them). Inference frames come from
the synthetic default rig (7 cameras, 320x256).

Example::

    python benchmarks/throughput.py --preset small --device cpu
    python benchmarks/throughput.py --preset paper --device cuda --batch 4 --train-steps 200
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
from _results import write_result


def _train_steps(args: argparse.Namespace, backends: list[str]) -> dict[str, float]:
    """Median seconds of one training step per backend (alternated, same batches)."""
    import torch

    from freipose.nn.config import config_from_dict
    from freipose.nn.data import TrainSamples, collate_prepared, to_device
    from freipose.nn.dataset import MultiViewDataset
    from freipose.nn.fast import inference_autocast, optimize
    from freipose.nn.losses import voxel_losses
    from freipose.nn.model import build_model, optimizer_groups
    from freipose.synth import SceneConfig, generate_session

    paths = generate_session(
        Path(tempfile.mkdtemp(prefix="fp_bench_train_")) / "s",
        SceneConfig(n_cameras=7, frames=16, size=(320, 256), seed=3),
        progress=False,
    )
    source = MultiViewDataset(paths.labels)
    cfg = config_from_dict(
        {
            "model": {"preset": args.preset},
            "schedule": {"refine_start": 0.0},
            "augment": {"max_views": 4},
        }
    )
    bs = cfg.schedule.batch_size
    samples = TrainSamples(source, cfg.model, cfg.augment, 0)
    dev = torch.device(args.device)
    keys = [[((s * bs + i) % len(source), s) for i in range(bs)] for s in range(8)]
    batches = [to_device(collate_prepared([samples[k] for k in ks]), dev) for ks in keys]
    runs = {}
    for name in backends:
        torch.manual_seed(0)
        model = optimize(build_model(cfg.model, len(source[0]["points3d"])).to(dev), name)
        model.train()
        runs[name] = (model, torch.optim.Adam(optimizer_groups(model), lr=1e-3))

    def step(name: str, b: dict) -> float:
        model, opt = runs[name]
        with inference_autocast(model, dev):
            out = model(b)
        loss, _ = voxel_losses(out, b, cfg.model, cfg.schedule, True)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if dev.type == "cuda":
            torch.cuda.synchronize()
        return float(loss.detach())

    times: dict[str, list[float]] = {k: [] for k in runs}
    for name in runs:
        step(name, batches[0])  # warm-up
    for s in range(args.train_steps):
        for name in runs:
            t = time.perf_counter()
            step(name, batches[s % len(batches)])
            times[name].append(time.perf_counter() - t)
    return {k: statistics.median(v) for k, v in times.items()}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--preset", default="small")
    ap.add_argument("--ckpt", help="a trained checkpoint instead of a preset")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--cameras", type=int, default=7)
    ap.add_argument("--size", type=int, nargs=2, default=(320, 256))
    ap.add_argument("--batch", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--backends", nargs="+", default=["eager", "optimized", "bf16"])
    ap.add_argument(
        "--train-steps", type=int, default=20, help="timed training steps per backend (0: none)"
    )
    args = ap.parse_args(argv)

    import torch

    from freipose.nn.checkpoint import load_checkpoint
    from freipose.nn.config import config_from_dict
    from freipose.nn.data import collate_prepared, prepare_sample, to_device
    from freipose.nn.fast import forward_flops, inference_autocast, matmul_roofline, optimize
    from freipose.nn.inference import predict_batch
    from freipose.nn.model import build_model
    from freipose.synth import default_rig

    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1")))
    from freipose.workers import keep_freed_memory

    keep_freed_memory()  # as the commands do (cli/_threads.py)
    rig = default_rig(args.cameras, tuple(args.size), seed=0)
    rng = np.random.default_rng(0)
    images = [
        [rng.integers(0, 255, (c.height, c.width, 3), dtype=np.uint8) for c in rig]
        for _ in range(args.batch)
    ]
    centers = rng.normal(0, 30, (args.batch, 3)) + np.array([0, 0, 40.0])
    models = {}
    for backend in args.backends:
        if args.ckpt:
            model, cfg, _ = load_checkpoint(args.ckpt, args.device)
            models[(cfg.model.kind, backend)] = optimize(model, backend)
            label = f"checkpoint {args.ckpt}"
            continue
        cfg = config_from_dict({"model": {"preset": args.preset}})
        for kind in ("voxel", "baseline"):
            torch.manual_seed(0)
            mc = dataclasses.replace(cfg.model, kind=kind)
            models[(kind, backend)] = optimize(build_model(mc, 12).to(args.device).eval(), backend)
        label = f"preset {args.preset}"
    dev = torch.device(args.device)
    print(
        f"{label}, device {args.device} ({torch.get_num_threads()} CPU threads), "
        f"{args.cameras} cameras {args.size[0]}x{args.size[1]}, batch {args.batch}, "
        f"medians of {args.repeats} alternated runs"
    )
    fns, flops = {}, {}
    for key, model in models.items():
        items = [
            prepare_sample(
                {"rig": rig, "images": images[i], "index": i}, model.cfg, center=centers[i]
            )
            for i in range(args.batch)
        ]
        batch = to_device(collate_prepared(items), dev)
        flops[key] = forward_flops(model, batch) / args.batch

        def forward(model=model, batch=batch):
            with torch.inference_mode(), inference_autocast(model, dev):
                model(batch)
            if dev.type == "cuda":
                torch.cuda.synchronize()

        def full(model=model):
            predict_batch(model, images, [rig] * args.batch, centers)

        fns[key] = (forward, full)
        forward()  # warm-up
        full()
    runs: dict[tuple, list[list[float]]] = {k: [[], []] for k in models}
    roofs = []
    for _ in range(args.repeats):
        roofs.append(matmul_roofline(device=args.device))
        for key, (forward, full) in fns.items():
            for j, fn in enumerate((forward, full)):
                t = time.perf_counter()
                fn()
                runs[key][j].append(args.batch / (time.perf_counter() - t))
    roof = statistics.median(roofs)
    print(f"  fp32 2048x2048 matmul roofline: {roof:.1f} GFLOP/s (same threads)")
    figures: dict[str, float] = {"matmul_gflops": roof}
    for (kind, backend), (fw, e2e) in runs.items():
        f, e = statistics.median(fw), statistics.median(e2e)
        g = flops[(kind, backend)] / 1e9 * f
        print(
            f"  {kind:8s} {backend:9s}: forward {f:7.2f} samples/s, end-to-end (crops + net + "
            f"3D) {e:7.2f} samples/s; {g:6.1f} GFLOP/s = {g / roof:.1%} of the roofline"
        )
        figures.update({
            f"{kind}/{backend}/forward_samples_per_s": f,
            f"{kind}/{backend}/end_to_end_samples_per_s": e,
            f"{kind}/{backend}/gflops": g,
            f"{kind}/{backend}/roofline_fraction": g / roof,
        })  # fmt: skip
    ref = args.backends[0]
    for kind, backend in runs:
        if backend != ref and (kind, ref) in runs:
            r = statistics.median(runs[(kind, backend)][1]) / statistics.median(
                runs[(kind, ref)][1]
            )
            print(f"  {kind} {backend} / {ref} end to end: {r:.2f}x")
            figures[f"{kind}/{backend}/speedup_end_to_end"] = r
    if args.train_steps > 0 and not args.ckpt:
        train_backends = [b for b in args.backends if b in ("eager", "optimized")]
        steps = _train_steps(args, train_backends)
        for name, s in steps.items():
            print(f"  training step ({name}): {s * 1000:.0f} ms (voxel, 4 views per sample)")
            figures[f"train/{name}/step_s"] = s
        if {"eager", "optimized"} <= steps.keys():
            r = steps["eager"] / steps["optimized"]
            print(f"  training step eager / optimized: {r:.2f}x (target >= 1.5x)")
            figures["train/speedup"] = r
    settings = {k: str(v) for k, v in vars(args).items()}
    write_result(
        "throughput", figures, extra={**settings, "torch_threads": torch.get_num_threads()}
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Inference throughput of the voxel network (multi-view samples per second).

Times :func:`freipose.nn.inference.predict_batch` (crops from full frames + network, inference
mode, autocast on GPU) and the network's forward pass alone, for the voxel network and for
the triangulation baseline of the same preset in the same run (whose 3D step is the robust
triangulation on the CPU). Weights are random unless ``--ckpt`` is given (speed does not
depend on them). Frames come from the synthetic default rig (7 cameras, 320x256).

Example::

    python benchmarks/throughput.py --preset small --device cpu
    python benchmarks/throughput.py --preset paper --device cuda --batch 4
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import time

import numpy as np
from _results import write_result


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--preset", default="small")
    ap.add_argument("--ckpt", help="a trained checkpoint instead of a preset")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--cameras", type=int, default=7)
    ap.add_argument("--size", type=int, nargs=2, default=(320, 256))
    ap.add_argument("--batch", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args(argv)

    import torch

    from freipose.nn.checkpoint import load_checkpoint
    from freipose.nn.config import config_from_dict
    from freipose.nn.data import collate_prepared, prepare_sample, to_device
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
    if args.ckpt:
        model, cfg, _ = load_checkpoint(args.ckpt, args.device)
        models = {cfg.model.kind: model}
        label = f"checkpoint {args.ckpt}"
    else:
        cfg = config_from_dict({"model": {"preset": args.preset}})
        models = {}
        for kind in ("voxel", "baseline"):
            torch.manual_seed(0)
            mc = dataclasses.replace(cfg.model, kind=kind)
            models[kind] = build_model(mc, 12).to(args.device).eval()
        label = f"preset {args.preset}"
    dev = torch.device(args.device)
    print(
        f"{label}, device {args.device} ({torch.get_num_threads()} CPU threads), "
        f"{args.cameras} cameras {args.size[0]}x{args.size[1]}, batch {args.batch}"
    )
    results = {}
    for kind, model in models.items():
        items = [
            prepare_sample(
                {"rig": rig, "images": images[i], "index": i}, model.cfg, center=centers[i]
            )
            for i in range(args.batch)
        ]
        batch = to_device(collate_prepared(items), dev)
        amp = dev.type == "cuda"

        def forward(model=model, batch=batch, amp=amp):
            with torch.inference_mode(), torch.autocast(dev.type, torch.bfloat16, enabled=amp):
                model(batch)
            if dev.type == "cuda":
                torch.cuda.synchronize()

        def full(model=model):
            predict_batch(model, images, [rig] * args.batch, centers)

        for fn in (forward, full):
            fn()  # warm-up
        t = {}
        for name, fn in (("forward", forward), ("end-to-end", full)):
            t0 = time.perf_counter()
            for _ in range(args.repeats):
                fn()
            t[name] = args.batch * args.repeats / (time.perf_counter() - t0)
        results[kind] = t
        print(
            f"  {kind:9s}: forward {t['forward']:8.2f} samples/s, "
            f"end-to-end (crops + net + 3D) {t['end-to-end']:8.2f} samples/s"
        )
    if len(results) == 2:
        r = results["voxel"]["end-to-end"] / results["baseline"]["end-to-end"]
        print(f"  voxel / baseline end-to-end throughput ratio: {r:.2f}")
    figures = {f"{k} samples/s": v for k, v in results.items()}
    settings = {k: str(v) for k, v in vars(args).items()}
    write_result(
        "throughput", figures, extra={**settings, "torch_threads": torch.get_num_threads()}
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

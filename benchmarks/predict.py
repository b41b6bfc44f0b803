"""Prediction throughput: end-to-end frames/s against decode-only and network-only, same run.

On a synthetic session (``freipose.synth.generate_session``), measures

* **decode**: all camera streams decoded and batched by the background-thread reader
  (:class:`freipose.predict.reader.SyncReader`), nothing else;
* **network**: the estimator (box source + voxel network) on batches already in memory;
* **end-to-end**: ``predict_session`` (decoding ahead in threads, estimator, chunked
  ``poses.h5`` writer),

and prints end-to-end / min(decode, network); the target is >= 0.8. The network and
end-to-end figures are measured for each backend of :mod:`freipose.nn.fast` (``--backends``,
default ``eager optimized bf16``) in the same run, alternating, ``--repeat`` times, and the
median kept (shared machines are noisy); the script prints optimized / eager end to end
(target >= 3), each backend's achieved GFLOP/s (``FlopCounterMode``: convolutions and matrix
products) and its ratio to the fp32 2048 x 2048 matmul of the same threads (target >= 0.4),
and the largest pose difference of each backend from eager on the same frames. The network is
the shipped base model for the small preset (``freipose/models/voxel_small.pt``), else an
untrained model of the chosen preset (its speed does not depend on the weights), unless
``--model`` gives a checkpoint; boxes come from fixed boxes covering each image, so the
numbers measure the pipeline, not a detector.

Usage::

    python benchmarks/predict.py                       # small preset, CPU
    python benchmarks/predict.py --preset paper --device cuda --cameras 7 --frames 400 --batch 16
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from _results import write_result


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="small", help="tiny, small or paper (default small)")
    ap.add_argument(
        "--model",
        type=Path,
        help="a checkpoint (default: the shipped base model of the small preset, else an "
        "untrained network of --preset)",
    )
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--frames", type=int, default=96)
    ap.add_argument("--cameras", type=int, default=4)
    ap.add_argument("--size", default="640x512", help="video size WxH")
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: leave as is)")
    ap.add_argument(
        "--repeat", type=int, default=3, help="measure each alternately N times, keep the median"
    )
    ap.add_argument("--backends", nargs="+", default=["eager", "optimized", "bf16"])
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    from freipose.workers import keep_freed_memory

    keep_freed_memory()  # as the commands do (cli/_threads.py)

    from freipose.detect.fallback import FixedBoxes
    from freipose.io.session import discover_sessions
    from freipose.nn.config import config_from_dict
    from freipose.nn.model import build_model
    from freipose.predict.network import NetworkEstimator, load_model
    from freipose.predict.reader import SyncReader
    from freipose.predict.run import predict_session
    from freipose.skeleton import load_skeleton
    from freipose.synth import SceneConfig, generate_session

    w, h = (int(v) for v in args.size.lower().split("x"))
    tmp = Path(tempfile.mkdtemp(prefix="fp_bench_predict_"))
    t0 = time.perf_counter()
    paths = generate_session(
        tmp / "bench",
        SceneConfig(n_cameras=args.cameras, frames=args.frames, size=(w, h), seed=0),
        progress=False,
    )
    print(f"synthetic session: {args.cameras} cameras {w}x{h}, {args.frames} frames "
          f"({time.perf_counter() - t0:.1f} s to render)")  # fmt: skip
    (session,) = discover_sessions([paths.folder])

    from freipose.nn.data import collate_prepared, prepare_sample, to_device
    from freipose.nn.fast import forward_flops, matmul_roofline, optimize
    from freipose.nn.inference import predict_batch

    base = Path(__file__).resolve().parents[1] / "freipose" / "models" / "voxel_small.pt"
    if args.model is None and args.preset == "small" and base.is_file():
        args.model = base

    def network(backend: str):
        if args.model is not None:
            net, cfg, skel, _ = load_model(args.model, args.device)
        else:
            cfg = config_from_dict({"model": {"preset": args.preset}})
            skel = load_skeleton("rat")
            torch.manual_seed(0)
            net = build_model(cfg.model, len(skel.keypoints)).to(args.device).eval()
        return optimize(net, backend), cfg, skel

    boxes = FixedBoxes({cam.name: [0, 0, cam.width, cam.height] for cam in session.rig})
    ests = {}
    for backend in args.backends:
        net, cfg, skel = network(backend)
        ests[backend] = NetworkEstimator(net, cfg, skel, boxes, refine=True)
    shapes = [(cam.height, cam.width) for cam in session.rig]
    videos = list(session.videos.values())
    T, B = session.num_frames, args.batch
    cuda = args.device.startswith("cuda")

    def decode_only() -> tuple[float, list]:
        t = time.perf_counter()
        kept = []
        with SyncReader(videos, 0, T, B, shapes) as reader:
            for fb in reader:
                if len(kept) < 4:
                    kept.append(fb)
        return T / (time.perf_counter() - t), kept

    def network_only(est, batches: list) -> float:
        if cuda:
            torch.cuda.synchronize()
        n = 0
        t = time.perf_counter()
        while n < T:
            fb = batches[(n // B) % len(batches)]
            est(fb.images, session.rig)
            n += len(fb)
        if cuda:
            torch.cuda.synchronize()
        return n / (time.perf_counter() - t)

    def end_to_end(est) -> float:
        out = Path(tempfile.mkdtemp(dir=tmp))
        t = time.perf_counter()
        res = predict_session(session, est, out, batch_size=B, progress=False, skeleton=skel)
        assert res.frames == T
        return T / (time.perf_counter() - t)

    _, batches = decode_only()  # warms the page cache
    first = batches[0]
    frames = [[first.images[c][b] for c in range(len(session.rig))] for b in range(len(first))]
    centers = np.array([est(first.images, session.rig).center for est in ests.values()][0])
    poses, flops = {}, {}
    for name, est in ests.items():
        t = time.perf_counter()
        est(first.images, session.rig)  # warm-up (and any first-use cost)
        print(f"{name}: first batch {time.perf_counter() - t:.1f} s")
        with torch.inference_mode():
            poses[name] = predict_batch(est.model, frames, [session.rig] * len(frames), centers)
        items = [
            prepare_sample({"rig": session.rig, "images": f, "index": i}, cfg.model, center=c)
            for i, (f, c) in enumerate(zip(frames, centers, strict=True))
            if np.isfinite(c).all()
        ]
        batch = to_device(collate_prepared(items), args.device)
        flops[name] = forward_flops(est.model, batch) / max(len(items), 1)
    dec_runs: list[float] = []
    net_runs: dict[str, list[float]] = {k: [] for k in ests}
    e2e_runs: dict[str, list[float]] = {k: [] for k in ests}
    roof_runs: list[float] = []
    for _ in range(max(1, args.repeat)):  # alternate, so that load changes hit all of them
        d, batches = decode_only()
        dec_runs.append(d)
        roof_runs.append(matmul_roofline(device=args.device))
        for name, est in ests.items():
            net_runs[name].append(network_only(est, batches))
            e2e_runs[name].append(end_to_end(est))
    med = statistics.median
    dec, roof = med(dec_runs), med(roof_runs)
    print(f"device {args.device}, torch threads {torch.get_num_threads()}, batch {B}, "
          f"model {'checkpoint' if args.model else args.preset}, "
          f"medians of {args.repeat} alternated runs")  # fmt: skip
    print(f"decode-only   {dec:8.1f} frames/s")
    print(f"fp32 {2048}x{2048} matmul roofline {roof:8.1f} GFLOP/s (same threads)")
    figures: dict[str, float] = {"decode_fps": dec, "matmul_gflops": roof}
    ref = next(iter(ests))
    for name in ests:
        netfps, e2e = med(net_runs[name]), med(e2e_runs[name])
        gflops = flops[name] / 1e9 * netfps
        diff = {
            k: float(np.nanmax(np.linalg.norm(poses[name][k] - poses[ref][k], axis=-1)))
            for k in ("P0", "P1")
        }
        print(f"[{name}] network-only {netfps:7.1f} frames/s, end-to-end {e2e:7.1f} frames/s, "
              f"end-to-end / slower of decode, network {e2e / min(dec, netfps):.2f}")  # fmt: skip
        print(f"[{name}] {flops[name] / 1e9:.3f} GFLOP per multi-view frame, {gflops:.1f} "
              f"GFLOP/s = {gflops / roof:.1%} of the matmul roofline (target >= 40 %); "
              f"max pose difference from {ref}: P0 {diff['P0']:.4f} mm, "
              f"P1 {diff['P1']:.4f} mm")  # fmt: skip
        figures.update({
            f"{name}/network_fps": netfps,
            f"{name}/end_to_end_fps": e2e,
            f"{name}/gflop_per_frame": flops[name] / 1e9,
            f"{name}/gflops": gflops,
            f"{name}/roofline_fraction": gflops / roof,
            f"{name}/max_diff_p1_mm": diff["P1"],
            f"{name}/max_diff_p0_mm": diff["P0"],
            f"{name}/end_to_end_over_slower": e2e / min(dec, netfps),
        })  # fmt: skip
    for name in ests:
        if name != ref:
            r = med(e2e_runs[name]) / med(e2e_runs[ref])
            print(f"{name} / {ref} end to end: {r:.2f}x (target >= 3x)")
            figures[f"{name}/speedup_end_to_end"] = r
    settings = {k: str(v) for k, v in vars(args).items()}
    write_result("predict", figures, extra={**settings, "torch_threads": torch.get_num_threads()})


if __name__ == "__main__":
    main()

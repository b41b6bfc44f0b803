"""Prediction throughput: end-to-end frames/s against decode-only and network-only, same run.

On a synthetic session (``freipose.synth.generate_session``), measures

* **decode**: all camera streams decoded and batched by the background-thread reader
  (:class:`freipose.predict.reader.SyncReader`), nothing else;
* **network**: the estimator (box source + voxel network) on batches already in memory;
* **end-to-end**: ``predict_session`` (decoding ahead in threads, estimator, chunked
  ``poses.h5`` writer),

and prints end-to-end / min(decode, network); the target is >= 0.8. Each is measured
``--repeat`` times, alternating, and the best kept (shared machines are noisy). The network is an
untrained model of the chosen preset (its speed does not depend on the weights) unless
``--model`` gives a checkpoint; boxes come from fixed boxes covering each image, so the
numbers measure the pipeline, not a detector.

Usage::

    python benchmarks/predict.py                       # small preset, CPU
    python benchmarks/predict.py --preset paper --device cuda --frames 400 --batch 16
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import torch
from _results import write_result


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="small", help="tiny, small or paper (default small)")
    ap.add_argument("--model", type=Path, help="a checkpoint instead of an untrained preset")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--frames", type=int, default=96)
    ap.add_argument("--cameras", type=int, default=4)
    ap.add_argument("--size", default="640x512", help="video size WxH")
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: leave as is)")
    ap.add_argument(
        "--repeat", type=int, default=2, help="measure each alternately N times, keep the best"
    )
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

    if args.model is not None:
        net, cfg, skel, _ = load_model(args.model, args.device)
    else:
        cfg = config_from_dict({"model": {"preset": args.preset}})
        skel = load_skeleton("rat")
        torch.manual_seed(0)
        net = build_model(cfg.model, len(skel.keypoints)).to(args.device).eval()
    boxes = FixedBoxes({cam.name: [0, 0, cam.width, cam.height] for cam in session.rig})
    est = NetworkEstimator(net, cfg, skel, boxes, refine=True)
    shapes = [(cam.height, cam.width) for cam in session.rig]
    videos = list(session.videos.values())
    T, B = session.num_frames, args.batch

    def decode_only() -> tuple[float, list]:
        t = time.perf_counter()
        kept = []
        with SyncReader(videos, 0, T, B, shapes) as reader:
            for fb in reader:
                if len(kept) < 4:
                    kept.append(fb)
        return T / (time.perf_counter() - t), kept

    def network_only(batches: list) -> float:
        est(batches[0].images, session.rig)  # warm-up
        if args.device.startswith("cuda"):
            torch.cuda.synchronize()
        n = 0
        t = time.perf_counter()
        while n < T:
            fb = batches[(n // B) % len(batches)]
            est(fb.images, session.rig)
            n += len(fb)
        if args.device.startswith("cuda"):
            torch.cuda.synchronize()
        return n / (time.perf_counter() - t)

    def end_to_end() -> float:
        out = Path(tempfile.mkdtemp(dir=tmp))
        t = time.perf_counter()
        res = predict_session(session, est, out, batch_size=B, progress=False, skeleton=skel)
        assert res.frames == T
        return T / (time.perf_counter() - t)

    decode_only()  # warm the page cache
    dec, netfps, e2e = 0.0, 0.0, 0.0
    for _ in range(max(1, args.repeat)):  # alternate, so that load changes hit all three
        d, batches = decode_only()
        dec = max(dec, d)
        netfps = max(netfps, network_only(batches))
        e2e = max(e2e, end_to_end())
    slower = min(dec, netfps)
    print(f"device {args.device}, torch threads {torch.get_num_threads()}, batch {B}, "
          f"model {'checkpoint' if args.model else args.preset}")  # fmt: skip
    print(f"decode-only   {dec:8.1f} frames/s")
    print(f"network-only  {netfps:8.1f} frames/s")
    print(f"end-to-end    {e2e:8.1f} frames/s")
    print(f"end-to-end / slower of the two = {e2e / slower:.2f} (target >= 0.80)")
    figures = {"decode_fps": dec, "network_fps": netfps, "end_to_end_fps": e2e,
               "end_to_end_over_slower": e2e / slower}  # fmt: skip
    settings = {k: str(v) for k, v in vars(args).items()}
    write_result("predict", figures, extra={**settings, "torch_threads": torch.get_num_threads()})


if __name__ == "__main__":
    main()

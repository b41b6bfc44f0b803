"""Detector benchmark: train on one synthetic session, evaluate on another.

The evaluation session has a different seed *and* a different camera layout (another
number of cameras, so other positions, focal lengths and distortions); the rat's coat
(``--appearance``) is the same, as when a lab trains on its own strain. A third session
with the other coat shows how far the detector generalises to an unseen appearance. Prints,
for the trained detector and for the background-subtraction baseline measured in the same run:
recall at IoU 0.5 over the views that show the animal, the median 3D centre error (mm)
against the triangulated ground-truth box centres, the rate of time instants with a 3D
centre, and CPU images per second.

Usage (CPU)::

    python benchmarks/detector.py --workdir /tmp/fp_bench_detector
    python benchmarks/detector.py --steps 300 --train-frames 60 --eval-frames 30   # quick look

Targets: recall >= 0.95 and median 3D centre error < 10 mm.
"""

from __future__ import annotations

import argparse
import logging
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from _results import write_result


def main() -> None:
    """Render the sessions, train the detector, evaluate it and the baseline, print a table."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--workdir", type=Path, default=None, help="keeps sessions and the run")
    ap.add_argument("--train-frames", type=int, default=200)
    ap.add_argument("--eval-frames", type=int, default=100)
    ap.add_argument("--train-cameras", type=int, default=7)
    ap.add_argument("--eval-cameras", type=int, default=6)
    ap.add_argument("--steps", type=int, default=1500)
    ap.add_argument("--batch-size", type=int, default=8)
    ap.add_argument("--input-size", type=int, default=192)
    ap.add_argument("--width", type=float, default=0.5)
    ap.add_argument("--train-crop", type=int, default=128)
    ap.add_argument("--device", default="cpu")
    ap.add_argument(
        "--appearance",
        default="hooded",
        choices=["hooded", "albino"],
        help="the rat's coat in the training and main evaluation sessions",
    )
    ap.add_argument("--resume", action="store_true", help="continue an interrupted run")
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    torch.set_num_threads(1)

    from freipose.detect import BackgroundSubtractor, ConsistencyConfig, Detector
    from freipose.detect.evaluate import evaluate_source, measure_fps
    from freipose.detect.train import train_detector
    from freipose.nn.dataset import MultiViewDataset
    from freipose.synth import SceneConfig, generate_session

    work = args.workdir or Path(tempfile.mkdtemp(prefix="fp_bench_detector_"))
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    other = "albino" if args.appearance == "hooded" else "hooded"
    train_cfg = SceneConfig(frames=args.train_frames, seed=11, n_cameras=args.train_cameras,
                            appearance=args.appearance)  # fmt: skip
    eval_cfg = SceneConfig(frames=args.eval_frames, seed=23, n_cameras=args.eval_cameras,
                           appearance=args.appearance)  # fmt: skip
    cross_cfg = SceneConfig(frames=args.eval_frames, seed=37, n_cameras=args.eval_cameras,
                            appearance=other)  # fmt: skip
    generate_session(work / f"train_{args.appearance}", train_cfg, progress=False)
    generate_session(work / f"eval_{args.appearance}", eval_cfg, progress=False)
    generate_session(work / f"eval_{other}", cross_cfg, progress=False)
    print(
        f"sessions rendered in {time.perf_counter() - t0:.0f} s: train seed 11 with "
        f"{args.train_cameras} cameras, eval seed 23 with {args.eval_cameras} cameras"
    )

    config = {
        "data": {
            "labels": str(work / f"train_{args.appearance}" / "labels.h5"),
            "eval_labels": str(work / f"eval_{args.appearance}" / "labels.h5"),
        },
        "detector": {
            "input_size": args.input_size,
            "width": args.width,
            "steps": args.steps,
            "batch_size": args.batch_size,
            "max_eval_instants": args.eval_frames,
            "train_crop": args.train_crop,
        },
    }
    ckpt = train_detector(config, work / "train.toml", work / "run", args.resume, args.device)

    # The same evaluation for the trained detector and the no-training baseline.
    ds = MultiViewDataset(work / f"eval_{args.appearance}" / "labels.h5")
    samples = [ds[i] for i in range(len(ds))]
    consistency = ConsistencyConfig(cube_size=400.0)
    det = Detector.load(ckpt, "cpu")
    m_det = evaluate_source(det, samples, consistency=consistency)
    names = list(samples[0]["camera_names"])
    frames = {n: [s["images"][i] for s in samples] for i, n in enumerate(names)}
    bg = BackgroundSubtractor.fit(frames, n_samples=40)
    m_bg = evaluate_source(bg, samples, consistency=consistency)
    fps_det = measure_fps(det, tuple(samples[0]["rig"][0].size), n_images=64)
    fps_bg = _fps_bg(bg, frames, names)

    print("\n=== detector benchmark (eval session: other seed, other camera layout) ===")
    print(f"{'':22s}{'detector':>12s}{'bgsub':>12s}{'ratio':>10s}")
    rows = [
        ("recall@IoU0.5", m_det.recall, m_bg.recall),
        ("recall (top box)", m_det.recall_top1, m_bg.recall_top1),
        ("median centre err mm", m_det.median_center_error, m_bg.median_center_error),
        ("centre found rate", m_det.center_rate, m_bg.center_rate),
        ("mean agreeing views", m_det.mean_agree, m_bg.mean_agree),
        ("CPU images/s", fps_det, fps_bg),
    ]
    for name, a, b in rows:
        print(f"{name:22s}{a:12.3f}{b:12.3f}{a / b if b else float('nan'):10.2f}")
    print(f"views showing the animal: {m_det.n_views}, time instants: {m_det.n_instants}")
    # Harder: a coat never seen in training (seed 37, the other appearance).
    cds = MultiViewDataset(work / f"eval_{other}" / "labels.h5")
    m_cross = evaluate_source(det, [cds[i] for i in range(len(cds))], consistency=consistency)
    print(f"unseen coat ({other}, seed 37): {m_cross.summary()}")
    ok = m_det.recall >= 0.95 and m_det.median_center_error < 10.0
    print(f"targets (recall >= 0.95, median centre error < 10 mm): {'met' if ok else 'NOT met'}")
    keys = ("recall", "recall_top1", "median_center_error", "center_rate", "mean_agree")
    figures = {
        "detector": {k: getattr(m_det, k) for k in keys} | {"cpu_images_per_s": fps_det},
        "bgsub": {k: getattr(m_bg, k) for k in keys} | {"cpu_images_per_s": fps_bg},
        f"detector unseen coat {other}": {k: getattr(m_cross, k) for k in keys},
    }
    settings = {k: v for k, v in vars(args).items() if k not in ("workdir", "resume")}
    write_result("detector", figures, extra={"seed": 11, **settings})


def _fps_bg(bg, frames: dict, names: list[str], n: int = 64) -> float:
    """Images per second of the background subtractor ``bg`` on ``n`` frames."""
    imgs = [frames[names[i % len(names)]][i % len(frames[names[0]])] for i in range(n)]
    cams = [names[i % len(names)] for i in range(n)]
    t = time.perf_counter()
    bg.propose(imgs, cams)
    return n / (time.perf_counter() - t)


if __name__ == "__main__":
    np.set_printoptions(precision=3, suppress=True)
    main()

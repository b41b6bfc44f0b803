"""Temporal smoothing against the truth on a demo's predicted poses (``freipose smooth``).

Reads the predicted ``DIR/poses/<session>.poses.h5`` of a finished ``freipose demo DIR``
and the session's true keypoints (``DIR/recordings/<session>/labels.h5``, mapped into the
calibrated world frame as the demo's ``evaluate`` step does), smooths the predictions
with :func:`freipose.predict.smooth.smooth_poses` and prints, raw against smoothed:

* the median joint position error (JPE, mm) and the median velocity error (mm/s against
  the true velocity, from frame differences);
* the lag: the shift (frames) at which the cross-correlation of the smoothed and the true
  velocity peaks, per keypoint and axis (0 = no lag);
* the coverage of the 1, 2 and 3 sigma bands (per axis; a Gaussian gives 68.3, 95.4 and
  99.7 %) per keypoint class, and in the gap.

The smoother's standard deviation is fitted on the recording alone, so it describes the
frame-to-frame noise of the predictions; an error that persists over many frames (the
network's bias) is invisible to it. ``--floor-from SESSION`` therefore also fits, on
another session with truth, a per-keypoint error floor ``b`` (mm,
:func:`freipose.predict.smooth.fit_error_floor`) added in quadrature
(``sqrt(std^2 + b^2)``) so that 95.4 % of that session's axes lie within 2 sigma, and
prints the coverage of this session with it (held out: the floor never sees it).

``--gap N`` removes the predictions of N frames in the middle of the session (a camera
dropout) before smoothing, and reports the error and the 2-sigma coverage in the gap.

Example::

    python benchmarks/smooth.py --demo /work/demo_new --gap 10
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from freipose.demo.context import truth_to_calibrated
from freipose.demo.markers import step_results
from freipose.io.labels import read_labels_h5
from freipose.io.poses import PoseData, read_poses_h5
from freipose.predict.smooth import smooth_poses
from freipose.predict.smooth_error import fit_error_floor

CLASSES = {"head": ("Ear", "Eye", "Nose"), "front paws": ("Paw Front",), "back paws": (
    "Paw Back",), "tail": ("Tail",)}  # fmt: skip


def _truth(demo: Path, session: str, data: PoseData) -> np.ndarray:
    """(T, K, 3) true keypoints of the predicted frames in the calibrated world frame."""
    labels = read_labels_h5(demo / "recordings" / session / "labels.h5")
    align = step_results(demo, "calibrate")["alignment"]
    gt = truth_to_calibrated(labels.points3d, align)
    rows = {int(f): i for i, f in enumerate(labels.frame_index)}
    order = [labels.keypoints.index(k) for k in data.keypoints]
    return gt[np.array([rows[int(f)] for f in data.frame_index])][:, order]


def _with_gap(data: PoseData, n: int) -> tuple[PoseData, slice]:
    """The poses with no prediction in ``n`` frames in the middle."""
    mid = data.num_frames // 2
    gap = slice(mid - n // 2, mid - n // 2 + n)
    poses, conf = data.poses.copy(), data.confidence.copy()
    poses[gap], conf[gap] = np.nan, 0.0
    kw = {f: getattr(data, f) for f in ("keypoints", "frame_index", "fps", "up", "skeleton")}
    return PoseData(poses=poses, confidence=conf, **kw), gap


def _lags(a: np.ndarray, b: np.ndarray, max_lag: int = 5) -> list[int]:
    """Per keypoint and axis: the shift of b against a that maximises their correlation."""
    va, vb = np.diff(a, axis=0), np.diff(b, axis=0)
    lags = np.arange(-max_lag, max_lag + 1)
    out = []
    for k in range(a.shape[1]):
        for ax in range(3):
            x, y = va[:, k, ax], vb[:, k, ax]
            ok = np.isfinite(x) & np.isfinite(y)
            x, y = np.where(ok, x, 0.0), np.where(ok, y, 0.0)
            sl = slice(max_lag, len(x) - max_lag)
            cc = [float(np.dot(x[sl], np.roll(y, lag)[sl])) for lag in lags]
            out.append(int(lags[int(np.argmax(cc))]))
    return out


def _coverage(raw: PoseData, err: np.ndarray, std: np.ndarray, title: str) -> None:
    """Print the 1/2/3-sigma coverage per keypoint class."""
    print(title)
    print(f"{'class':12s} {'n':>6s} {'1 sigma':>8s} {'2 sigma':>8s} {'3 sigma':>8s}  "
          "median std (mm)")  # fmt: skip
    rows = {c: [i for i, k in enumerate(raw.keypoints) if k.startswith(p)] for c, p in
            CLASSES.items()}  # fmt: skip
    rows["all"] = list(range(len(raw.keypoints)))
    for name, idx in rows.items():
        if not idx:
            continue
        e, s = err[:, idx], std[:, idx]
        cov = [100 * float((e <= m * s).mean()) for m in (1, 2, 3)]
        print(f"{name:12s} {e.size:6d} {cov[0]:7.1f}% {cov[1]:7.1f}% {cov[2]:7.1f}%  "
              f"{np.median(s):.2f}")  # fmt: skip


def _report(raw: PoseData, sm: PoseData, truth: np.ndarray, gap: slice | None) -> None:
    """Print the figures of the module docstring."""
    fps = raw.fps
    jpe_raw = np.linalg.norm(raw.poses - truth, axis=-1)
    jpe_sm = np.linalg.norm(sm.poses - truth, axis=-1)
    vt = np.diff(truth, axis=0) * fps
    ve_raw = np.linalg.norm(np.diff(raw.poses, axis=0) * fps - vt, axis=-1)
    ve_sm = np.linalg.norm(np.diff(sm.poses, axis=0) * fps - vt, axis=-1)
    print(f"frames {raw.num_frames}, keypoints {len(raw.keypoints)}, fps {fps:g}")
    print(f"median JPE        raw {np.nanmedian(jpe_raw):7.2f} mm    smoothed "
          f"{np.median(jpe_sm):7.2f} mm")  # fmt: skip
    print(f"median vel. error raw {np.nanmedian(ve_raw):7.1f} mm/s  smoothed "
          f"{np.median(ve_sm):7.1f} mm/s")  # fmt: skip
    lags = _lags(truth, sm.poses)
    vals, counts = np.unique(lags, return_counts=True)
    print("lag of the smoothed velocity (frames: count of keypoint axes):",
          ", ".join(f"{v}: {c}" for v, c in zip(vals, counts, strict=True)))  # fmt: skip
    std = sm.extra["smooth_std"].astype(np.float64)
    err = np.abs(sm.poses - truth)
    _coverage(raw, err, std, "coverage of the smoother's own std (fitted on the recording):")
    if gap is not None:
        e, s = err[gap], std[gap]
        print(f"gap of {gap.stop - gap.start} frames: median JPE {np.median(jpe_sm[gap]):.2f} "
              f"mm, 2-sigma coverage {100 * float((e <= 2 * s).mean()):.1f}% "
              f"(median std {np.median(s):.2f} mm)")  # fmt: skip
    print(f"outliers rejected: {int(sm.extra['rejected'].sum())} of {sm.extra['rejected'].size}")


def main() -> None:
    """Parse the arguments, smooth, print."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--demo", type=Path, required=True, help="a finished freipose demo folder")
    ap.add_argument("--session", default="rat1_day2", help="the held-out session")
    ap.add_argument("--gap", type=int, default=0, help="frames without prediction to add")
    ap.add_argument("--floor-from", default=None, help="session to fit the error floor on")
    args = ap.parse_args()
    raw = read_poses_h5(args.demo / "poses" / f"{args.session}.poses.h5")
    truth = _truth(args.demo, args.session, raw)
    gap = None
    if args.gap:
        raw_in, gap = _with_gap(raw, args.gap)
    else:
        raw_in = raw
    t0 = time.perf_counter()
    sm = smooth_poses(raw_in)
    print(f"smoothed in {time.perf_counter() - t0:.2f} s")
    _report(raw, sm, truth, gap)
    if args.floor_from:
        other = read_poses_h5(args.demo / "poses" / f"{args.floor_from}.poses.h5")
        o_sm = smooth_poses(other)
        floor = fit_error_floor(
            o_sm.poses, o_sm.extra["smooth_std"], _truth(args.demo, args.floor_from, other)
        )
        std = smooth_poses(raw_in, error_floor=floor).extra["smooth_std"].astype(np.float64)
        err = np.abs(sm.poses - truth)
        _coverage(raw, err, std, f"with the error floor fitted on {args.floor_from} (median "
                  f"{np.median(floor):.1f} mm):")  # fmt: skip
        if gap is not None:
            cov = 100 * float((err[gap] <= 2 * std[gap]).mean())
            print(f"gap: 2-sigma coverage with the floor {cov:.1f}%")
    for k, p in sm.provenance["smoother"]["params"].items():
        print(f"  {k:20s} q {p['q_mm2_s3']:10.3g} mm^2/s^3  sigma0 {p['sigma0_mm']:6.2f} mm  "
              f"beta {p['beta']:.2f}")  # fmt: skip


if __name__ == "__main__":
    main()

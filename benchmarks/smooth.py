"""Temporal smoothing against the truth on a demo's predicted poses (``freipose smooth``).

Reads the predicted ``DIR/poses/<session>.poses.h5`` of a finished ``freipose demo DIR``
and the session's true keypoints (``DIR/recordings/<session>/labels.h5``, mapped into the
calibrated world frame as the demo's ``evaluate`` step does), smooths the predictions
with :func:`freipose.predict.smooth.smooth_poses` and prints, raw against smoothed (and
against the smoother with one process noise per keypoint, ``fixed q``, for comparison):

* the median joint position error (JPE, mm) and the median velocity error (mm/s against
  the true velocity, from frame differences), and their ratio;
* the lag: the shift (frames) at which the cross-correlation of the smoothed and the true
  velocity, summed over keypoints and axes, peaks (0 = no lag), and the per-axis peaks;
* the coverage of the 1, 2 and 3 sigma bands (per axis; a Gaussian gives 68.3, 95.4 and
  99.7 %) per keypoint class: of the smoother's own std (the frame-to-frame noise), and
  with the network's error on the held-out labels ``DIR/labels/eval.h5`` added
  (:func:`freipose.predict.smooth_error.model_validation_error`, no truth of the session
  used; the labeled instants themselves are left out of the coverage);
* ``--gap N`` (default 10): the predictions of N frames in the middle are removed (a
  camera dropout) before smoothing; the error and coverage in the gap;
* the bound of any smoother: the velocity error (and its ratio to raw) of the truth plus
  the network's error with everything above 4, 6 and 8 Hz removed, i.e. of a smoother that
  removed the network's error above that frequency and kept every movement;
* the stimulated paw's 5 Hz amplitude during the stimulation (truth, raw, smoothed);
* ``--bones``: the median over bones of the bone-length standard deviation (truth, raw,
  smoothed, smoothed with ``--bones``) and the JPE with ``--bones``;
* with ``--analysis``: the demo's analysis on raw and on smoothed poses of all sessions
  side by side (balanced accuracy, rank of the stimulated part's best variable).

``--bursts SEEDS`` measures the same figures (no analysis, no held-out error) on synthetic
recordings instead: 12 keypoints of slow motion (30 s at 25 fps), one of them oscillating
at 5 Hz (10 mm) in 2 s of every 4 s, with the error model of ``freipose analyze simulate``
(a first-order autoregressive error per keypoint and axis, 3.25 mm, correlation time
0.2 s) plus a white error of 0.5 mm.

Example::

    python benchmarks/smooth.py --demo /work/demo_final --analysis
    python benchmarks/smooth.py --bursts 0 1 2
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time
from pathlib import Path

import numpy as np
from _results import write_result

from freipose.demo.context import truth_to_calibrated
from freipose.demo.markers import step_results
from freipose.io.labels import read_labels_h5
from freipose.io.poses import PoseData, read_poses_h5
from freipose.predict.smooth import frame_intervals, smooth_arrays, smooth_poses
from freipose.predict.smooth_error import model_validation_error

CLASSES = {"head": ("Ear", "Eye", "Nose"), "front paws": ("Paw Front",), "back paws": (
    "Paw Back",), "tail": ("Tail",)}  # fmt: skip
STIM_HZ = 5.0
BONES = "smoothed, --bones"  # the estimate of freipose smooth --bones


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
    return PoseData(poses=poses, confidence=conf, provenance=data.provenance, **kw), gap


def _lag(truth: np.ndarray, est: np.ndarray, max_lag: int = 5) -> tuple[int, list[int]]:
    """Shift of ``est`` against ``truth`` maximising the velocity correlation: pooled, per axis."""
    va, vb = np.diff(truth, axis=0), np.diff(est, axis=0)
    va, vb = va - va.mean(0), vb - vb.mean(0)
    sl = slice(max_lag, len(va) - max_lag)
    lags = np.arange(-max_lag, max_lag + 1)
    cc = np.array([(va[sl] * np.roll(vb, lag, axis=0)[sl]).sum(axis=0) for lag in lags])
    pooled = int(lags[int(np.argmax(cc.sum(axis=(1, 2))))])
    return pooled, [int(v) for v in lags[np.argmax(cc.reshape(len(lags), -1), axis=0)]]


def _classes(keypoints: tuple[str, ...]) -> dict[str, list[int]]:
    rows = {c: [i for i, k in enumerate(keypoints) if k.startswith(p)] for c, p in
            CLASSES.items()}  # fmt: skip
    rows["all"] = list(range(len(keypoints)))
    return {c: i for c, i in rows.items() if i}


def _coverage(keypoints, err, std, frames, title: str) -> float:
    """Print the 1/2/3-sigma coverage per keypoint class over ``frames``; the 2-sigma of all."""
    print(title)
    print(f"  {'class':12s} {'n':>6s} {'1 sigma':>8s} {'2 sigma':>8s} {'3 sigma':>8s}  "
          "median std (mm)")  # fmt: skip
    for name, idx in _classes(keypoints).items():
        e, s = err[frames][:, idx], std[frames][:, idx]
        cov = [100 * float((e <= m * s).mean()) for m in (1, 2, 3)]
        print(f"  {name:12s} {e.size:6d} {cov[0]:7.1f}% {cov[1]:7.1f}% {cov[2]:7.1f}%  "
              f"{np.median(s):.2f}")  # fmt: skip
    return 100 * float((err[frames] <= 2 * std[frames]).mean())


def _amplitude(x: np.ndarray, fps: float, windows: np.ndarray) -> float:
    """Mean amplitude (mm) of the STIM_HZ component of (T, 3) ``x`` in 1 s stimulation windows."""
    t = np.arange(len(x)) / fps
    c = np.exp(-2j * np.pi * STIM_HZ * t)
    n, amps = int(round(fps)), []
    for a, b in windows:
        for s in range(int(a * fps), int(b * fps) - n + 1, n):
            seg = x[s : s + n] - x[s : s + n].mean(axis=0)
            amps.append(np.linalg.norm(np.abs((seg * c[s : s + n, None]).sum(axis=0)) * 2 / n))
    return float(np.mean(amps)) if amps else float("nan")


def error_figures(est: np.ndarray, truth: np.ndarray, fps: float) -> dict[str, float]:
    """Median and mean JPE (mm) and median velocity error (mm/s) of (T, K, 3) ``est``.

    The velocity from frame differences, against the truth's; frames without a
    prediction (NaN) are left out.
    """
    e = np.linalg.norm(est - truth, axis=-1)
    vt = np.diff(truth, axis=0) * fps
    v = np.linalg.norm(np.diff(est, axis=0) * fps - vt, axis=-1)
    return {"median_jpe_mm": float(np.nanmedian(e)), "mean_jpe_mm": float(np.nanmean(e)),
            "velocity_error_mm_s": float(np.nanmedian(v))}  # fmt: skip


def _errors(raw: PoseData, truth: np.ndarray, est: dict[str, np.ndarray]) -> dict[str, dict]:
    """Print JPE, velocity error and lag of the raw and each smoothed estimate."""
    out = {"raw": error_figures(raw.poses, truth, raw.fps)}
    jr, mr, vr = out["raw"].values()
    print(f"{'':22s} {'median JPE':>11s} {'mean JPE':>9s} {'vel. error':>11s} {'vel/raw':>8s} "
          f"{'lag':>4s}")  # fmt: skip
    print(f"{'raw':22s} {jr:8.2f} mm {mr:6.2f} mm {vr:6.1f} mm/s {1:8.2f} "
          f"{_lag(truth, raw.poses)[0]:4d}")  # fmt: skip
    for name, m in est.items():
        f = error_figures(m, truth, raw.fps)
        j, mj, v = f.values()
        pooled, per = _lag(truth, m)
        vals, counts = np.unique(per, return_counts=True)
        spread = ", ".join(f"{a}: {b}" for a, b in zip(vals, counts, strict=True))
        print(f"{name:22s} {j:8.2f} mm {mj:6.2f} mm {v:6.1f} mm/s {v / vr:8.2f} {pooled:4d}   "
              f"(per axis {spread})")  # fmt: skip
        out[name] = f | {"lag_frames": pooled}
    return out


def _analysis(demo: Path, held_out) -> dict[str, dict]:
    """The demo's analysis on raw and smoothed poses of every session, side by side.

    Smoothed as ``freipose smooth`` does by default, with one process noise per keypoint
    (``fixed q``) and with ``--bones`` where the skeleton has bones.
    """
    from freipose.demo.context import DemoContext
    from freipose.demo.markers import read_marker
    from freipose.demo.presets import PRESETS
    from freipose.demo.steps.analyze import analyze_poses, study_toml
    from freipose.io.poses import write_poses_h5

    preset = PRESETS[(read_marker(demo, "synth") or {})["preset"]["name"]]
    ctx = DemoContext(out=demo, preset=preset, say=lambda m: None)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        base = Path(tmp)
        variants = {
            "smoothed": lambda d: _smoothed(d, True, held_out),
            "smoothed, fixed q": lambda d: _smoothed(d, False, None),
        }
        if _has_bones(read_poses_h5(demo / "poses" / f"{preset.analysed[0].name}.poses.h5")):
            variants[BONES] = lambda d: smooth_poses(d, error_floor=held_out, bones=True)
        for label, smooth in variants.items():
            sub = base / label.replace(", ", "_").replace(" ", "_").replace("--", "")
            (sub / "poses").mkdir(parents=True)
            for s in preset.analysed:
                d = read_poses_h5(demo / "poses" / f"{s.name}.poses.h5")
                write_poses_h5(smooth(d), sub / "poses" / f"{s.name}.poses.h5")
            rows.append((label, analyze_poses(ctx, sub / "study.toml",
                         study_toml(ctx, sub, sub / "poses"), sub / "results")))  # fmt: skip
        raw = analyze_poses(ctx, base / "study.toml", study_toml(ctx, base), base / "results")
    print("analysis (balanced accuracy; rank of the stimulated part's best single variable):")
    for label, r in [("raw", raw), *rows]:
        print(f"  {label:22s} {r['balanced_accuracy']:.3f}  rank {r['stimulated_best_rank']:4d}  "
              f"F1 {r['stimulated_best_f1']:.3f} ({r['stimulated_best_variable']})")  # fmt: skip
    keys = ("balanced_accuracy", "stimulated_best_rank", "stimulated_best_f1")
    return {label: {k: r[k] for k in keys} for label, r in [("raw", raw), *rows]}


def _lowpass(x: np.ndarray, fps: float, hz: float) -> np.ndarray:
    """(T, ...) ``x`` without its components above ``hz`` (FFT along time, mean kept)."""
    mean = x.mean(axis=0)
    spec = np.fft.rfft(x - mean, axis=0)
    spec[np.fft.rfftfreq(len(x), 1 / fps) > hz] = 0
    return np.fft.irfft(spec, n=len(x), axis=0) + mean


def _bound(raw: PoseData, truth: np.ndarray, vr: float) -> dict[str, float]:
    """Print the velocity error of the truth plus the network's error low-passed at 4, 6, 8 Hz."""
    vt = np.diff(truth, axis=0) * raw.fps
    err = np.nan_to_num(raw.poses.astype(np.float64) - truth)
    out = {}
    for hz in (4.0, 6.0, 8.0):
        est = truth + _lowpass(err, raw.fps, hz)
        v = float(np.median(np.linalg.norm(np.diff(est, axis=0) * raw.fps - vt, axis=-1)))
        out[f"{hz:g} Hz"] = v
    print("bound: the truth plus the network's error without its part above 4 / 6 / 8 Hz: "
          "velocity error " + " / ".join(f"{v:.1f}" for v in out.values()) + " mm/s ("
          + " / ".join(f"{v / vr:.2f}" for v in out.values()) + " x raw)")  # fmt: skip
    return out


def _targets(figures: dict, cover: float, name: str = "smoothed") -> dict[str, bool]:
    """Print and return the smoother's targets for the estimate ``name``: met or not.

    The issue's figures, raw against ``name`` (``smoothed`` or ``smoothed, --bones``); the
    coverage and the analysis are the default smoother's.
    """
    raw, sm = figures["errors"]["raw"], figures["errors"][name]
    amp = figures[f"paw front right {STIM_HZ:g} Hz amplitude mm"]
    checks = {
        "median JPE <= raw": sm["median_jpe_mm"] <= raw["median_jpe_mm"],
        "mean JPE <= raw": sm["mean_jpe_mm"] <= raw["mean_jpe_mm"],
        "velocity error <= 0.6 x raw": sm["velocity_error_mm_s"]
        <= 0.6 * raw["velocity_error_mm_s"],
        f"{STIM_HZ:g} Hz amplitude at least as close to the truth as raw": abs(
            amp[name] - amp["truth"]
        )
        <= abs(amp["raw"] - amp["truth"]),
    }
    if name == "smoothed":
        checks["2-sigma coverage with --validation in 90-98 %"] = 90.0 <= cover <= 98.0
        if "analysis" in figures:
            a = figures["analysis"]
            checks["balanced accuracy >= raw - 0.02"] = (
                a["smoothed"]["balanced_accuracy"] >= a["raw"]["balanced_accuracy"] - 0.02
            )
    print(f"targets ({name}):")
    for label, ok in checks.items():
        print(f"  {'met ' if ok else 'MISSED'} {label}")
    return checks


def _smoothed(data: PoseData, adaptive: bool, held_out) -> PoseData:
    """``smooth_poses`` or, without adaptation, the same with one process noise per keypoint."""
    if adaptive:
        return smooth_poses(data, error_floor=held_out)
    res = smooth_arrays(data.poses, data.confidence, frame_intervals(data.frame_index, data.fps),
                        adaptive=False)  # fmt: skip
    return dataclasses.replace(data, poses=res.mean.astype(np.float32))


def _burst_recording(seed: int) -> tuple[PoseData, np.ndarray, np.ndarray]:
    """Synthetic predictions, truth and stimulation windows (see the module's ``--bursts``)."""
    from freipose.synth.study import ar1_error

    rng = np.random.default_rng(seed)
    fps, n, k = 25.0, 750, 12
    t = np.arange(n) / fps
    f, ph = rng.uniform(0.1, 1.0, (k, 3, 3)), rng.uniform(0, 2 * np.pi, (k, 3, 3))
    truth = (rng.uniform(5, 20, (k, 3, 3)) * np.sin(2 * np.pi * f * t[:, None, None, None] + ph)
             ).sum(-1)  # fmt: skip
    windows = np.array([(a, a + 2.0) for a in np.arange(1.0, 29.0, 4.0)])
    on = ((t[:, None] >= windows[:, 0]) & (t[:, None] < windows[:, 1])).any(axis=1)
    truth[:, 0, 2] += np.where(on, 10.0 * np.sin(2 * np.pi * STIM_HZ * t), 0.0)
    z = truth + ar1_error(truth.shape, 3.25, 0.2 * fps, rng) + rng.normal(0, 0.5, truth.shape)
    names = ("Paw Front Right", *(f"kp{i}" for i in range(1, k)))
    data = PoseData(poses=z.astype(np.float32), confidence=np.ones((n, k), np.float32),
                    keypoints=names, frame_index=np.arange(n), fps=fps)  # fmt: skip
    return data, truth, windows


def _bursts(seeds: list[int]) -> None:
    """Raw vs smoothed on synthetic bursts with the network-like error model; recorded."""
    rows = {}
    for seed in seeds:
        raw, truth, windows = _burst_recording(seed)
        sm = smooth_poses(raw)
        print(f"seed {seed}:")
        errors = _errors(raw, truth, {"smoothed": sm.poses})
        vr = errors["raw"]["velocity_error_mm_s"]
        amps = [_amplitude(x[:, 0], raw.fps, windows) for x in (truth, raw.poses, sm.poses)]
        print(f"5 Hz amplitude: truth {amps[0]:.2f} mm, raw {amps[1]:.2f}, smoothed {amps[2]:.2f}")
        rows[str(seed)] = {
            "errors": errors,
            "velocity error bound mm/s": _bound(raw, truth, vr),
            "5 Hz amplitude mm": dict(zip(("truth", "raw", "smoothed"), amps)),
        }
    write_result("smooth", {"bursts": rows}, extra={"bursts": seeds})


def main() -> None:
    """Parse the arguments, smooth, print."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--demo", type=Path, help="a finished freipose demo folder")
    ap.add_argument("--session", default="rat1_day2", help="the held-out session")
    ap.add_argument("--gap", type=int, default=10, help="frames without prediction to add")
    ap.add_argument("--analysis", action="store_true", help="also run the analysis side by side")
    ap.add_argument("--bursts", type=int, nargs="+", help="synthetic bursts of these seeds")
    args = ap.parse_args()
    if args.bursts:
        _bursts(args.bursts)
        return
    if args.demo is None:
        ap.error("give --demo DIR (a finished freipose demo) or --bursts SEEDS")
    demo = args.demo
    raw = read_poses_h5(demo / "poses" / f"{args.session}.poses.h5")
    truth = _truth(demo, args.session, raw)
    t0 = time.perf_counter()
    labels = demo / "labels" / "eval.h5"
    held_out = model_validation_error(demo / "train" / "pose" / "model.pt", labels)
    print(f"held-out error of the network ({time.perf_counter() - t0:.1f} s): {held_out.source}")
    t0 = time.perf_counter()
    sm = smooth_poses(raw, error_floor=held_out)
    print(f"smoothed in {time.perf_counter() - t0:.2f} s; process noise raised on "
          f"{sm.provenance['smoother']['adaptive_process_noise']['frames_raised']} of "
          f"{raw.poses.shape[0] * raw.poses.shape[1]} frames x keypoints")  # fmt: skip
    fixed = _smoothed(raw, False, None)
    bones = _with_bones(raw, held_out)
    print(f"session {args.session}: {raw.num_frames} frames, {len(raw.keypoints)} keypoints, "
          f"{raw.fps:g} fps")  # fmt: skip
    est = {"smoothed": sm.poses, "smoothed, fixed q": fixed.poses}
    if bones is not None:
        est[BONES] = bones.poses
    figures: dict[str, object] = {"errors": _errors(raw, truth, est)}
    figures["velocity error bound mm/s"] = _bound(
        raw, truth, figures["errors"]["raw"]["velocity_error_mm_s"]
    )
    own = smooth_poses(raw)
    err = np.abs(sm.poses - truth)
    lab_frames = set(int(f) for f in read_labels_h5(labels).frame_index)
    frames = np.array([int(f) not in lab_frames for f in raw.frame_index])
    _coverage(raw.keypoints, err, own.extra["smooth_std"].astype(np.float64), frames,
              "coverage of the smoother's own std (frame-to-frame noise only):")  # fmt: skip
    cover = _coverage(raw.keypoints, err, sm.extra["smooth_std"].astype(np.float64), frames,
                      f"coverage with the held-out error ({frames.sum()} frames not among the "
                      "labeled instants):")  # fmt: skip
    prov = sm.provenance["smoother"]
    n_pred = int(np.isfinite(raw.poses[..., 0]).sum())
    weight = float(sm.extra["smooth_weight"].mean())
    print(f"left out as gross outliers: {prov['rejected']} of {n_pred} predictions; mean "
          f"Student-t weight {weight:.2f}")  # fmt: skip
    if args.gap:
        gapped, gap = _with_gap(raw, args.gap)
        g = smooth_poses(gapped, error_floor=held_out)
        e, s = np.abs(g.poses[gap] - truth[gap]), g.extra["smooth_std"][gap]
        nb = np.r_[gap.start - 20 : gap.start, gap.stop : gap.stop + 20]
        en, sn = np.abs(g.poses[nb] - truth[nb]), g.extra["smooth_std"][nb]
        print(f"gap of {args.gap} frames (no prediction): median JPE "
              f"{np.median(np.linalg.norm(g.poses[gap] - truth[gap], axis=-1)):.2f} mm, "
              f"2-sigma coverage {100 * float((e <= 2 * s).mean()):.1f}% (median std "
              f"{np.median(s):.2f} mm); 20 frames either side: 2-sigma coverage "
              f"{100 * float((en <= 2 * sn).mean()):.1f}% (median std "
              f"{np.median(sn):.2f} mm)")  # fmt: skip
    events = np.loadtxt(demo / "recordings" / args.session / "events.csv", delimiter=",",
                        skiprows=1, ndmin=2)  # fmt: skip
    k = raw.keypoints.index("Paw Front Right")
    series = {"truth": truth, "raw": raw.poses, "smoothed": sm.poses, "fixed q": fixed.poses}
    if bones is not None:
        series[BONES] = bones.poses
    amps = {n: _amplitude(x[:, k], raw.fps, events) for n, x in series.items()}
    print(f"Paw Front Right {STIM_HZ:g} Hz amplitude in the stimulation: "
          + ", ".join(f"{n} {a:.2f}" for n, a in amps.items()) + " mm")  # fmt: skip
    figures[f"paw front right {STIM_HZ:g} Hz amplitude mm"] = amps
    if bones is not None:
        figures["bones"] = _bones_figures(raw, truth, sm, bones)
    if args.analysis:
        figures["analysis"] = _analysis(demo, held_out)
    figures["targets"] = _targets(figures, cover)
    if bones is not None:
        figures["targets with --bones"] = _targets(figures, cover, BONES)
    extra = {"demo": str(demo), "session": args.session, "gap": args.gap}
    write_result("smooth", figures, extra=extra)


def _has_bones(data: PoseData) -> bool:
    """Whether the poses' skeleton has limbs between single keypoints (``--bones`` applies)."""
    from freipose.predict.smooth_bones import bone_pairs

    return data.skeleton is not None and bool(len(bone_pairs(data.skeleton, data.keypoints)))


def _with_bones(raw: PoseData, held_out) -> PoseData | None:
    """``freipose smooth --bones`` (with ``--validation``); None without bones in the skeleton."""
    if not _has_bones(raw):
        print("--bones: the poses have no skeleton with single-keypoint limbs")
        return None
    return smooth_poses(raw, error_floor=held_out, bones=True)


def _bones_figures(
    raw: PoseData, truth: np.ndarray, sm: PoseData, bones: PoseData
) -> dict[str, float]:
    """Bone-length spread and JPE without and with ``--bones``."""
    from freipose.predict.smooth_bones import bone_pairs

    pairs = bone_pairs(raw.skeleton, raw.keypoints)

    def spread(x: np.ndarray) -> float:
        d = np.linalg.norm(x[:, pairs[:, 0]] - x[:, pairs[:, 1]], axis=-1)
        return float(np.median(d.std(axis=0)))

    jpe = [float(np.median(np.linalg.norm(x - truth, axis=-1))) for x in (sm.poses, bones.poses)]
    print(f"--bones ({len(pairs)} bones): median bone-length std truth {spread(truth):.2f} mm, "
          f"raw {spread(raw.poses):.2f}, smoothed {spread(sm.poses):.2f}, with --bones "
          f"{spread(bones.poses):.2f}; median JPE smoothed {jpe[0]:.2f} mm, with --bones "
          f"{jpe[1]:.2f} mm")  # fmt: skip
    return {"bone_length_std_truth_mm": spread(truth), "bone_length_std_raw_mm": spread(raw.poses),
            "bone_length_std_smoothed_mm": spread(sm.poses),
            "bone_length_std_bones_mm": spread(bones.poses), "median_jpe_smoothed_mm": jpe[0],
            "median_jpe_bones_mm": jpe[1]}  # fmt: skip


if __name__ == "__main__":
    main()

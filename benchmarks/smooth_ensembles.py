"""Several predictions of each frame against the network's persistent error.

``freipose smooth`` removes the part of the network's error that changes from frame to
frame; most of the error persists over several frames and stays (``benchmarks/smooth.py``
prints the bound: the truth plus the network's error without its part above 4 Hz).
Lightning Pose's ensemble Kalman smoother takes several predictions of each frame instead,
from test-time augmentation or networks trained with different seeds. This benchmark
measures what such predictions would give FreiPose on the held-out sessions of finished
demos (``--demo DIR...``, e.g. the seeds of ``benchmarks/demo.py``; the demos differ only
in the networks' training seed, so their sessions and truth are the same):

* **test-time augmentation** (per demo, the first ``--frames`` frames): the demo's voxel
  network on the same frames and cube centres with the voxel grid turned about the world's
  up by 0, 90, 180 and 270 degrees (the training turns it at random) and, for 4 more
  members, by 45, 135, 225 and 315 degrees with the cube shifted by up to one voxel on
  every axis; the members' mean;
* **an ensemble of fine-tunings** (with two or more demos): the mean of the demos'
  predictions;

each raw and after :func:`freipose.predict.smooth.smooth_poses`, against the truth: median
and mean JPE and the median velocity error with its ratio to the single network's raw
predictions, and how alike the members' errors are (the correlation of their errors and
of their frame-to-frame changes, pooled over frames, keypoints and axes). Members whose
errors are nearly the same cannot average them away.

Example (about 3 minutes per demo and session at 300 frames, 2 cores)::

    python benchmarks/smooth_ensembles.py --demo runs/demo_seed0 runs/demo_seed1 runs/demo_seed2
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np
from _results import write_result
from smooth import _truth, error_figures

from freipose.io.poses import PoseData, read_poses_h5
from freipose.predict.smooth import smooth_poses

SESSIONS = ("rat1_day2", "rat1_day3")
TURNS = (0.0, 90.0, 180.0, 270.0, 45.0, 135.0, 225.0, 315.0)


def augmentations(voxel_mm: float, seed: int = 0) -> list[tuple[float, np.ndarray]]:
    """The members' (turn in degrees, (3,) cube shift in mm): see the module docstring."""
    rng = np.random.default_rng(seed)
    return [(a, np.zeros(3) if i < 4 else rng.uniform(-1, 1, 3) * voxel_mm)
            for i, a in enumerate(TURNS)]  # fmt: skip


def tta_predictions(demo: Path, session: str, frames: int) -> tuple[np.ndarray, np.ndarray]:
    """(N, F, K, 3) P1 and (N, F, K) confidences of the augmented members on the first frames."""
    import torch

    from freipose.geometry.transforms import rodrigues
    from freipose.io.calibration_world import stored_up_or_z
    from freipose.io.session import discover_sessions
    from freipose.nn.data import collate_prepared, prepare_sample
    from freipose.nn.inference import predict_prepared
    from freipose.predict.network import load_model
    from freipose.predict.reader import SyncReader

    (s,) = discover_sessions([demo / "recordings" / session],
                             demo / "calibration" / "calibration.toml")  # fmt: skip
    centres = np.asarray(read_poses_h5(demo / "poses" / f"{session}.poses.h5").extra["center"],
                         np.float64)  # fmt: skip
    net, config, skel, _ = load_model(demo / "train" / "pose" / "model.pt", "cpu", None, "auto")
    cfg, up = config.model, stored_up_or_z(s.rig)
    augs = augmentations(float(cfg.voxel_size))
    n, k = min(frames, s.num_frames), len(skel.keypoints)
    poses, conf = np.full((len(augs), n, k, 3), np.nan), np.zeros((len(augs), n, k))
    shapes = [(c.height, c.width) for c in s.rig]
    net.eval()
    with torch.inference_mode(), SyncReader(list(s.videos.values()), 0, n, 8, shapes) as reader:
        for batch in reader:
            rows = [int(f) for f in batch.frame_index if np.isfinite(centres[f]).all()]
            views = {f: [im[i] for im in batch.images] for i, f in enumerate(batch.frame_index)}
            crops: dict[bytes, list] = {}  # the crops of a cube shift, prepared once
            for a, (turn, shift) in enumerate(augs):
                if shift.tobytes() not in crops:
                    crops[shift.tobytes()] = [
                        prepare_sample({"rig": s.rig, "images": views[f], "index": f}, cfg,
                                       center=centres[f] + shift)
                        for f in rows
                    ]  # fmt: skip
                turned = rodrigues(np.radians(turn) * up)
                items = [{**item, "grid_rotation": turned} for item in crops[shift.tobytes()]]
                if items:
                    out = predict_prepared(net, collate_prepared(items))
                    poses[a, rows], conf[a, rows] = out["P1"], out["confidence"]
    return poses, conf


def member_correlation(members: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    """Mean correlation between (N, T, K, 3) members' errors and their frame-to-frame changes."""
    err = members - truth[None]
    out = {}
    for name, x in (("error", err), ("error_change", np.diff(err, axis=1))):
        flat = x.reshape(len(x), -1)
        flat = flat[:, np.isfinite(flat).all(axis=0)]
        c = np.corrcoef(flat)
        n = len(c)
        out[f"{name}_correlation"] = float((c.sum() - n) / (n * (n - 1)))
    return out


def with_smoothed(raw: PoseData, poses: np.ndarray, conf: np.ndarray) -> tuple[np.ndarray, ...]:
    """``(poses, smoothed)``: (T, K, 3) poses and their ``smooth_poses`` at ``raw``'s frames."""
    n = len(poses)
    data = PoseData(poses=poses.astype(np.float32), confidence=conf.astype(np.float32),
                    keypoints=raw.keypoints, frame_index=raw.frame_index[:n], fps=raw.fps,
                    up=raw.up, skeleton=raw.skeleton)  # fmt: skip
    return poses, smooth_poses(data).poses.astype(np.float64)


def compare(raw: PoseData, truth: np.ndarray, estimates: dict[str, tuple]) -> dict[str, Any]:
    """Figures of the single network and of each :func:`with_smoothed` estimate, both versions.

    Args:
        raw: the single network's predictions.
        truth: (T, K, 3) the true poses of its frames.
        estimates: name -> ``(poses, smoothed)``, (F, K, 3) each over the first F frames.
    """
    n = len(next(iter(estimates.values()))[0]) if estimates else raw.num_frames
    single = raw.poses[:n].astype(np.float64)
    rows = {"single": with_smoothed(raw, single, raw.confidence[:n]), **estimates}
    base = error_figures(single, truth[:n], raw.fps)["velocity_error_mm_s"]
    out: dict[str, Any] = {}
    for name, (poses, smoothed) in rows.items():
        for label, x in ((name, poses), (f"{name}, smoothed", smoothed)):
            f = error_figures(x, truth[:n], raw.fps)
            out[label] = f | {"velocity_ratio": f["velocity_error_mm_s"] / base}
    return out


def _print(title: str, figures: dict[str, Any]) -> None:
    print(title)
    print(f"  {'':30s} {'median JPE':>11s} {'mean JPE':>9s} {'vel. error':>11s} {'x single':>9s}")
    for name, f in figures.items():
        if isinstance(f, dict) and "median_jpe_mm" in f:
            print(f"  {name:30s} {f['median_jpe_mm']:8.2f} mm {f['mean_jpe_mm']:6.2f} mm "
                  f"{f['velocity_error_mm_s']:6.1f} mm/s {f['velocity_ratio']:9.2f}")  # fmt: skip
    for key in ("error_correlation", "error_change_correlation"):
        if key in figures:
            print(f"  members' {key.replace('_', ' ')}: {figures[key]:.3f}")


# the summary's rows: (label, kind of run, estimate, figure); "jpe_change" is the median
# JPE minus the single network's raw one
SUMMARY = (
    ("single network smoothed, velocity x single", None, "single, smoothed", "velocity_ratio"),
    ("TTA mean smoothed, velocity x single", "tta", "8 members, smoothed", "velocity_ratio"),
    ("TTA mean smoothed, median JPE change mm", "tta", "8 members, smoothed", "jpe_change"),
    ("TTA members' error correlation", "tta", None, "error_correlation"),
    ("TTA members' error change correlation", "tta", None, "error_change_correlation"),
    ("demos' mean smoothed, velocity x single", "ensemble", "ensemble of demos, smoothed",
     "velocity_ratio"),
    ("demos' mean smoothed, median JPE change mm", "ensemble", "ensemble of demos, smoothed",
     "jpe_change"),
    ("demos' error correlation", "ensemble", None, "error_correlation"),
    ("demos' error change correlation", "ensemble", None, "error_change_correlation"),
)  # fmt: skip


def summarize(runs: list[dict[str, Any]]) -> dict[str, dict[str, float]]:
    """The range (min, max) of each :data:`SUMMARY` figure over the runs that have it."""
    out = {}
    for label, kind, name, key in SUMMARY:
        vals = []
        for r in runs:
            f = r["figures"]
            if (kind is not None and r["kind"] != kind) or (name is not None and name not in f):
                continue
            if key == "jpe_change":
                vals.append(f[name]["median_jpe_mm"] - f["single"]["median_jpe_mm"])
            else:
                vals.append(f[name][key] if name is not None else f[key])
        if vals:
            out[label] = {"min": float(min(vals)), "max": float(max(vals))}
    return out


def main() -> None:
    """Parse the arguments, predict the members, print and record."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--demo", type=Path, nargs="+", required=True, help="finished demo folders")
    ap.add_argument("--frames", type=int, default=300, help="frames of test-time augmentation")
    ap.add_argument("--no-tta", action="store_true", help="only the ensemble of the demos")
    args = ap.parse_args()
    runs: list[dict[str, Any]] = []
    for session in SESSIONS:
        raws = [read_poses_h5(d / "poses" / f"{session}.poses.h5") for d in args.demo]
        truth = _truth(args.demo[0], session, raws[0])
        if len(raws) > 1:
            members = np.stack([r.poses.astype(np.float64) for r in raws])
            conf = np.mean([r.confidence for r in raws], axis=0)
            mean = {"ensemble of demos": with_smoothed(raws[0], members.mean(0), conf)}
            alike = member_correlation(members, truth)
            for i, (d, raw) in enumerate(zip(args.demo, raws, strict=True)):
                f = compare(raw, truth, mean) | alike
                runs.append({"session": session, "demo": d.name, "kind": "ensemble", "figures": f})
                if i == 0:
                    _print(f"{session}: the {len(raws)} demos' mean against {d.name}", f)
        if args.no_tta:
            continue
        for d, raw in zip(args.demo, raws, strict=True):
            poses, conf = tta_predictions(d, session, args.frames)
            n = poses.shape[1]
            f = compare(raw, truth, {
                "4 turns": with_smoothed(raw, poses[:4].mean(0), conf[:4].mean(0)),
                "8 members": with_smoothed(raw, poses.mean(0), conf.mean(0)),
            })  # fmt: skip
            f |= member_correlation(poses, truth[:n])
            f["member0_vs_single_max_mm"] = float(np.nanmax(np.abs(poses[0] - raw.poses[:n])))
            runs.append({"session": session, "demo": d.name, "kind": "tta", "figures": f})
            _print(f"{session}, {d.name}: test-time augmentation, first {n} frames", f)
    summary = summarize(runs)
    print("over the demos and sessions (min - max):")
    for label, v in summary.items():
        print(f"  {label:45s} {v['min']:6.2f} - {v['max']:.2f}")
    extra = {"demos": [str(d) for d in args.demo], "frames": args.frames, "tta": not args.no_tta}
    write_result("smooth_ensembles", {"summary": summary, "runs": runs}, extra=extra)


if __name__ == "__main__":
    main()

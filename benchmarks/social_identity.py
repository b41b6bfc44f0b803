r"""Several animals: who is who in the poses that ``freipose predict --animals`` writes.

``benchmarks/social.py`` scores the tracks (the animals' 3D centres); a user analyses the
poses. Each animal's pose comes from the network on its track's cube, which in close
contact holds parts of the other animal, so a pose can come out as the other animal's
although the track was right. This benchmark runs the whole command on held-out synthetic
social sessions (rendered as ``benchmarks/social.py`` renders them: seeds 1000 + i,
``--cameras`` cameras, 10 fps, two animals of different coats) with a pose network trained
among animals (``--model``, e.g. ``OUT/seed0/social_masked/pose/model.pt`` of
``benchmarks/social_poses.py --mask-others``), and scores the written poses against the
exact truth:

* identity switches of the poses: per frame the predicted poses are matched to the true
  animals by the RMS distance of their keypoints (a match counts only where a pose is at
  most half as far from its animal as from any other,
  :func:`freipose.predict.tracking.identity_switches` on whole poses), and every change of
  the row an animal is matched to is a switch; *lasting* switches (the animal stays with
  the new row for a second or more) and the identity accuracy (share of the matched
  animal-frames on the animal's own row) tell strays from swaps;
* the same for the poses in the tracks' order (``extra/identity_order`` undone): what the
  poses' identity pass (:func:`freipose.predict.identity.relabel_by_poses`) changed;
* how many of the switches of the written poses a user who checks the flagged frames finds
  (``extra/identity_flagged`` on either row within 5 frames before), and the share of
  flagged animal-frames;
* the median error of each animal's keypoints on its own row (P1).

``--workdir`` keeps the sessions and the predictions; a finished step is skipped when run
again.

Example (about 7 minutes per 2-minute session on 2 cores, its rendering included)::

    python benchmarks/social_identity.py --sessions 5 --seconds 120 \
        --model bench/social_poses/seed0/social_masked/pose/model.pt
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
from _cli import step
from _results import write_result
from scipy.optimize import linear_sum_assignment

from freipose.io.poses import read_poses_h5
from freipose.predict.animals import flagged_switches
from freipose.predict.tracking import identity_accuracy, identity_switches, lasting_switches
from freipose.synth import SceneConfig, generate_session


def _session(folder: Path, seed: int, args: argparse.Namespace) -> Path:
    """The rendered two-animal session of ``seed`` (rendered unless it is there)."""
    out = folder / f"a2_s{seed}"
    if not (out / "true_poses.h5").is_file():
        cfg = SceneConfig(frames=int(round(args.seconds * args.fps)), fps=args.fps, seed=seed,
                          n_cameras=args.cameras, size=(args.width, args.height), animals=2,
                          coat_mix="different")  # fmt: skip
        generate_session(out, cfg, workers=1, progress=False)
    return out


def pose_identity(
    poses: np.ndarray, truth: np.ndarray, fps: float, flagged: np.ndarray | None = None
) -> dict[str, float]:
    """Identity figures of poses (T, A, K, 3) against true poses (T, B, K, 3).

    A pose is matched to a true animal within 60 mm RMS over the keypoints (the distance at
    which ``benchmarks/social.py`` matches the tracks' centres). With ``flagged`` (T, A),
    the switches with a flag on either row from 5 frames before are counted too.
    """
    k = poses.shape[2]
    flat = poses.reshape(*poses.shape[:2], -1) / np.sqrt(k)  # norms are RMS keypoint errors
    switches, assigned = identity_switches(
        flat, truth.reshape(*truth.shape[:2], -1) / np.sqrt(k), max_dist=60.0
    )
    return {
        "switches": int(switches),
        "lasting_switches": lasting_switches(assigned, max(int(round(fps)), 1)),
        "identity_accuracy": identity_accuracy(assigned, poses.shape[1]),
        "matched": float((assigned >= 0).mean()),
        **({} if flagged is None else {
            "switches_flagged": flagged_switches(assigned, flagged, 5),
            "flagged_fraction": float(np.asarray(flagged).mean()),
        }),
    }  # fmt: skip


def score(path: Path, truth_path: Path) -> dict[str, Any]:
    """The figures of one predicted session (module docstring)."""
    pred, truth = read_poses_h5(path), read_poses_h5(truth_path)
    p, g = np.asarray(pred.poses, np.float64), np.asarray(truth.poses, np.float64)
    order = np.asarray(pred.extra["identity_order"], np.int64)
    flagged = pred.extra.get("identity_flagged")
    tracks_order = np.empty_like(p)  # row k of frame t: the pose of track k
    np.put_along_axis(tracks_order, order[:, :, None, None], p, axis=1)
    written = pose_identity(p, g, pred.fps, flagged)
    err = [[np.nanmedian(np.linalg.norm(p[:, a] - g[:, b], axis=-1)) for b in range(g.shape[1])]
           for a in range(p.shape[1])]  # fmt: skip
    rows, own = linear_sum_assignment(np.nan_to_num(np.asarray(err), nan=1e9))
    jpe = [float(err[a][b]) for a, b in zip(rows, own, strict=True)]
    return {
        **written,
        "tracks_order": pose_identity(tracks_order, g, pred.fps),
        "relabelled_frames": int((order[1:] != order[:-1]).any(1).sum()),
        "minutes": len(p) / pred.fps / 60.0,
        "jpe_mm": jpe,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", type=Path, required=True, help="pose network trained among animals")
    ap.add_argument("--sessions", type=int, default=2, help="held-out sessions [2]")
    ap.add_argument("--seconds", type=float, default=60.0, help="length of a session [60]")
    ap.add_argument("--fps", type=float, default=10.0)
    ap.add_argument("--cameras", type=int, default=4)
    ap.add_argument("--width", type=int, default=256)
    ap.add_argument("--height", type=int, default=208)
    ap.add_argument("--workdir", type=Path, default=None, help="keep sessions and poses here")
    args = ap.parse_args()
    settings = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()}
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = args.workdir or Path(tmp)
        for i in range(args.sessions):
            seed = 1000 + i
            session = _session(folder, seed, args)
            outdir = folder / "poses"
            out = outdir / f"{session.name}.poses.h5"
            step(out, ["predict", str(session), "--calibration",
                       str(session / "true_calibration.toml"), "--model", str(args.model),
                       "--method", "bgsub", "--animals", "2", "-o", str(outdir),
                       ])  # fmt: skip
            r = {"seed": seed, **score(out, session / "true_poses.h5")}
            runs.append(r)
            t = r["tracks_order"]
            print(f"seed {seed}: {r['switches']} switches of the poses (lasting "
                  f"{r['lasting_switches']}, identity accuracy {r['identity_accuracy']:.3f}, "
                  f"{r['switches_flagged']} flagged, {100 * r['flagged_fraction']:.1f} % of "
                  f"the animal-frames flagged); "
                  f"in the tracks' order {t['switches']} (lasting {t['lasting_switches']}, "
                  f"identity accuracy {t['identity_accuracy']:.3f}); {r['relabelled_frames']} "
                  f"frames relabelled; median error {np.round(r['jpe_mm'], 2)} mm in "
                  f"{r['minutes']:.1f} min", flush=True)  # fmt: skip
    minutes = sum(r["minutes"] for r in runs)
    per10 = 10.0 / minutes if minutes else float("nan")
    summary = {
        "minutes": minutes,
        "switches_per_10min": sum(r["switches"] for r in runs) * per10,
        "lasting_switches_per_10min": sum(r["lasting_switches"] for r in runs) * per10,
        "min_identity_accuracy": min(r["identity_accuracy"] for r in runs),
        "switches_flagged": sum(r["switches_flagged"] for r in runs),
        "switches": sum(r["switches"] for r in runs),
        "flagged_fraction": float(np.mean([r["flagged_fraction"] for r in runs])),
        "tracks_order_switches_per_10min": sum(r["tracks_order"]["switches"] for r in runs) * per10,
        "tracks_order_lasting_switches_per_10min": sum(
            r["tracks_order"]["lasting_switches"] for r in runs
        )
        * per10,
        "tracks_order_min_identity_accuracy": min(
            r["tracks_order"]["identity_accuracy"] for r in runs
        ),
        "median_jpe_mm": float(np.median([j for r in runs for j in r["jpe_mm"]])),
    }
    print(f"== poses written: {summary['switches_per_10min']:.1f} switches per 10 min (lasting "
          f"{summary['lasting_switches_per_10min']:.1f}, identity accuracy >= "
          f"{summary['min_identity_accuracy']:.3f}; {summary['switches_flagged']} of "
          f"{summary['switches']} switches flagged, {100 * summary['flagged_fraction']:.1f} % "
          f"of the animal-frames); in the tracks' order "
          f"{summary['tracks_order_switches_per_10min']:.1f} (lasting "
          f"{summary['tracks_order_lasting_switches_per_10min']:.1f}, identity accuracy >= "
          f"{summary['tracks_order_min_identity_accuracy']:.3f}) over {minutes:.1f} min",
          flush=True)  # fmt: skip
    write_result("social_identity", {"summary": summary, "runs": runs}, extra=settings)


if __name__ == "__main__":
    main()

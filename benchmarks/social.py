"""Several animals: identity swaps and detection recall on held-out synthetic social sessions.

Renders ``--sessions`` synthetic social scenes per animal count (``freipose synth`` with
``--animals``; seeds 1000 + i, never used in the tests), fits a background per camera,
and runs :func:`freipose.predict.animals.track_recording` with
:class:`freipose.detect.multi.SplitForeground` (background subtraction that splits
touching animals), then :func:`freipose.predict.animals.score_tracks` against the truth:

* identity switches per minute (and per 10 minutes, the issue's unit): every change of
  the track an animal is matched to, including a track's stray onto the other animal of
  a contact for a few frames and back (two switches); *lasting* switches (the animal
  stays with the new track for at least a second) and the identity accuracy (share of
  the matched animal-frames on the animal's own track) tell those apart;
* detection recall per animal over the views where it is visible (at least half its
  keypoints visible and half its box inside the image), of the candidate boxes and of
  the tracked animal's own box (IoU >= 0.5);
* frames followed per animal, median 3D centre error, share of flagged frames, and how
  many of the switches were flagged (a flag on either track from 5 frames before).

References in the same run: the frame-by-frame tracker alone (without the
whole-recording identity pass, :mod:`freipose.predict.identity`), the tracker without
the coat colours (motion alone), and the tracker fed the true centres (an ideal
detector; what it switches, motion alone cannot tell apart). The
2-animal figures are the target's; the 3-animal figures are printed and recorded.

With ``--detector-steps N`` the same sessions are also tracked with a trained detector's
peaks (:class:`freipose.detect.multi.PeakBoxes`) instead of the split foreground: per
animal count, ``--detector-sessions`` training sessions (seeds 2000 + i, the last one for
the training's evaluation) are rendered with their labels (a row per animal and frame)
and the detector is fine-tuned from the shipped base for N steps (input side the
image's longer side, batch 8); its figures are recorded under ``detector``.

Example (about 2 minutes per 2-minute session on 2 cores)::

    flock /work/notes/heavy.lock python benchmarks/social.py --sessions 3 --seconds 120
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from _results import write_result

from freipose.detect import BackgroundSubtractor
from freipose.detect.multi import SplitForeground
from freipose.io.calibration import load_calibration
from freipose.io.poses import read_poses_h5
from freipose.io.video import FrameSource
from freipose.predict.animals import score_tracks, track_recording, true_animal_boxes
from freipose.predict.tracking import TrackingConfig, identity_switches, track_animals
from freipose.synth import SceneConfig, generate_session

ARENA = np.array([[-300.0, 300], [-300, 300], [-20, 250]])


def _render(folder: Path, animals: int, seed: int, args: argparse.Namespace) -> Any:
    frames_n = int(round(args.seconds * args.fps))
    cfg = SceneConfig(frames=frames_n, fps=args.fps, seed=seed, n_cameras=args.cameras,
                      size=(args.width, args.height), animals=animals,
                      coat_mix=args.coat_mix)  # fmt: skip
    return generate_session(folder / f"a{animals}_s{seed}", cfg, workers=1, progress=False)


def train_detector(folder: Path, animals: int, args: argparse.Namespace) -> Path:
    """Render the training sessions and fine-tune the detector on them (resumable)."""
    from freipose.detect.train import train_detector as train

    labels = [_render(folder, animals, 2000 + i, args).labels
              for i in range(args.detector_sessions)]  # fmt: skip
    side = 32 * int(np.ceil(max(args.width, args.height) / 32))
    config = {
        "data": {"labels": [str(p) for p in labels[:-1]], "eval_labels": str(labels[-1])},
        "detector": {"input_size": side, "width": 0.35, "neck_channels": 24,
                     "steps": args.detector_steps, "batch_size": 8, "max_images": 2400,
                     "max_eval_instants": 40, "warmup_steps": 20, "checkpoint_every": 500,
                     "log_every": 250},
    }  # fmt: skip
    out = folder / f"detector_a{animals}"
    return train(config, folder / "detector.toml", out, resume=True, device="cpu")


def _detector_figures(frames: list, rig: Any, truth: Any, animals: int, path: Path) -> dict:
    from freipose.detect.detector import Detector
    from freipose.detect.multi import PeakBoxes

    source = PeakBoxes(Detector.load(path, top_k=animals + 2), max_boxes=animals + 2)
    t0 = time.perf_counter()
    res = track_recording(frames, rig, source, animals, truth.fps, bounds=ARENA)
    t_track = time.perf_counter() - t0
    s = score_tracks(res, truth.extra["points2d"], truth.extra["visible2d"], rig)
    return _scores(s) | {"track_ms_per_frame": 1000 * t_track / len(frames)}


def _scores(s: Any) -> dict:
    """The figures of a :class:`~freipose.predict.animals.TrackScores` that both runs record."""
    return {
        "switches": s.switches,
        "recall_boxes": list(s.recall_boxes),
        "recall_tracked": list(s.recall_tracked),
        "followed": list(s.followed),
        "center_error_mm": s.center_error_mm,
        "switches_flagged": s.switches_flagged,
        "lasting_switches": s.lasting_switches,
        "identity_accuracy": s.identity_accuracy,
    }


def run_session(
    folder: Path, animals: int, seed: int, args: argparse.Namespace, detector: Path | None
) -> dict:
    """Render one session, track it three ways (and with the detector) and return its figures."""
    frames_n = int(round(args.seconds * args.fps))
    t0 = time.perf_counter()
    paths = _render(folder, animals, seed, args)
    t_render = time.perf_counter() - t0
    rig = load_calibration(paths.calibration)
    truth = read_poses_h5(paths.truth)
    src = [FrameSource(paths.videos[n]) for n in rig.names]
    frames = [[s.read(t) for s in src] for t in range(frames_n)]
    bg = BackgroundSubtractor.fit({n: [f[i] for f in frames] for i, n in enumerate(rig.names)})
    t0 = time.perf_counter()
    res = track_recording(frames, rig, SplitForeground(bg, animals), animals, truth.fps,
                          bounds=ARENA)  # fmt: skip
    t_track = time.perf_counter() - t0
    p2, v2 = truth.extra["points2d"], truth.extra["visible2d"]
    full = score_tracks(res, p2, v2, rig)
    _, centres = true_animal_boxes(p2, rig)
    hyps = [d.centers for d in res.detections]
    blind = track_animals(hyps, animals, truth.fps)
    blind_sw, _ = identity_switches(blind.centers, centres)
    online = track_animals(hyps, animals, truth.fps, features=list(res.features),
                           config=TrackingConfig(resolve=False))  # fmt: skip
    online_sw, _ = identity_switches(online.centers, centres)
    ideal = track_animals(list(centres), animals, truth.fps)
    ideal_sw, _ = identity_switches(ideal.centers, centres)
    contact = truth.extra["contact"]
    out = {
        "seed": seed,
        "minutes": full.minutes,
        **_scores(full),
        "switches_motion_only": int(blind_sw),
        "switches_frame_by_frame": int(online_sw),
        "switches_true_centres": int(ideal_sw),
        "flagged_fraction": full.flagged_fraction,
        "contact_fraction": float(np.asarray(contact).any((1, 2)).mean()),
        "render_s": t_render,
        "track_ms_per_frame": 1000 * t_track / frames_n,
    }
    if detector is not None:
        out["detector"] = _detector_figures(frames, rig, truth, animals, detector)
    return out


def summarize(runs: list[dict]) -> dict:
    """Totals over the sessions of one animal count."""
    minutes = sum(r["minutes"] for r in runs)
    sw = sum(r["switches"] for r in runs)
    return {
        "sessions": len(runs),
        "minutes": minutes,
        "switches": sw,
        "switches_per_10min": 10 * sw / minutes,
        "switches_per_10min_motion_only": 10
        * sum(r["switches_motion_only"] for r in runs)
        / minutes,
        "switches_per_10min_frame_by_frame": 10
        * sum(r["switches_frame_by_frame"] for r in runs)
        / minutes,
        "switches_true_centres": sum(r["switches_true_centres"] for r in runs),
        "min_recall_boxes": min(min(r["recall_boxes"]) for r in runs),
        "min_recall_tracked": min(min(r["recall_tracked"]) for r in runs),
        "median_recall_boxes": float(np.median([x for r in runs for x in r["recall_boxes"]])),
        "min_followed": min(min(r["followed"]) for r in runs),
        "median_center_error_mm": float(np.median([r["center_error_mm"] for r in runs])),
        "flagged_fraction": float(np.mean([r["flagged_fraction"] for r in runs])),
        "switches_flagged": sum(r["switches_flagged"] for r in runs),
        "lasting_switches_per_10min": 10 * sum(r["lasting_switches"] for r in runs) / minutes,
        "min_identity_accuracy": min(r["identity_accuracy"] for r in runs),
        "contact_fraction": float(np.mean([r["contact_fraction"] for r in runs])),
        "track_ms_per_frame": float(np.median([r["track_ms_per_frame"] for r in runs])),
    } | _detector_summary(runs, minutes)


def _detector_summary(runs: list[dict], minutes: float) -> dict:
    """The detector's totals over the sessions (empty without ``--detector-steps``)."""
    det = [r["detector"] for r in runs if "detector" in r]
    if not det:
        return {}
    return {
        "detector_switches_per_10min": 10 * sum(d["switches"] for d in det) / minutes,
        "detector_min_recall_boxes": min(min(d["recall_boxes"]) for d in det),
        "detector_median_recall_boxes": float(
            np.median([x for d in det for x in d["recall_boxes"]])
        ),
        "detector_min_recall_tracked": min(min(d["recall_tracked"]) for d in det),
        "detector_min_followed": min(min(d["followed"]) for d in det),
        "detector_median_center_error_mm": float(np.median([d["center_error_mm"] for d in det])),
        "detector_lasting_switches_per_10min": 10
        * sum(d["lasting_switches"] for d in det)
        / minutes,
        "detector_min_identity_accuracy": min(d["identity_accuracy"] for d in det),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sessions", type=int, default=2, help="sessions per animal count [2]")
    ap.add_argument("--seconds", type=float, default=60.0, help="length of a session [60]")
    ap.add_argument("--fps", type=float, default=10.0, help="frame rate [10]")
    ap.add_argument("--cameras", type=int, default=4)
    ap.add_argument("--width", type=int, default=256)
    ap.add_argument("--height", type=int, default=208)
    ap.add_argument("--coat-mix", default="different", choices=("random", "same", "different"))
    ap.add_argument("--animals", default="2,3", help="animal counts [2,3]")
    ap.add_argument("--workdir", type=Path, default=None, help="keep the sessions here")
    ap.add_argument(
        "--detector-steps",
        type=int,
        default=0,
        help="also track with a detector fine-tuned this many steps [0: no]",
    )
    ap.add_argument(
        "--detector-sessions",
        type=int,
        default=6,
        help="training sessions of the detector, the last for evaluation [6]",
    )
    args = ap.parse_args()
    settings = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()}
    figures: dict = {}
    with tempfile.TemporaryDirectory() as tmp:
        folder = args.workdir or Path(tmp)
        for n in (int(a) for a in args.animals.split(",")):
            runs = []
            det = train_detector(folder, n, args) if args.detector_steps > 0 else None
            for i in range(args.sessions):
                r = run_session(folder, n, 1000 + i, args, det)
                runs.append(r)
                print(f"{n} animals, seed {r['seed']}: {r['switches']} switches "
                      f"(frame by frame only {r['switches_frame_by_frame']}, motion only "
                      f"{r['switches_motion_only']}, true centres "
                      f"{r['switches_true_centres']}; lasting {r['lasting_switches']}, identity "
                      f"accuracy {r['identity_accuracy']:.3f}) in {r['minutes']:.1f} min; "
                      f"recall boxes "
                      f"{np.round(r['recall_boxes'], 3)}, tracked "
                      f"{np.round(r['recall_tracked'], 3)}, "
                      f"followed {np.round(r['followed'], 3)}; centre error "
                      f"{r['center_error_mm']:.1f} mm; contact {100 * r['contact_fraction']:.0f} %",
                      flush=True)  # fmt: skip
                if "detector" in r:
                    d = r["detector"]
                    print(f"  with the detector: {d['switches']} switches (lasting "
                          f"{d['lasting_switches']}, identity accuracy "
                          f"{d['identity_accuracy']:.3f}); recall boxes "
                          f"{np.round(d['recall_boxes'], 3)}, tracked "
                          f"{np.round(d['recall_tracked'], 3)}; centre error "
                          f"{d['center_error_mm']:.1f} mm", flush=True)  # fmt: skip
            s = summarize(runs)
            figures[f"animals{n}"] = {"summary": s, "runs": runs}
            print(f"== {n} animals: {s['switches_per_10min']:.2f} switches per 10 min "
                  f"(frame by frame only {s['switches_per_10min_frame_by_frame']:.2f}, "
                  f"motion only {s['switches_per_10min_motion_only']:.2f}; true centres "
                  f"{s['switches_true_centres']} switches; lasting "
                  f"{s['lasting_switches_per_10min']:.2f} per 10 min, identity accuracy >= "
                  f"{s['min_identity_accuracy']:.3f}), recall per animal and view "
                  f">= {s['min_recall_boxes']:.3f} (tracked {s['min_recall_tracked']:.3f}), "
                  f"{s['switches_flagged']} of {s['switches']} switches flagged "
                  f"({100 * s['flagged_fraction']:.1f} % of the frames flagged), "
                  f"median centre error {s['median_center_error_mm']:.1f} mm",
                  flush=True)  # fmt: skip
            if "detector_switches_per_10min" in s:
                print(f"== {n} animals with the detector: "
                      f"{s['detector_switches_per_10min']:.2f} switches per 10 min (lasting "
                      f"{s['detector_lasting_switches_per_10min']:.2f}, identity accuracy >= "
                      f"{s['detector_min_identity_accuracy']:.3f}), recall per "
                      f"animal and view >= {s['detector_min_recall_boxes']:.3f} (median "
                      f"{s['detector_median_recall_boxes']:.3f}; tracked "
                      f"{s['detector_min_recall_tracked']:.3f}), median centre error "
                      f"{s['detector_median_center_error_mm']:.1f} mm", flush=True)  # fmt: skip
    write_result("social", figures, extra=settings)


if __name__ == "__main__":
    main()

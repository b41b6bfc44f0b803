"""FreiPose calibration vs aniposelib on the same rendered ChArUco rig videos.

Renders board videos with ``freipose.synth.board`` (known cameras with lens distortion and
sensor noise; principal points at the image centre, square pixels, no tangential
distortion), calibrates them with ``freipose calib``'s pipeline and with aniposelib's
``CameraGroup.calibrate_videos`` (its two halves, timed separately), and prints camera-centre,
rotation and focal-length errors (the maximum over cameras, after the same similarity
alignment of all camera centres for both tools), detection and solver times, and ratios.
FreiPose detects with its default of one process per CPU; aniposelib runs in one process,
its OpenCV calls on OpenCV's thread pool.
The videos are .mp4 (MPEG-4 Part 2) by default, like camera recordings: ~1 ms per frame to
decode; ``--format .mkv`` writes lossless FFV1 (~20 ms per frame), whose decoding then
dominates both tools' time. ``--noise-floor N`` also reports what FreiPose's solver gives when
its own corners are replaced by exact projections plus Gaussian noise of the measured size.

``--inverted`` renders the board printed inverted (``inverted = true``); ``--below-floor``
puts the last camera below a transparent floor, looking up at a transparent board (it and any
camera behind the board see the pattern mirrored: FreiPose finds it in the mirror image).
Both also render and calibrate the normal recording of the same seed ("freipose normal");
aniposelib, which reads neither, runs on that normal recording. The per-camera counts of
front and back views are printed. ``--noisy-camera PX`` adds heavy-tailed noise (Student t,
4 degrees of freedom, scale PX) to the last camera's detected corners before FreiPose's
solver, as a camera whose corners are honestly noisier than the others' (0.45 gives a median
error of about 0.6 px), and prints the share of its detections the solver rejected.

Every seed's table is recorded as a result (``benchmarks/results/calibration/``); the
recorded runs, as median and range, are in ``docs/benchmarks.md``.

    python benchmarks/calibration.py --seed 1 2 3 --repeat 3
"""

from __future__ import annotations

import argparse
import contextlib
import io
import os
import tempfile
import time
from pathlib import Path

import numpy as np
from _results import write_result

DIVERGED_MM = 20.0  # an aniposelib result this far off counts as diverged


def errors(centers, rotations, focals, truth):
    """Max centre error (mm), max rotation error (deg), max |focal error| (%)."""
    from freipose.geometry.alignment import camera_errors

    dc, rot, fe, _ = camera_errors(centers, rotations, focals, truth)
    return float(dc.max()), float(np.max(rot)), float(np.max(np.abs(fe)))


def run_freipose(videos, board, out: Path, jobs: int | None, noisy: float = 0.0):
    """What ``calibrate`` does (detection in ``jobs`` processes, then the solver), timed.

    ``noisy``: scale (px) of the Student-t noise added to the last camera's corners.

    Returns centres, rotations, focals, detection s, solver s, detections, result.
    """
    from freipose.calibration.detect_videos import detect_cameras
    from freipose.calibration.options import CalibrationOptions
    from freipose.calibration.pipeline import calibrate_detections

    t0 = time.perf_counter()
    dets = detect_cameras(videos, board, cache_dir=None, jobs=jobs, progress=False)
    t1 = time.perf_counter()
    if noisy > 0:
        import dataclasses

        p = dets[-1].points.copy()
        m = np.isfinite(p[..., 0])
        p[m] += noisy * np.random.default_rng(1).standard_t(4, (int(m.sum()), 2))
        dets = [*dets[:-1], dataclasses.replace(dets[-1], points=p)]
    res = calibrate_detections(dets, board, CalibrationOptions(jobs=jobs, progress=False))
    t2 = time.perf_counter()
    rig = res.rig
    focals = [0.5 * (c.K[0, 0] + c.K[1, 1]) for c in rig]
    return rig.centers, [c.R for c in rig], focals, t1 - t0, t2 - t1, dets, res


def noise_floor(dets, board, truth, poses, sigma: float, draws: int, seed: int) -> np.ndarray:
    """FreiPose's errors (draws, 3) from its detected corners' exact projections plus noise.

    The noise is independent Gaussian noise of ``sigma`` px per axis: what the detector's
    noise alone leaves on this recording (its board views, image coverage and tilts).
    """
    from freipose.calibration.detect import CameraDetections
    from freipose.calibration.options import CalibrationOptions
    from freipose.calibration.pipeline import calibrate_detections
    from freipose.geometry import project

    rng = np.random.default_rng(seed)
    out = []
    for _ in range(draws):
        noisy = []
        for cam, d in zip(truth, dets):
            pts = np.full_like(d.points, np.nan)
            for f in np.flatnonzero(d.mask.any(axis=1)):
                m = d.mask[f]
                X = board.object_points[m] @ poses[f, :3, :3].T + poses[f, :3, 3]
                pts[f, m] = project(X, cam) + rng.normal(0, sigma, (int(m.sum()), 2))
            noisy.append(CameraDetections(d.name, d.size, pts))
        rig = calibrate_detections(noisy, board, CalibrationOptions(progress=False)).rig
        out.append(errors(rig.centers, [c.R for c in rig], [c.K[0, 0] for c in rig], truth))
    return np.array(out)


def run_aniposelib(videos, board, seed: int):
    """``CameraGroup.calibrate_videos`` timed in its two parts.

    The parts are ``get_rows_videos`` and ``calibrate_rows``. aniposelib subsamples points
    with ``np.random``: seeded for reproducibility.
    """
    import cv2
    from aniposelib.boards import CharucoBoard
    from aniposelib.cameras import CameraGroup

    bits = int(board.dictionary.split("_")[1][0])
    size = int(board.dictionary.split("_")[2])
    ab = CharucoBoard(
        board.squares_x,
        board.squares_y,
        square_length=board.square_size,
        marker_length=board.marker_size,
        marker_bits=bits,
        dict_size=size,
    )
    names = [Path(v).stem for v in videos]
    # aniposelib at its defaults: OpenCV's thread pool over all CPUs (its detection uses it)
    cv2.setNumThreads(-1)
    cg = CameraGroup.from_names(names, fisheye=False)
    vids = [[str(v)] for v in videos]
    np.random.seed(seed)
    # (aniposelib prints its camera dicts even with verbose=False)
    with contextlib.redirect_stdout(io.StringIO()):
        t0 = time.perf_counter()
        rows = cg.get_rows_videos(vids, ab, verbose=False)
        cg.set_camera_sizes_videos(vids)
        t1 = time.perf_counter()
        cg.calibrate_rows(rows, ab, verbose=False)
        t2 = time.perf_counter()
    centers, rots, focals = [], [], []
    for cam in cg.cameras:
        R = cam.get_rotation()
        R = R if np.shape(R) == (3, 3) else cv2.Rodrigues(np.asarray(R))[0]
        t = np.asarray(cam.get_translation()).reshape(3)
        centers.append(-R.T @ t)
        rots.append(R)
        K = cam.get_camera_matrix()
        focals.append(0.5 * (K[0, 0] + K[1, 1]))
    return np.array(centers), rots, focals, t1 - t0, t2 - t1


def render_rig(args, seed: int, work: Path, variant: bool):
    """Render one recording: ``(rig, board, videos, poses, render s)``.

    The default rig and board, or (``variant``) with the board inverted (``--inverted``)
    and/or the last camera below a transparent floor looking up at a transparent board
    (``--below-floor``; every camera behind the board sees its pattern mirrored).
    """
    import dataclasses

    from freipose.geometry import CameraRig
    from freipose.synth.board import default_board, write_board_videos
    from freipose.synth.rig import camera_below_floor, default_rig

    size = (args.width, args.width * 3 // 4)
    rig = default_rig(args.cameras, size=size)
    board = default_board()
    below = variant and args.below_floor
    if variant and args.inverted:
        board = dataclasses.replace(board, inverted=True)
    if below:
        last = camera_below_floor(rig[-1].name, size)
        rig = CameraRig((*rig.cameras[:-1], last), rig.metadata)
    t0 = time.perf_counter()
    vids, poses = write_board_videos(
        work, rig, board, args.frames, seed=seed, fmt=args.format, progress=False,
        transparent=below,
    )  # fmt: skip
    return rig, board, [vids[n] for n in rig.names], poses, time.perf_counter() - t0


def bench_seed(args, seed: int, work: Path) -> dict:
    variant = args.inverted or args.below_floor or args.noisy_camera > 0
    rig, board, videos, poses, t_render = render_rig(args, seed, work, variant)
    jobs = args.jobs or os.cpu_count() or 1
    what = " inverted board" if args.inverted else ""
    if args.below_floor:
        what += f", {rig[-1].name} below a transparent floor (transparent board)"
    if args.noisy_camera > 0:
        what += f", {rig[-1].name}'s corners with t noise of {args.noisy_camera} px"
    print(
        f"\nseed {seed}: {args.cameras} x {args.frames} frames {args.width}x"
        f"{args.width * 3 // 4} {args.format}{what} (rendered in {t_render:.1f} s); "
        f"FreiPose detection processes: {jobs}; aniposelib: OpenCV's default thread pool"
    )
    normal = None
    if variant:  # the normal case of the same seed, for FreiPose and aniposelib
        normal = render_rig(args, seed, work / "normal", False)
        print(
            "aniposelib runs on the normal recording (normal print, default rig): it reads "
            "neither inverted boards nor boards seen from behind"
        )
    anipose_videos = normal[2] if normal else videos
    rows, runs = {}, {"freipose": [], "aniposelib": []}
    if normal:
        runs["freipose normal"] = []
    have_aniposelib = True
    # the tools take turns, so that a slower spell of a shared machine falls on both; each
    # tool's errors are the same in every run (aniposelib's sampling is seeded)
    for i in range(args.repeat):
        c, r, f, td, ts, dets, res = run_freipose(videos, board, work, jobs, args.noisy_camera)
        runs["freipose"].append((td, ts))
        if i == 0:
            rows["freipose"] = errors(np.asarray(c), r, f, rig)
            last = res.bundle.obs.cam == len(rig) - 1
            print(
                f"{rig[-1].name}: median error {np.median(res.bundle.errors[last]):.2f} px, "
                f"{100 * np.mean(~res.bundle.inliers[last]):.1f} % of its detections rejected"
            )
            print(
                "board views per camera (front/back): "
                + ", ".join(
                    f"{d.name} {int((d.counts >= 4).sum()) - d.back_views}/{d.back_views}"
                    for d in dets
                )
            )
        if normal:
            c, r, f, td, ts, _d, _r = run_freipose(normal[2], normal[1], work, jobs)
            runs["freipose normal"].append((td, ts))
            if i == 0:
                rows["freipose normal"] = errors(np.asarray(c), r, f, normal[0])
        if not have_aniposelib:
            continue
        try:
            c, r, f, td, ts = run_aniposelib(anipose_videos, normal[1] if normal else board, seed)
        except ImportError:
            print("aniposelib is not installed (pip install -e .[bench]); FreiPose only")
            have_aniposelib = False
            continue
        runs["aniposelib"].append((td, ts))
        if i == 0:
            rows["aniposelib"] = errors(c, r, f, normal[0] if normal else rig)
    for k in rows:
        # the run with the median wall time (detect + solve)
        rows[k] = (*rows[k], *sorted(runs[k], key=sum)[len(runs[k]) // 2])
    if args.repeat > 1:
        print(
            "wall s per run: "
            + "; ".join(f"{k} " + ", ".join(f"{sum(t):.2f}" for t in runs[k]) for k in rows)
            + f" (the table: the median of {args.repeat})"
        )
    print(
        f"{'method':<16}{'centre err mm':>15}{'rot err deg':>13}{'focal err %':>13}"
        f"{'detect s':>10}{'solve s':>9}{'wall s':>9}"
    )
    for k, v in rows.items():
        print(
            f"{k:<16}{v[0]:>15.3f}{v[1]:>13.3f}{v[2]:>13.3f}{v[3]:>10.2f}{v[4]:>9.2f}"
            f"{v[3] + v[4]:>9.2f}"
        )
    if "aniposelib" in rows:
        a, b = rows["aniposelib"], rows["freipose"]
        print(
            f"{'ratio a/f':<16}{a[0] / b[0]:>15.2f}{a[1] / b[1]:>13.2f}{a[2] / b[2]:>13.2f}"
            f"{a[3] / b[3]:>10.2f}{a[4] / b[4]:>9.2f}{(a[3] + a[4]) / (b[3] + b[4]):>9.2f}"
            f"   (aniposelib / FreiPose; > 1 means FreiPose is better)"
        )
    if args.noise_floor:
        from freipose.calibration.robust import noise_sigma

        ba = res.bundle
        sigma = noise_sigma(ba.errors[ba.inliers])
        nf = noise_floor(dets, board, rig, poses, sigma, args.noise_floor, seed)
        lo, med, hi = np.percentile(nf, [0, 50, 100], axis=0)
        print(
            f"noise floor ({args.noise_floor} draws: FreiPose on its own corners projected "
            f"exactly + N(0, {sigma:.3f} px), the detection noise it measured): centre "
            f"{med[0]:.3f} mm ({lo[0]:.3f}-{hi[0]:.3f}), rot {med[1]:.3f} deg "
            f"({lo[1]:.3f}-{hi[1]:.3f}), focal {med[2]:.3f} % ({lo[2]:.3f}-{hi[2]:.3f}): "
            f"median (min-max)"
        )
    return rows


def _figures(rows: dict) -> dict:
    """One seed's table as figures: per method the largest errors and the times."""
    keys = ("max_center_mm", "max_rotation_deg", "max_focal_percent", "detect_s", "solve_s")
    return {m: dict(zip(keys, map(float, v))) for m, v in rows.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cameras", type=int, default=4)
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument(
        "--jobs", type=int, default=None, help="FreiPose detection processes (default: CPUs)"
    )
    ap.add_argument(
        "--seed", type=int, nargs="+", default=[1], help="board motion and image noise seed(s)"
    )
    ap.add_argument(
        "--workdir", type=Path, default=None, help="keep the videos here (seed<N>/ per seed)"
    )
    ap.add_argument(
        "--repeat",
        type=int,
        default=3,
        metavar="N",
        help="time each tool N times, taking turns, and report the run with the median wall "
        "time (default 3)",
    )
    ap.add_argument(
        "--noise-floor",
        type=int,
        default=0,
        metavar="N",
        help="also calibrate N times from FreiPose's corners projected exactly plus Gaussian "
        "noise of the measured detection noise (what noise alone leaves on the recording)",
    )
    ap.add_argument(
        "--format",
        default=".mp4",
        choices=(".mp4", ".mkv"),
        help="video container: .mp4 (MPEG-4 Part 2, lossy, fast to decode, like camera "
        "recordings; default) or .mkv (lossless FFV1, ~20 ms per frame to decode)",
    )
    ap.add_argument(
        "--inverted",
        action="store_true",
        help="render the board printed inverted (white on black; inverted = true) and also "
        "the normal case of each seed",
    )
    ap.add_argument(
        "--below-floor",
        action="store_true",
        help="the last camera stands below a transparent floor looking up at a transparent "
        "board (cameras behind the board see it mirrored); also renders the normal case",
    )
    ap.add_argument(
        "--noisy-camera",
        type=float,
        default=0.0,
        metavar="PX",
        help="add Student-t noise (4 degrees of freedom, scale PX) to the last camera's "
        "corners before FreiPose's solver (a camera with noisier corners); also renders the "
        "normal case",
    )
    args = ap.parse_args()
    if args.repeat < 1:
        ap.error("--repeat must be at least 1")

    from freipose.synth.board import default_board

    tmp = tempfile.TemporaryDirectory()
    root = args.workdir or Path(tmp.name)
    print(f"board {default_board()}")
    results = {s: bench_seed(args, s, root / f"seed{s}") for s in args.seed}
    settings = {k: getattr(args, k) for k in ("cameras", "frames", "width", "format", "repeat")}
    settings |= {"inverted": args.inverted, "below_floor": args.below_floor}
    if args.noisy_camera > 0:
        settings["noisy_camera"] = args.noisy_camera
    for s, rows in results.items():
        write_result("calibration", _figures(rows), extra={"seed": s, **settings})
    print(
        "\nerrors are the maximum over cameras after a similarity alignment of all camera "
        "centres (the same for both tools); wall = detect + solve"
    )
    both = {s: r for s, r in results.items() if "aniposelib" in r}
    diverged = [s for s, r in both.items() if r["aniposelib"][0] > DIVERGED_MM]
    if diverged:
        print(
            f"aniposelib diverged (centre error > {DIVERGED_MM:.0f} mm) on seed(s) "
            f"{' '.join(map(str, diverged))}: left out of the error ratios below"
        )
    names = ("centre err", "rot err", "focal err", "wall")
    ratios = np.array(
        [[r["aniposelib"][i] / r["freipose"][i] if s not in diverged else np.nan
          for i in range(3)] + [sum(r["aniposelib"][3:]) / sum(r["freipose"][3:])]
         for s, r in both.items()]
    ).reshape(-1, 4)  # fmt: skip
    if len(ratios) > 1:
        parts = []
        for i, n in enumerate(names):
            v = ratios[:, i][np.isfinite(ratios[:, i])]
            if len(v):
                parts.append(
                    f"{n}: FreiPose better or equal in {int((v >= 1).sum())}/{len(v)}, ratio min "
                    f"{v.min():.2f}, geometric mean {np.exp(np.log(v).mean()):.2f}"
                )
        print(
            f"aniposelib / FreiPose over seeds {' '.join(map(str, both))}:\n  " + "\n  ".join(parts)
        )


if __name__ == "__main__":
    main()

"""How far off is an animal near the floor when the board never went there?

A rig of four wide-angle cameras with strong barrel distortion (k1 k2 k3, fisheye-like)
looks down at a 400 mm arena. The board is laid on the floor once (the origin frame) and
then waved only in the upper part of the volume (``--upper``: its centre 200-330 mm above
the floor), or all over it down to the floor (``--covered``). The board corners are
projected exactly (plus 0.2 px noise; no rendering), calibrated with ``freipose calib``'s
pipeline (``--origin-frame 0``, default model selection: k1 k2 unless more is significant),
and 81 "mice" (80 mm from nose to tail) all over the 400 mm arena, 20 mm above the floor
and at the board's height, are projected with the true cameras and triangulated with the
calibrated ones. Printed: the mice's length errors (median and worst), the board's
reprojection RMS, the coverage figures and the warnings the calibration gives.

    python benchmarks/calibration_coverage.py --seed 0 1 2

What to look for: the board reprojects equally well in both recordings and mice at the
board's height come out right in both, so a board that measures right says nothing about
the floor. Where the board never was in the image, the fitted k1 k2 model extrapolates the
true lens (with k3) wrongly and lengths there are off (the worst mice stand at the arena's
edge, low in the images). Each seed's figures are recorded as a result
(``benchmarks/results/calibration_coverage/``, shown in ``docs/benchmarks.md``).
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass

import numpy as np

from freipose.calibration.boards import CharucoBoard
from freipose.calibration.detect import CameraDetections
from freipose.calibration.options import CalibrationOptions
from freipose.calibration.pipeline import CalibrationResult, calibrate_detections
from freipose.geometry import Camera, CameraRig, project, triangulate
from freipose.geometry.transforms import rodrigues

BOARD = CharucoBoard(7, 5, 30.0, 22.0, "DICT_4X4_50")
ARENA = 200.0  # half the side of the square arena (mm)
# fisheye-like barrel distortion; k3 makes the true lens differ from a k1 k2 model
TRUE_DIST = np.array([-0.32, 0.11, 0.0, 0.0, -0.018])


def fisheye_rig(n: int = 4) -> CameraRig:
    """``n`` 1280x1024 cameras, f = 480 px, 380 mm out and 200 mm up.

    They look at the arena's centre 150 mm above the floor, so the floor fills the lower
    part of their images.
    """
    cams = []
    for i in range(n):
        a = 2 * np.pi * i / n + 0.3
        pos = (380.0 * np.cos(a), 380.0 * np.sin(a), 200.0)
        cam = Camera.look_at(f"cam{i}", pos, (0, 0, 150), (1280, 1024), 480.0, dist=TRUE_DIST)
        cams.append(cam)
    return CameraRig(tuple(cams), {"world": "arena centre on the floor, z up"})


def board_poses(frames: int, covered: bool, rng: np.random.Generator) -> np.ndarray:
    """(F, 4, 4) board→world: frame 0 flat on the floor, then waved (see the module)."""
    centroid = np.array([BOARD.size_mm[0] / 2, BOARD.size_mm[1] / 2, 0.0])
    poses = np.zeros((frames, 4, 4))
    flat = np.diag([1.0, -1.0, -1.0])  # printed side up: the board's z points down
    for f in range(frames):
        if f == 0:
            R, c = flat, np.array([0.0, 0.0, 0.0])
        else:
            R = rodrigues(rng.normal(0, 0.45, 3)) @ flat
            low = covered and f % 2 == 1
            lo, hi = (20.0, 80.0) if low else (150.0, 250.0)
            reach = ARENA - 60 if covered else 60.0  # else held above the arena's middle
            c = np.array([*rng.uniform(-reach, reach, 2), rng.uniform(lo, hi)])
        t = c - R @ centroid
        corners = BOARD.object_points @ R.T + t
        t[2] += max(0.0, 2.0 - corners[:, 2].min())  # never below the floor
        poses[f, :3, :3], poses[f, :3, 3], poses[f, 3, 3] = R, t, 1.0
    return poses


def detections(
    rig: CameraRig, poses: np.ndarray, rng: np.random.Generator, noise_px: float = 0.2
) -> list[CameraDetections]:
    """The board's corners as each camera sees them (facing it, inside the image)."""
    out = []
    P = len(BOARD.object_points)
    for cam in rig:
        pts = np.full((len(poses), P, 2), np.nan)
        for f, B in enumerate(poses):
            X = BOARD.object_points @ B[:3, :3].T + B[:3, 3]
            ray = X.mean(axis=0) - cam.center
            if ray @ B[:3, 2] < 0.25 * np.linalg.norm(ray):  # printed side away or grazing
                continue
            uv = project(X, cam)
            ok = np.isfinite(uv).all(axis=1)
            ok &= (uv[:, 0] >= 0) & (uv[:, 0] <= cam.width - 1)
            ok &= (uv[:, 1] >= 0) & (uv[:, 1] <= cam.height - 1)
            if ok.sum() >= 8:
                pts[f, ok] = uv[ok] + rng.normal(0, noise_px, (int(ok.sum()), 2))
        out.append(CameraDetections(cam.name, tuple(cam.size), pts))
    return out


def mouse_errors(est: CameraRig, truth: CameraRig, height: float, seed: int = 0) -> np.ndarray:
    """Relative length errors (%) of 80 mm "mice" all over the arena at ``height`` mm.

    A mouse is a pair of points 80 mm apart (nose and tail base), one on each of 9 x 9
    positions over the arena (``ARENA``), turned at random; both points are projected
    exactly with ``truth`` and triangulated with ``est``.

    Returns:
        (81,) signed errors of the triangulated length, percent.
    """
    rng = np.random.default_rng(seed)
    g = np.linspace(-ARENA + 40, ARENA - 40, 9)
    mid = np.array([[x, y, height] for x in g for y in g])
    a = rng.uniform(0, np.pi, len(mid))
    half = 40.0 * np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], axis=1)
    X = np.concatenate([mid - half, mid + half])  # (2M, 3)
    Y = triangulate(np.moveaxis(truth.project(X), 0, -2), est)
    n = len(mid)
    return 100 * (np.linalg.norm(Y[n:] - Y[:n], axis=1) / 80.0 - 1)


@dataclass(frozen=True)
class Outcome:
    """One calibration of the scenario."""

    result: CalibrationResult
    floor_errors_pct: np.ndarray
    board_errors_pct: np.ndarray


def run(covered: bool, seed: int, frames: int = 120) -> Outcome:
    """Calibrate the scenario and measure the scale near the floor and at the board's height."""
    rng = np.random.default_rng(seed)
    truth = fisheye_rig()
    dets = detections(truth, board_poses(frames, covered, rng), rng)
    res = calibrate_detections(
        dets,
        BOARD,
        CalibrationOptions(origin_frame=0, jobs=1, progress=False, accept_implausible=True),
    )  # an implausible calibration is measured too (its findings are printed)
    return Outcome(res, mouse_errors(res.rig, truth, 20.0), mouse_errors(res.rig, truth, 200.0))


def main() -> None:
    """Print the scale errors and warnings of both board recordings for each seed."""
    from _results import write_result

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seed", type=int, nargs="+", default=[0])
    ap.add_argument("--frames", type=int, default=120)
    a = ap.parse_args()
    for seed in a.seed:
        figures = {}
        for covered in (False, True):
            o = run(covered, seed, a.frames)
            res = o.result
            rms = float(np.sqrt(np.mean(res.bundle.errors[res.bundle.inliers] ** 2)))
            models = {c: m["distortion"] for c, m in res.rig.metadata["intrinsics_model"].items()}
            floor = [c.floor_views for c in res.coverage]
            region = [None if c.floor_region is None else round(c.floor_region, 2)
                      for c in res.coverage]  # fmt: skip
            fl, bo = o.floor_errors_pct, o.board_errors_pct
            print(
                f"seed {seed} {'covered' if covered else 'upper  '}: 80 mm mouse on the floor "
                f"{np.median(fl):+.2f} % median, {np.abs(fl).max():.2f} % worst; at the "
                f"board's height {np.median(bo):+.2f} %, {np.abs(bo).max():.2f} % worst; "
                f"RMS {rms:.3f} px, floor views {floor}, floor region covered {region}, "
                f"distortion {sorted(set(models.values()))}, "
                f"{sum('floor' in w for w in res.warnings)} floor warnings"
                + (f"; REFUSED without --force: {[f.check for f in res.findings]}"
                   if res.findings else "")
            )  # fmt: skip
            figures["covered" if covered else "upper"] = {
                "floor_median_pct": np.median(fl),
                "floor_worst_pct": np.abs(fl).max(),
                "board_height_median_pct": np.median(bo),
                "board_height_worst_pct": np.abs(bo).max(),
                "rms_px": rms,
                "floor_warnings": sum("floor" in w for w in res.warnings),
                "refused": bool(res.findings),
            }
        write_result("calibration_coverage", figures, extra={"seed": seed, "frames": a.frames})


if __name__ == "__main__":
    main()

"""Board coverage (#21 item 8): image cells, depths and the floor per camera, and the warning."""

from __future__ import annotations

import dataclasses
import importlib.util
import json
import sys
from pathlib import Path

import numpy as np
import pytest

from freipose.calibration.coverage import board_coverage, coverage_warnings
from freipose.calibration.options import CalibrationOptions
from freipose.calibration.pipeline import calibrate_detections
from freipose.calibration.report import report_text, write_report
from freipose.io.calibration_world import world_up

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def scenario():
    """benchmarks/calibration_coverage.py: fisheye rig, board above the arena or all over it."""
    spec = importlib.util.spec_from_file_location(
        "calibration_coverage", ROOT / "benchmarks" / "calibration_coverage.py"
    )
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # its dataclasses look their module up
    spec.loader.exec_module(mod)
    yield mod
    del sys.modules[spec.name]


def _calibrate(scenario, covered: bool, origin: int | None = 0):
    rng = np.random.default_rng(3)
    truth = scenario.fisheye_rig()
    dets = scenario.detections(truth, scenario.board_poses(60, covered, rng), rng)
    opts = CalibrationOptions(origin_frame=origin, jobs=1, progress=False)
    return calibrate_detections(dets, scenario.BOARD, opts), truth


def test_a_board_held_above_the_arena_warns_for_the_floor(scenario, tmp_path):
    res, truth = _calibrate(scenario, covered=False)
    floor_warnings = [w for w in res.warnings if "of the floor" in w]
    assert len(floor_warnings) == 4, res.warnings  # one per camera
    assert "came within 50 mm of the floor in 1 of its views" in floor_warnings[0]
    assert "coverage_cam0.png" in " ".join(floor_warnings)
    for c in res.coverage:
        assert c.floor_views == 1 and c.lowest_mm < 5.0  # only the origin frame
        assert 0 < c.image_fraction < 1 and c.depth_mm[0] < c.depth_mm[1] < c.depth_mm[2]
    for c, d in zip(res.coverage, res.detections):
        assert c.grid.shape == (6, 8) and c.grid.sum() == d.mask.sum()
    paths = write_report(res, tmp_path)
    summary = json.loads((tmp_path / "summary.json").read_text())
    cov = summary["cameras"]["cam0"]["coverage"]
    assert cov["floor_views"] == 1 and 0 < cov["floor_region_covered"] <= 1
    assert len(cov["depth_mm_p5_median_p95"]) == 3
    assert tmp_path / "coverage_cam0.png" in paths
    text = (tmp_path / "report.txt").read_text()
    assert "printed normally" in text and "0 of them seen from behind" in text
    assert "views within 50 mm of the floor" in text and "Warnings:" in text
    assert "Plausibility checks passed" in text and "refused unless --force" in text
    inverted = dataclasses.replace(res, board=dataclasses.replace(res.board, inverted=True))
    assert "printed inverted (white pattern on black)" in report_text(inverted)


def test_a_board_all_over_the_arena_covers_the_floor(scenario):
    res, _ = _calibrate(scenario, covered=True)
    assert not [w for w in res.warnings if "of the floor" in w], res.warnings
    assert all(c.floor_views >= 10 and c.floor_region > 0.5 for c in res.coverage)


def _small_arena_poses(scenario, frames: int, reach: float, rng) -> np.ndarray:
    """Frame 0 on the floor, then every other view low (20-80 mm), the centre within reach."""
    board = scenario.BOARD
    centroid = np.array([board.size_mm[0] / 2, board.size_mm[1] / 2, 0.0])
    flat = np.diag([1.0, -1.0, -1.0])
    poses = np.tile(np.eye(4), (frames, 1, 1))
    for f in range(frames):
        R = flat if f == 0 else scenario.rodrigues(rng.normal(0, 0.45, 3)) @ flat
        lo, hi = (20.0, 80.0) if f % 2 else (150.0, 250.0)
        c = (
            np.zeros(3)
            if f == 0
            else np.array([*rng.uniform(-reach, reach, 2), rng.uniform(lo, hi)])
        )
        t = c - R @ centroid
        t[2] += max(0.0, 2.0 - (board.object_points @ R.T + t)[:, 2].min())
        poses[f, :3, :3], poses[f, :3, 3] = R, t
    return poses


def test_a_small_arena_covered_all_over_is_not_warned_about(scenario):
    # cameras 380 mm out around an arena of +-110 mm: the floor outside it, which the
    # cameras see but neither the board nor the animal reaches, is not asked for
    rng = np.random.default_rng(4)
    truth = scenario.fisheye_rig()
    dets = scenario.detections(truth, _small_arena_poses(scenario, 60, 40.0, rng), rng)
    opts = CalibrationOptions(origin_frame=0, jobs=1, progress=False)
    res = calibrate_detections(dets, scenario.BOARD, opts)
    assert not [w for w in res.warnings if "of the floor" in w], res.warnings
    assert all(c.floor_views >= 10 and c.floor_region > 0.5 for c in res.coverage)


def test_no_floor_no_floor_figures_and_the_region_share(scenario):
    res, _ = _calibrate(scenario, covered=True, origin=None)
    assert all(c.floor_views is None and c.floor_region is None for c in res.coverage)
    assert coverage_warnings(res.coverage) == []
    # the floor's image region: a camera whose corners all lie in one corner cell of the
    # image covers little of it, and is warned about although it saw the board on the floor
    res, _ = _calibrate(scenario, covered=True)
    d0, d1 = res.detections[:2]
    one = type(d0)(d0.name, d0.size, np.where(d0.mask[..., None], [5.0, 5.0], np.nan))
    rig = res.rig.subset([d0.name, d1.name])
    c0, c1 = board_coverage(
        [one, d1], rig, res.board_poses, scenario.BOARD.object_points, world_up(res.rig)
    )
    assert c0.floor_region < 0.1 < 0.5 < c1.floor_region
    (w,) = coverage_warnings([c0, c1])
    assert w.startswith(f"camera {d0.name}: ") and "of the floor's image region holds" in w

"""An up direction estimated from labels is stored only when they determine it.

Synthetic animals (``freipose.synth``) give the truth: world z. A few instants, or an
animal walking along one line, fix the up only loosely; the estimate says by how much and
``freipose calib up --from-labels`` refuses it instead of writing a wrong direction.
"""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

from freipose.cli.main import cli
from freipose.geometry.floor import estimate_up
from freipose.io.calibration import load_calibration, save_calibration
from freipose.io.calibration_world import WorldUpError, up_from_labels, world_up
from freipose.io.labels import LabelSet, SessionInfo, write_labels_h5
from freipose.synth import SceneConfig
from freipose.synth.scene import build_scene


def _scene(seed: int):
    scene = build_scene(SceneConfig(frames=400, seed=seed))
    return scene.rig, scene.geometry.keypoints  # (T, K, 3), world z up


def _angle_to_z(up: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(up[2], -1.0, 1.0))))


def test_eight_instants_along_a_walk_are_refused_many_are_kept():
    rig, kp = _scene(0)
    few = kp[150 + 6 * np.arange(8)]  # 8 instants of one walk along a line
    est = estimate_up(few, rig.centers)
    # the scatter alone looks like a plane, but the direction is far from the truth ...
    assert est.flatness < 0.5 and _angle_to_z(est.up) > 30
    # ... and the resampled instants say it is not determined
    assert est.instants == 8 and est.uncertainty_deg > 3
    with pytest.raises(WorldUpError, match=r"8 instants determine it only to within"):
        up_from_labels(rig, few)
    rig1, kp1 = _scene(1)
    many = up_from_labels(rig1, kp1)
    assert _angle_to_z(many.up) < 1.0 and "400 instants" in many.source
    rand8 = kp1[np.sort(np.random.default_rng(8).choice(len(kp1), 8, replace=False))]
    with pytest.raises(WorldUpError, match="label more instants"):
        up_from_labels(rig1, rand8)


def _labels(path, rig, pts):
    n, k = pts.shape[:2]
    write_labels_h5(
        LabelSet(
            session=np.array(["s"] * n),
            frame_index=np.arange(n),
            points2d=np.full((n, len(rig), k, 2), np.nan),
            points3d=pts,
            cameras=tuple(rig.names),
            keypoints=tuple(f"kp{i}" for i in range(k)),
            sessions={"s": SessionInfo(calibration=rig)},
        ),
        path,
    )
    return path


def test_calib_up_from_eight_labeled_instants_refuses_and_writes_nothing(tmp_path):
    rig, kp = _scene(0)
    cal = tmp_path / "calibration.toml"
    save_calibration(rig.__class__(rig.cameras, {}), cal)
    before = cal.read_bytes()
    labels = _labels(tmp_path / "labels.h5", rig, kp[150 + 6 * np.arange(8)])
    res = CliRunner().invoke(cli, ["calib", "up", str(cal), "--from-labels", str(labels)])
    assert res.exit_code != 0
    assert "degrees" in res.output and "--up X,Y,Z" in res.output
    assert "Traceback" not in res.output
    assert cal.read_bytes() == before
    labels = _labels(tmp_path / "many.h5", rig, _scene(1)[1])
    rig1 = _scene(1)[0]
    save_calibration(rig1.__class__(rig1.cameras, {}), cal)
    res = CliRunner().invoke(cli, ["calib", "up", str(cal), "--from-labels", str(labels)])
    assert res.exit_code == 0, res.output
    assert _angle_to_z(world_up(load_calibration(cal)).up) < 1.0

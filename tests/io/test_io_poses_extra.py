"""poses.h5's extra datasets are checked against the main arrays when a file is read."""

from __future__ import annotations

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from freipose.io.poses import PoseData, PosesFormatError, read_poses_h5, write_poses_h5
from freipose.skeleton import load_skeleton
from freipose.testing import make_circle_rig

T, K, C = 6, 12, 3


def _write(path, calibration=True, **extra):
    rng = np.random.default_rng(0)
    data = PoseData(
        poses=rng.normal(0, 50, (T, K, 3)),
        confidence=np.full((T, K), 0.9),
        keypoints=load_skeleton("rat").keypoints,
        frame_index=np.arange(T),
        fps=30.0,
        calibration=make_circle_rig(C) if calibration else None,
        extra={
            "points2d": rng.normal(300, 20, (T, C, K, 2)),
            "confidence2d": np.ones((T, C, K)),
            "center": np.zeros((T, 3)),
        },
    )
    write_poses_h5(data, path)
    with h5py.File(path, "a") as f:
        for name, arr in extra.items():
            del f[f"extra/{name}"]
            f[f"extra/{name}"] = arr


@pytest.mark.parametrize(
    "name, arr, message",
    [
        (
            "points2d",
            np.zeros((T, C, K - 2, 2)),
            r"\(T, C, K, 2\) = \(6, 3, 12, 2\); K=12 from the poses' keypoints",
        ),
        ("points2d", np.zeros((T, C + 1, K, 2)), r"C=3 from the calibration's cameras"),
        ("confidence2d", np.zeros((T, C, K, 1)), r"'confidence2d' has shape \(6, 3, 12, 1\)"),
        ("center", np.zeros((T - 1, 3)), r"T=6 from the poses' frames"),
    ],
)
def test_inconsistent_extra_is_named(tmp_path, name, arr, message):
    p = tmp_path / "bad.poses.h5"
    _write(p, **{name: arr})
    with pytest.raises(PosesFormatError, match=message) as e:
        read_poses_h5(p)
    assert str(e.value).startswith(f"{p}: extra dataset {name!r}")


def test_cameras_from_the_first_dataset_without_calibration(tmp_path):
    p = tmp_path / "nocal.poses.h5"
    _write(p, calibration=False, confidence2d=np.zeros((T, C - 1, K)))
    with pytest.raises(
        PosesFormatError,
        match=r"'points2d' has shape \(6, 3, 12, 2\).*C=2 from extra dataset 'confidence2d'",
    ):
        read_poses_h5(p)
    _write(p, calibration=False)
    assert read_poses_h5(p).extra["points2d"].shape == (T, C, K, 2)


def test_export_anipose_refuses_with_a_message(tmp_path):
    from freipose.cli.main import cli

    p = tmp_path / "bad.poses.h5"
    _write(p, points2d=np.zeros((T, C, K - 1, 2)))
    r = CliRunner().invoke(
        cli, ["export", str(p), "--format", "anipose", "-o", str(tmp_path / "a.csv")]
    )
    assert r.exit_code != 0 and "extra dataset 'points2d' has shape" in r.output, r.output
    assert "Traceback" not in r.output and not (tmp_path / "a.csv").exists()

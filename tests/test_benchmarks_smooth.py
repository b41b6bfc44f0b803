"""benchmarks/smooth.py: the smoother's targets, for the default and for ``--bones``."""

from __future__ import annotations

BENCHMARK = "smooth"  # the script the conftest fixture ``bench`` loads


def _figures(bench) -> dict:
    def err(median: float, mean: float, vel: float) -> dict:
        return {"median_jpe_mm": median, "mean_jpe_mm": mean, "velocity_error_mm_s": vel}

    return {
        "errors": {
            "raw": err(4.0, 5.0, 30.0),
            "smoothed": err(4.01, 5.02, 27.0),
            bench.BONES: err(3.95, 4.98, 17.0),
        },  # fmt: skip
        f"paw front right {bench.STIM_HZ:g} Hz amplitude mm": {
            "truth": 8.0,
            "raw": 7.0,
            "smoothed": 6.9,
            bench.BONES: 7.1,
        },  # fmt: skip
        "analysis": {"raw": {"balanced_accuracy": 0.75}, "smoothed": {"balanced_accuracy": 0.74}},
    }


def test_targets_of_each_estimate(bench, capsys):
    figures = _figures(bench)
    default = bench._targets(figures, 95.0)
    assert default == {
        "median JPE <= raw": False, "mean JPE <= raw": False,
        "velocity error <= 0.6 x raw": False,
        "5 Hz amplitude at least as close to the truth as raw": False,
        "2-sigma coverage with --validation in 90-98 %": True,
        "balanced accuracy >= raw - 0.02": True,
    }  # fmt: skip
    bones = bench._targets(figures, 95.0, bench.BONES)
    assert bones == {
        "median JPE <= raw": True, "mean JPE <= raw": True,
        "velocity error <= 0.6 x raw": True,
        "5 Hz amplitude at least as close to the truth as raw": True,
    }  # fmt: skip
    printed = capsys.readouterr().out
    assert "targets (smoothed):" in printed and f"targets ({bench.BONES}):" in printed


def test_bones_apply_only_with_single_keypoint_limbs(bench):
    import numpy as np

    from freipose.io.poses import PoseData
    from freipose.skeleton import Skeleton

    kp = ("head", "neck", "paw")
    poses = np.zeros((3, 3, 3), np.float32)

    def data(skeleton):
        return PoseData(poses=poses, confidence=np.ones((3, 3), np.float32), keypoints=kp,
                        frame_index=np.arange(3), fps=10.0, skeleton=skeleton)  # fmt: skip

    limb = Skeleton("toy", kp, limbs=(((0,), (1,)),))
    grouped = Skeleton("toy", kp, limbs=(((0, 1), (2,)),))  # a group's centre: no bone
    assert bench._has_bones(data(limb))
    assert not bench._has_bones(data(grouped)) and not bench._has_bones(data(None))

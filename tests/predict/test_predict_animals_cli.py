"""Two animals end to end on the command line: synth -> predict --animals 2 -> render,
export --format movement and analyze variables (with the social variables).

The scene is a rendered pair (4 cameras, 256x208, 40 frames at 6 fps, different coats);
the animals are found by background subtraction split into animals, followed with motion
and coat colour, and the shipped base model (trained on single rats, never on a pair)
predicts each one's cube. Measured here: median keypoint error 7.9 and 36.5 mm from the
animal each track follows, 161 and 107 mm from the other one, both animals predicted in
all 40 frames. The tracking's figures on longer and harder scenes are benchmarks/social.py's.
"""

from __future__ import annotations

from itertools import permutations
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from freipose.cli.main import cli

BASE = Path(__file__).parents[2] / "freipose" / "models" / "voxel_small.pt"
T = 40


def _run(args: list[str]) -> str:
    res = CliRunner().invoke(cli, ["-q", *args], catch_exceptions=False)
    assert res.exit_code == 0, res.output
    return res.output


@pytest.fixture(scope="module")
def pair(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(session folder, its predicted poses file)."""
    if not BASE.is_file():
        pytest.skip(f"the shipped base model {BASE} is not in this checkout")
    root = tmp_path_factory.mktemp("pair")
    session = root / "pair"
    _run(["synth", str(session), "--animals", "2", "--coat-mix", "different", "--frames",
          str(T), "--fps", "6", "--cameras", "4", "--size", "256x208", "--seed", "6"])  # fmt: skip
    _run(["predict", str(session), "--model", str(BASE), "--method", "bgsub", "--animals", "2",
          "-o", str(root / "poses"), "--device", "cpu", "--batch", "4", "--smooth"])  # fmt: skip
    return session, root / "poses" / "pair.poses.h5"


@pytest.mark.slow
def test_predicted_animals_are_each_near_their_own_truth(pair: tuple[Path, Path]) -> None:
    from freipose.io.poses import read_poses_h5

    session, path = pair
    d = read_poses_h5(path)
    truth = read_poses_h5(session / "true_poses.h5")
    assert d.individuals == ("animal_0", "animal_1")
    assert d.poses.shape == (T, 2, 12, 3) and d.keypoints == truth.keypoints
    assert d.identity_confidence is not None and d.identity_confidence.shape == (T, 2)
    assert d.extra["identity_flagged"].shape == (T, 2)
    assert d.extra["identity_flagged"].dtype == bool
    order = np.asarray(d.extra["identity_order"])  # the track each animal's pose came from
    assert order.shape == (T, 2) and (np.sort(order, 1) == [0, 1]).all()
    assert d.extra["center"].shape == (T, 2, 3) and d.extra["points2d"].shape == (T, 2, 4, 12, 2)
    assert d.provenance["animals"] == 2 and d.provenance["detection"] == "bgsub"
    assert (d.extra["status"] == 0).all()
    smoothed = read_poses_h5(path.parent / "smoothed" / path.name)  # --smooth: per animal
    assert smoothed.individuals == d.individuals and smoothed.poses.shape == d.poses.shape
    assert set(smoothed.provenance["smoother"]["animals"]) == set(d.individuals)
    found = np.isfinite(d.poses).all((2, 3))
    assert found.sum(0).min() >= 30, found.sum(0)
    ok = found & np.isfinite(d.identity_confidence)
    assert ((d.identity_confidence[ok] >= 0) & (d.identity_confidence[ok] <= 1)).all()
    # median error of each predicted animal (rows) from each true animal (columns)
    err = np.linalg.norm(d.poses[:, :, None] - truth.poses[:, None], axis=-1)  # (T, A, A, K)
    med = np.array([[np.nanmedian(err[:, a, b]) for b in range(2)] for a in range(2)])
    best = min(permutations(range(2)), key=lambda p: sum(med[a, p[a]] for a in range(2)))
    for a in range(2):
        own, other = med[a, best[a]], med[a, 1 - best[a]]
        print(f"animal_{a}: {own:.1f} mm from its animal, {other:.1f} mm from the other")
        assert own < 60.0, med
        assert other > 2.0 * own, med  # not the same animal twice


@pytest.mark.slow
def test_render_export_and_social_variables_take_the_animals(
    pair: tuple[Path, Path], tmp_path: Path
) -> None:
    from freipose.analysis.io import read_variables_h5
    from freipose.io.movement import read_movement
    from freipose.io.poses import read_poses_h5
    from freipose.io.video import FrameSource

    session, path = pair
    d = read_poses_h5(path)
    video = tmp_path / "overlay.mp4"
    _run(["render", str(session), str(path), "-o", str(video), "--tile-width", "160"])
    src = FrameSource(video)
    try:
        assert src.num_frames == T
    finally:
        src.close()

    nc = tmp_path / "pair.nc"
    _run(["export", str(path), "--format", "movement", "-o", str(nc)])
    m = read_movement(nc)
    assert tuple(m.individuals) == d.individuals
    np.testing.assert_allclose(m.poses, d.poses, equal_nan=True)

    out = tmp_path / "pair.vars.h5"
    _run(["analyze", "variables", str(path), "-o", str(out)])
    var = read_variables_h5(out)
    assert var.info["individuals"] == ["animal_0", "animal_1"]
    assert len(var.names) % 2 == 0
    half = len(var.names) // 2
    assert all(n.startswith("animal_0/") for n in var.names[:half])
    assert all(n.startswith("animal_1/") for n in var.names[half:])
    centre = var.names.index("animal_0/social_dist[centre-centre of animal_1]")
    got = var.values[:, centre]
    assert np.isfinite(got).all()
    c = d.poses.astype(np.float64).mean(2)  # every frame predicted: no gap to fill
    np.testing.assert_allclose(got, np.linalg.norm(c[:, 0] - c[:, 1], axis=-1), rtol=1e-5)
    contact = var.values[:, var.names.index("animal_1/contact[animal_0]")]
    assert set(np.unique(contact)) <= {0.0, 1.0}
    facing = var.values[:, var.names.index("animal_0/facing[animal_1]")]
    assert np.isfinite(facing).all() and ((facing >= 0) & (facing <= 180)).all()


@pytest.mark.parametrize(
    ("extra", "says"),
    [
        (["--method", "bgsub", "--shard", "0/2"], "--shard"),
        (["--method", "bgsub", "--executor", "local"], "--executor"),
        (["--method", "fixed", "--fixed-boxes", "BOXES"], "--method fixed"),
    ],
)
def test_several_animals_refuse_options_they_do_not_take(
    tmp_path: Path, extra: list[str], says: str
) -> None:
    from predict_helpers import make_session

    if not BASE.is_file():
        pytest.skip(f"the shipped base model {BASE} is not in this checkout")
    make_session(tmp_path / "rec", n_frames=4)
    boxes = tmp_path / "boxes.toml"
    boxes.write_text("[boxes]\n" + "".join(f"cam{i} = [0, 0, 50, 50]\n" for i in range(4)))
    extra = [str(boxes) if e == "BOXES" else e for e in extra]
    args = ["predict", str(tmp_path / "rec"), "--model", str(BASE), "--animals", "2",
            "-o", str(tmp_path / "out"), *extra]  # fmt: skip
    res = CliRunner().invoke(cli, args)
    assert res.exit_code != 0
    assert says in res.output and "Traceback" not in res.output, res.output
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())

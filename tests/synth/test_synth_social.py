"""Synthetic social scenes: several animals, their truth, visibility and label files."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

from freipose.cli.main import cli
from freipose.io.labels import read_labels_h5
from freipose.io.poses import read_poses_h5
from freipose.synth import SceneConfig
from freipose.synth.body import PART_NAMES, RatBody
from freipose.synth.errors import SynthError
from freipose.synth.scene import build_scene
from freipose.synth.social import simulate_social
from freipose.synth.social_scene import animal_views


def test_two_rats_meet_cross_and_climb():
    bodies = [RatBody.random(np.random.default_rng(i)) for i in range(2)]
    rngs = [np.random.default_rng(10 + i) for i in range(2)]
    m = simulate_social(3000, 50.0, rngs, np.random.default_rng(6), bodies)
    touch = m.contact[:, 0, 1]
    assert m.contact[:, 1, 0].tolist() == touch.tolist()
    assert 0.05 < touch.mean() < 0.9  # they meet, and part again
    climbing = m.on_top_of >= 0
    assert climbing.any()
    assert np.all(m.lift[~climbing] <= m.lift.max() * 0.5 + 1e-9)  # raised only near a climb
    assert m.lift.max() > 40  # on the other's back
    # apart from climbs the bodies do not sink into each other: torso centres stay apart
    d = np.linalg.norm(m.states[0].root_xy - m.states[1].root_xy, axis=1)
    free = ~climbing.any(1)
    assert np.min(d[free]) > 45


def test_social_scene_needs_a_valid_count():
    with pytest.raises(SynthError, match="animals"):
        SceneConfig(animals=5)
    with pytest.raises(SynthError, match="animal_scales"):
        SceneConfig(animals=2, animal_scales=(1.0,))
    assert "animals" not in SceneConfig().to_dict()  # one animal: scene.toml as it was


@pytest.fixture(scope="module")
def scene():
    cfg = SceneConfig(animals=2, frames=400, n_cameras=4, seed=6, coat_mix="different")
    return build_scene(cfg)


def test_hidden_by_another_animal_agrees_with_the_renderer(scene):
    """Where the visibility test says another animal hides a keypoint, the rendered pixel
    shows a body in front of it (not the keypoint's own parts); where it says the keypoint
    is visible, the pixels around it show its own animal (tips lie on the silhouette)."""
    from freipose.synth.body import KEYPOINT_OWNERS
    from freipose.synth.render import CameraRenderer

    views = animal_views(scene.geometry, scene.rig, scene.arena, 2)
    T, C, A, K = views.visible.shape
    assert A == 2 and len(scene.bodies) == 2
    assert scene.bodies[0].appearance != scene.bodies[1].appearance
    hidden = views.hidden_by_other
    assert hidden.any(), "the scene has no occlusion between the animals"
    t = int(np.argmax(hidden.sum((1, 2, 3))))
    n_parts = len(PART_NAMES)
    agree = total = 0
    for c, cam in enumerate(scene.rig):
        r = CameraRenderer(cam, scene.arena, seed=c)
        box, _, pid = r.render_animal(scene.geometry, t, scene.palette)
        x0, y0, x1, y1 = box
        for a in range(A):
            for k in range(K):
                u, v = np.round(views.points2d[t, c, a, k]).astype(int)
                if not (x0 <= u < x1 and y0 <= v < y1):
                    continue
                seen = pid[v - y0, u - x0]
                near = pid[max(0, v - y0 - 1) : v - y0 + 2, max(0, u - x0 - 1) : u - x0 + 2]
                owners = [i + a * n_parts for i in KEYPOINT_OWNERS[k]]
                if hidden[t, c, a, k]:
                    total += 1
                    agree += bool(seen >= 0 and seen not in owners)
                elif views.visible[t, c, a, k]:
                    total += 1
                    agree += bool(np.any((near >= 0) & (near // n_parts == a)))
    assert total > 20 and agree / total > 0.95, (agree, total)


def test_social_session_truth_labels_and_label_files(tmp_path):
    out = tmp_path / "pair"
    r = CliRunner().invoke(
        cli,
        ["synth", str(out), "--animals", "2", "--frames", "12", "--cameras", "3", "--size",
         "160x128", "--seed", "2", "--label-files", "sleap,dlc,sleap-session",
         "--label-noise", "0.5"],
    )  # fmt: skip
    assert r.exit_code == 0, r.output
    truth = read_poses_h5(out / "true_poses.h5")
    assert truth.individuals == ("animal0", "animal1") and truth.poses.shape == (12, 2, 12, 3)
    assert truth.extra["visible2d"].shape == (12, 2, 3, 12)
    lab = read_labels_h5(out / "labels.h5")
    assert len(lab) == 24 and lab.individuals == ("animal0", "animal1")
    np.testing.assert_array_equal(lab.frame_index, np.repeat(np.arange(12), 2))
    np.testing.assert_array_equal(
        lab.points3d.reshape(12, 2, 12, 3).astype(np.float32), truth.poses
    )
    # the label files import back with each animal's identity
    cal = str(out / "true_calibration.toml")
    pred = ["--instances", "predicted"]
    for fmt, src, extra in (
        ("sleap", [out / c / f"{c}.slp" for c in ("cam0", "cam1", "cam2")],
         ["--calibration", cal, *pred]),
        ("dlc", [out], ["--calibration", cal]),
        ("sleap", [out / "pair.slp"], pred),  # the multi-camera file: its cameras and groups
    ):  # fmt: skip
        dst = tmp_path / f"{fmt}_{src[0].name}.h5"
        r = CliRunner().invoke(
            cli, ["labels", "import", "--format", fmt, *map(str, src), "-o", str(dst), *extra]
        )
        assert r.exit_code == 0, r.output
        assert "animal1: reprojection error" in r.output, (fmt, src)
        got = read_labels_h5(dst)
        assert set(got.individuals) == {"animal0", "animal1"}
        for i in range(len(got)):
            a = truth.individuals.index(got.individual[i])
            true = truth.poses[got.frame_index[i]]  # (A, K, 3)
            err = np.nanmedian(np.linalg.norm(got.points3d[i] - true[a], axis=-1))
            swapped = np.nanmedian(np.linalg.norm(got.points3d[i] - true[1 - a], axis=-1))
            assert err < 15.0 and err < swapped / 3, (fmt, i, err, swapped)  # 0.5 px noise
    text = (out / "config.yaml").read_text()
    assert "multianimalproject: true" in text and '- "animal1"' in text
    # scene.toml reproduces the scene
    r = CliRunner().invoke(cli, ["synth", str(tmp_path / "again"), "--config",
                                 str(out / "scene.toml")])  # fmt: skip
    assert r.exit_code == 0, r.output
    again = read_poses_h5(tmp_path / "again" / "true_poses.h5")
    np.testing.assert_array_equal(again.poses, truth.poses)


def test_labels_of_two_animals_export_to_dlc_and_back(tmp_path):
    sess = tmp_path / "duo"
    r = CliRunner().invoke(
        cli,
        ["synth", str(sess), "--animals", "2", "--frames", "5", "--cameras", "2", "--size",
         "96x80", "--seed", "3"],
    )  # fmt: skip
    assert r.exit_code == 0, r.output
    lab = read_labels_h5(sess / "labels.h5")
    out = tmp_path / "dlc"
    r = CliRunner().invoke(
        cli, ["labels", "export", str(sess / "labels.h5"), "--format", "dlc", "-o", str(out)]
    )
    assert r.exit_code == 0, r.output
    head = next(out.glob("labeled-data/*/CollectedData_*.csv")).read_text().splitlines()[1]
    assert head.startswith("individuals,animal0")
    back = tmp_path / "back.h5"
    r = CliRunner().invoke(
        cli, ["labels", "import", "--format", "dlc", str(out), "--calibration",
              str(sess / "true_calibration.toml"), "-o", str(back)],
    )  # fmt: skip
    assert r.exit_code == 0, r.output
    got = read_labels_h5(back)
    assert len(got) == len(lab) and got.individuals == lab.individuals
    for i in range(len(got)):
        j = np.flatnonzero((lab.frame_index == got.frame_index[i])
                           & (lab.individual == got.individual[i]))  # fmt: skip
        assert len(j) == 1
        cams = [lab.cameras.index(c) for c in got.cameras]
        np.testing.assert_array_equal(got.points2d[i], lab.points2d[j[0]][cams])


def test_one_animal_sleap_session_has_no_individuals(tmp_path):
    out = tmp_path / "solo"
    r = CliRunner().invoke(
        cli,
        ["synth", str(out), "--frames", "4", "--cameras", "2", "--size", "96x80",
         "--label-files", "sleap-session"],
    )  # fmt: skip
    assert r.exit_code == 0, r.output
    dst = tmp_path / "solo.h5"
    r = CliRunner().invoke(
        cli, ["labels", "import", "--format", "sleap", str(out / "solo.slp"), "--instances",
              "predicted", "-o", str(dst)],
    )  # fmt: skip
    assert r.exit_code == 0, r.output
    got = read_labels_h5(dst)
    assert got.individual is None and len(got) == 4
    truth = read_labels_h5(out / "labels.h5")
    err = np.linalg.norm(got.points3d - truth.points3d, axis=-1)
    assert np.nanmedian(err) < 15.0

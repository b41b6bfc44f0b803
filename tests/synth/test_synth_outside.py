"""A coat and a rig layout outside the base models' training data: piebald, arc."""

from __future__ import annotations

import numpy as np
from click.testing import CliRunner

from freipose._compat import tomllib
from freipose.cli.main import cli
from freipose.geometry import project
from freipose.synth import RatBody, SceneConfig, build_body, default_rig, simulate_motion
from freipose.synth.body import PIEBALD_MATERIAL
from freipose.synth.coats import FURRY
from freipose.synth.render import CameraRenderer
from freipose.synth.rig import ArenaConfig, Camera


def _still(body: RatBody):
    """One frame of ``body`` standing at the arena centre."""
    return simulate_motion(1, 50.0, np.random.default_rng(0), body, start=(0, 0, 0))


def _fur_pixels(appearance: str) -> np.ndarray:
    """(n,) brightness (linear, 0..1) of the furry pixels of one top view of the animal."""
    body = RatBody(appearance=appearance)
    geom = build_body(body, _still(body))
    cam = Camera.look_at("top", (0, 0, 700), (0, 0, 0), (160, 160), 600.0, up=(0, 1, 0))
    r = CameraRenderer(cam, ArenaConfig(), seed=0)
    _, rgb, pid = r.render_animal(geom, 0, body.palette)
    fur = np.isin(geom.materials[np.maximum(pid, 0)], FURRY) & (pid >= 0)
    assert fur.sum() > 500
    return rgb[fur].mean(-1)


def test_piebald_coat_is_white_fur_with_dark_patches():
    pie, albino, dark = (_fur_pixels(a) for a in ("piebald", "albino", "dark"))
    black, white = pie < 0.15, pie > 0.45
    assert 0.12 < black.mean() < 0.7 and white.mean() > 0.25  # patches on white
    assert (albino < 0.15).mean() < 0.02 and (dark > 0.45).mean() < 0.02  # one colour each
    body = RatBody(appearance="piebald")
    np.testing.assert_array_equal(build_body(body, _still(body)).materials, PIEBALD_MATERIAL)


def test_random_coats_and_randomize_never_draw_piebald_or_arc():
    rng = np.random.default_rng(1)
    coats = {RatBody.random(rng).appearance for _ in range(200)}
    coats |= {RatBody.random(rng, coats=("dark", "albino")).appearance for _ in range(50)}
    drawn = [SceneConfig(seed=s, frames=2, randomize=True).resolved() for s in range(60)]
    assert "piebald" not in coats | {d.appearance for d in drawn}
    assert "arc" not in {d.layout for d in drawn}


def test_arc_layout_puts_every_camera_on_one_side_seeing_the_arena():
    arena = ArenaConfig()
    for seed in (None, 3, 11):
        rig = default_rig(6, (320, 256), seed=seed, arena=arena, layout="arc")
        centres = np.array([c.center for c in rig])
        assert (centres[:, 0] > 100).all()  # all on the +x side of the arena
        assert np.ptp(np.degrees(np.arctan2(centres[:, 1], centres[:, 0]))) > 120
        assert centres[:, 2].min() < 550 < centres[:, 2].max()  # low and high
        for cam in rig:
            uv = project(arena.corners(0.0), cam)
            assert np.all((uv >= -0.5) & (uv <= np.array(cam.size) - 0.5))


def test_synth_command_renders_a_piebald_rat_on_an_arc_rig(tmp_path):
    out = tmp_path / "s"
    args = ["synth", str(out), "--cameras", "3", "--frames", "2", "--size", "96x80"]
    args += ["--appearance", "piebald", "--layout", "arc", "--seed", "4"]
    res = CliRunner().invoke(cli, args)
    assert res.exit_code == 0, res.output
    scene = tomllib.loads((out / "scene.toml").read_text())
    assert scene["scene"]["appearance"] == "piebald" and scene["scene"]["layout"] == "arc"
    assert scene["derived"]["animal"]["appearance"] == "piebald"

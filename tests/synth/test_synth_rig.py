"""Camera rigs: the default lab rig and validated rig files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from freipose.geometry import project
from freipose.synth import ArenaConfig, RigFileError, default_rig, load_rig_file

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "rig.toml"


@pytest.mark.parametrize("n", [1, 3, 7, 12])
def test_default_rig_sees_the_arena(n):
    rig = default_rig(n, (320, 256), seed=5)
    assert len(rig) == n and rig.names[0] == "cam0"
    arena = ArenaConfig()
    for cam in rig:
        assert cam.center[2] > 400  # above the arena
        uv = project(arena.corners(0.0), cam)
        assert np.all(np.isfinite(uv))
        assert np.all((uv >= -0.5) & (uv <= np.array(cam.size) - 0.5))  # whole floor in view
        assert cam.has_distortion


def test_default_rig_nominal_and_jittered():
    a = default_rig(7, (320, 256))
    b = default_rig(7, (320, 256))
    c = default_rig(7, (320, 256), seed=1)
    assert a.allclose(b) and not a.allclose(c)
    assert default_rig(7, (320, 256), seed=1).allclose(c)


def test_example_rig_file():
    rig, arena = load_rig_file(EXAMPLE, with_arena=True)
    assert len(rig) == 7 and rig.names[-1] == "top"
    assert rig["cam5"].size == (1280, 1024) and rig["cam5"].K[0, 0] == 1150.0
    np.testing.assert_allclose(rig["cam3"].K[0, 0], 320 / np.tan(np.radians(30)))
    np.testing.assert_allclose(rig["cam0"].center, [676.6, 246.3, 620.0])
    assert arena.size == (600.0, 600.0)
    for cam in rig:  # every camera looks at the arena centre
        uv = project(np.zeros(3), cam)
        assert np.all(np.abs(uv - (np.array(cam.size) - 1) / 2) < 0.2 * np.array(cam.size))


def _write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "rig.toml"
    p.write_text(text)
    return p


CAM = '[[camera]]\nname = "a"\nposition = [600.0, 0.0, 600.0]\nlook_at = [0.0, 0.0, 0.0]\n'


@pytest.mark.parametrize(
    "text, message",
    [
        ("", "no cameras"),
        ("[[camera]\n", "not valid TOML"),
        (CAM.replace("look_at", "lookat"), "did you mean 'look_at'"),
        (CAM.replace("look_at = [0.0, 0.0, 0.0]\n", ""), "has no 'look_at'"),
        (CAM + CAM, "used twice"),
        (CAM.replace("600.0]", "-5.0]"), "below the floor"),
        (
            CAM.replace("[600.0, 0.0, 600.0]", "[600.0, 0.0]"),
            "position must be a list of 3 numbers",
        ),
        (CAM + "size = [640.5, 480]\n", "two integers"),
        (CAM + "focal = -3\n", "focal must be a positive number"),
        (CAM + "focal = 500\nfov_deg = 40\n", "not both"),
        (CAM + "distortion = [0.1, 0.2]\n", "distortion"),
        (CAM.replace("[0.0, 0.0, 0.0]", "[600.0, 0.0, 600.0]"), "coincide"),
        (CAM.replace("[0.0, 0.0, 0.0]", "[1200.0, 0.0, 700.0]"), "behind the camera"),
        ("[arena]\nsize = [100, 100]\n" + CAM, "at least 150"),
        ("[defaults]\nsizes = [1, 2]\n" + CAM, "did you mean 'size'"),
    ],
)
def test_rig_file_errors(tmp_path, text, message):
    with pytest.raises(RigFileError, match=message):
        load_rig_file(_write(tmp_path, text), default_size=(320, 256))


def test_rig_file_missing_and_needs_size(tmp_path):
    with pytest.raises(FileNotFoundError):
        load_rig_file(tmp_path / "nope.toml")
    with pytest.raises(RigFileError, match="has no size"):
        load_rig_file(_write(tmp_path, CAM))
    rig = load_rig_file(_write(tmp_path, CAM), default_size=(320, 256))
    assert rig["a"].size == (320, 256)

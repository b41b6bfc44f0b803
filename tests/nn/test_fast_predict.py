"""``freipose predict --backend``: the optimized and the eager backend write the same poses.

The shipped base model predicts a rendered synthetic session through the command, once per
backend; the poses agree within 0.1 mm and the provenance names the backend.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from freipose.cli.main import cli
from freipose.io.labels import read_labels_h5
from freipose.io.poses import read_poses_h5

BASE = Path(__file__).parents[2] / "freipose" / "models" / "voxel_small.pt"


@pytest.fixture(scope="module")
def session(tmp_path_factory: pytest.TempPathFactory):
    """A rendered session and a fixed-boxes file around the rat in every camera."""
    from freipose.synth import SceneConfig, generate_session

    if not BASE.is_file():
        pytest.skip(f"the shipped base model {BASE} is not in this checkout")
    root = tmp_path_factory.mktemp("fastpredict")
    paths = generate_session(
        root / "rec", SceneConfig(n_cameras=4, frames=8, size=(320, 256), seed=5), progress=False
    )
    labels = read_labels_h5(paths.labels)
    lines = ["[boxes]"]
    for c, cam in enumerate(labels.cameras):
        uv = labels.points2d[:, c].reshape(-1, 2)
        lo, hi = np.nanmin(uv, 0) - 25, np.nanmax(uv, 0) + 25
        lines.append(f"{cam} = [{lo[0]:.0f}, {lo[1]:.0f}, {hi[0]:.0f}, {hi[1]:.0f}]")
    boxes = root / "boxes.toml"
    boxes.write_text("\n".join(lines) + "\n")
    return paths, boxes


def _predict(session, out: Path, backend: str):
    paths, boxes = session
    args = ["predict", str(paths.folder), "--model", str(BASE), "--calibration",
            str(paths.calibration), "--method", "fixed", "--fixed-boxes", str(boxes),
            "-o", str(out), "--device", "cpu", "--batch", "4", "--backend", backend]  # fmt: skip
    res = CliRunner().invoke(cli, args, catch_exceptions=False)
    assert res.exit_code == 0, res.output
    (path,) = out.glob("*.poses.h5")
    return read_poses_h5(path)


def test_predict_backends_agree(session, tmp_path: Path) -> None:
    eager = _predict(session, tmp_path / "eager", "eager")
    fast = _predict(session, tmp_path / "fast", "auto")
    assert eager.provenance["backend"] == "eager"
    assert fast.provenance["backend"] == "optimized"
    assert np.isfinite(eager.poses).all()
    d = np.linalg.norm(fast.poses - eager.poses, axis=-1)
    assert d.max() < 0.1, f"{d.max():.4f} mm"


def test_predict_refuses_unknown_backend(session, tmp_path: Path) -> None:
    paths, _ = session
    res = CliRunner().invoke(
        cli, ["predict", str(paths.folder), "--model", str(BASE), "-o", str(tmp_path),
              "--backend", "fastest"],
    )  # fmt: skip
    assert res.exit_code != 0
    assert "fastest" in res.output and "optimized" in res.output


def _cpu_bf16_units(monkeypatch: pytest.MonkeyPatch, present: bool) -> None:
    """Make PyTorch report a CPU with (or without) AVX-512-BF16 and AMX units."""
    import torch

    for probe in ("_is_avx512_bf16_supported", "_is_amx_tile_supported"):
        monkeypatch.setattr(torch.cpu, probe, lambda: present, raising=False)


def test_predict_refuses_bf16_on_a_cpu_without_bf16_units(
    session, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Emulated bfloat16 is many times slower than fp32: one clear message, nothing written."""
    _cpu_bf16_units(monkeypatch, False)
    paths, boxes = session
    args = ["predict", str(paths.folder), "--model", str(BASE), "--calibration",
            str(paths.calibration), "--method", "fixed", "--fixed-boxes", str(boxes),
            "-o", str(tmp_path / "out"), "--device", "cpu", "--backend", "bf16"]  # fmt: skip
    res = CliRunner().invoke(cli, args)
    assert res.exit_code != 0
    assert "Traceback" not in res.output
    assert "--backend bf16 needs bfloat16 units" in res.output
    assert "this CPU (" in res.output and "--backend auto" in res.output
    assert not list((tmp_path / "out").glob("*.poses.h5"))


def test_load_model_takes_bf16_on_a_cpu_with_bf16_units(monkeypatch: pytest.MonkeyPatch) -> None:
    from freipose.nn.fast import backend_of
    from freipose.predict.network import load_model

    if not BASE.is_file():
        pytest.skip(f"the shipped base model {BASE} is not in this checkout")
    _cpu_bf16_units(monkeypatch, True)
    net, _, _, _ = load_model(BASE, "cpu", None, "bf16")
    assert backend_of(net) == "bf16"

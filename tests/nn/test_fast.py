"""The optimized backend (freipose.nn.fast) against the eager reference.

The exactness guard: on the shipped trained base model and rendered frames of the synthetic
rat, ``optimized`` gives the eager poses within 0.1 mm and ``bf16`` within the bound stated
in docs/explanation/backends.md.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from freipose.nn.fast import backend_of, optimize, resolve_backend
from freipose.nn.geometry import voxel_axis, voxel_offsets
from freipose.nn.layers import Conv3d
from freipose.nn.unprojection import unproject, unproject_gather

BASE = Path(__file__).parents[2] / "freipose" / "models" / "voxel_small.pt"
# bf16 bound of docs/explanation/backends.md (P1 against fp32 eager, rendered rat frames)
BF16_MEDIAN_MM = 0.25
BF16_P90_MM = 0.5


def _rotation_z(angle: float) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _cameras(B: int, V: int, S: int, gen: torch.Generator):
    """Crop cameras looking at the origin from a ring, with distortion and an affine K."""
    K = torch.zeros(B, V, 3, 3)
    K[..., 0, 0], K[..., 1, 1], K[..., 0, 1] = 1.2 * S, 1.1 * S, 3.0
    K[..., 0, 2], K[..., 1, 2], K[..., 2, 2] = S / 2 - 2, S / 2 + 1, 1.0
    R = torch.zeros(B, V, 3, 3)
    for v in range(V):
        a = 2 * math.pi * v / V
        # camera at distance 800 on a ring, looking at the origin (z forward)
        fwd = torch.tensor([-math.cos(a), -math.sin(a), 0.0])
        right = torch.tensor([-math.sin(a), math.cos(a), 0.0])
        down = torch.linalg.cross(fwd, right)
        R[:, v] = torch.stack([right, down, fwd])
    t = torch.tensor([0.0, 0.0, 800.0]).expand(B, V, 3).clone()
    dist = 0.05 * torch.randn(B, V, 5, generator=gen)
    return K, R, t, dist


def test_gather_unprojection_equals_grid_sample() -> None:
    """Same volume, count and feature gradient as unproject (distortion, grid rotation,
    a padding view, voxels outside some crops)."""
    gen = torch.Generator().manual_seed(0)
    B, V, C, h, S, G, cube = 2, 3, 5, 12, 48, 6, 1000.0
    K, R, t, dist = _cameras(B, V, S, gen)
    mask = torch.ones(B, V, dtype=torch.bool)
    mask[1, 2] = False
    center = 20 * torch.randn(B, 3, generator=gen)
    rot = torch.stack([_rotation_z(0.0), _rotation_z(0.7)])
    points = center[:, None] + voxel_offsets(G, cube)[None] @ rot.mT
    grid = (center, rot, voxel_axis(G, cube))
    feats = torch.randn(B, V, C, h, h, generator=gen)
    f1, f2 = feats.clone().requires_grad_(), feats.clone().requires_grad_()
    ref, count_ref = unproject(f1, K, R, t, dist, mask, points, S)
    got, count = unproject_gather(f2, K, R, t, dist, mask, grid, S)
    assert torch.equal(count, count_ref)
    assert 0 < float((count == 0).float().mean()) < 1  # some voxels outside every crop
    scale = float(ref.detach().abs().max())
    assert float((got - ref).abs().max()) <= 1e-4 * scale
    w = torch.randn(ref.shape, generator=gen)
    (ref * w).sum().backward()
    (got * w).sum().backward()
    assert f1.grad is not None and f2.grad is not None
    assert float((f2.grad - f1.grad).abs().max()) <= 1e-4 * float(f1.grad.abs().max())


def test_pointwise_conv3d_channels_last_equals_conv() -> None:
    gen = torch.Generator().manual_seed(1)
    conv = Conv3d(6, 4, 1)
    x = torch.randn(2, 6, 5, 4, 3, generator=gen)
    ref = conv(x)
    got = conv(x.contiguous(memory_format=torch.channels_last_3d))
    assert got.is_contiguous(memory_format=torch.channels_last_3d)
    torch.testing.assert_close(got, ref)


def test_backend_names() -> None:
    assert resolve_backend("auto") == "optimized"
    with pytest.raises(ValueError, match="backend must be one of"):
        resolve_backend("fastest")


@pytest.fixture(scope="module")
def rendered(tmp_path_factory: pytest.TempPathFactory):
    """Rendered frames of the synthetic rat (4 cameras) and their labels."""
    from freipose.nn.dataset import MultiViewDataset
    from freipose.synth import SceneConfig, generate_session

    if not BASE.is_file():
        pytest.skip(f"the shipped base model {BASE} is not in this checkout")
    out = tmp_path_factory.mktemp("fast") / "s"
    paths = generate_session(
        out, SceneConfig(n_cameras=4, frames=12, size=(320, 256), seed=3), progress=False
    )
    return MultiViewDataset(paths.labels)


def _predict(backend: str, source) -> dict[str, np.ndarray]:
    from freipose.nn.checkpoint import load_checkpoint
    from freipose.nn.evaluate import predict_dataset

    torch.manual_seed(0)
    model, _, _ = load_checkpoint(BASE)
    optimize(model, backend)
    assert backend_of(model) == resolve_backend(backend)
    return predict_dataset(model, source, batch_size=4)


def test_optimized_poses_equal_eager_on_trained_model(rendered) -> None:
    """The exactness guard: the same P0 and P1 within 0.1 mm (fp32), every keypoint."""
    ref = _predict("eager", rendered)
    got = _predict("optimized", rendered)
    for key in ("P0", "P1"):
        d = np.linalg.norm(got[key] - ref[key], axis=-1)
        assert np.isfinite(d).all()
        assert d.max() < 0.1, f"{key}: {d.max():.4f} mm"
    # the poses are real predictions, not a degenerate output
    assert np.nanmedian(np.linalg.norm(ref["P1"] - ref["gt"], axis=-1)) < 15.0


def test_bf16_poses_within_stated_bound(rendered) -> None:
    ref = _predict("eager", rendered)
    got = _predict("bf16", rendered)
    d = np.linalg.norm(got["P1"] - ref["P1"], axis=-1)
    assert np.median(d) < BF16_MEDIAN_MM, f"median {np.median(d):.3f} mm"
    assert np.percentile(d, 90) < BF16_P90_MM, f"90th percentile {np.percentile(d, 90):.3f} mm"


@pytest.mark.gpu
def test_cuda_optimized_poses_within_bf16_bound(rendered) -> None:
    """The GPU path (bf16 autocast, channels-last, gather) against fp32 eager on the CPU."""
    from freipose.nn.checkpoint import load_checkpoint
    from freipose.nn.evaluate import predict_dataset

    ref = _predict("eager", rendered)
    model, _, _ = load_checkpoint(BASE, "cuda")
    got = predict_dataset(optimize(model, "optimized"), rendered, batch_size=4)
    d = np.linalg.norm(got["P1"] - ref["P1"], axis=-1)
    assert np.median(d) < BF16_MEDIAN_MM, f"median {np.median(d):.3f} mm"
    assert np.percentile(d, 90) < BF16_P90_MM, f"90th percentile {np.percentile(d, 90):.3f} mm"


@pytest.mark.parametrize("avx512_bf16, amx, native", [(False, False, False), (True, False, True),
                                                      (False, True, True)])  # fmt: skip
def test_bf16_support_of_the_cpu_follows_its_units(monkeypatch, avx512_bf16, amx, native) -> None:
    from freipose.nn.fast import bf16_support

    monkeypatch.setattr(torch.cpu, "_is_avx512_bf16_supported", lambda: avx512_bf16)
    monkeypatch.setattr(torch.cpu, "_is_amx_tile_supported", lambda: amx)
    got, what = bf16_support("cpu")
    assert got is native
    assert what == f"this CPU ({torch.backends.cpu.get_cpu_capability()})"


def test_bf16_support_without_the_probes_trusts_the_user(monkeypatch) -> None:
    from freipose.nn.fast import bf16_support

    monkeypatch.delattr(torch.cpu, "_is_avx512_bf16_supported", raising=False)
    monkeypatch.delattr(torch.cpu, "_is_amx_tile_supported", raising=False)
    assert bf16_support("cpu")[0] is True


def test_inference_autocast_on_the_cpu_only_for_the_bf16_backend() -> None:
    from freipose.nn.fast import inference_autocast

    net = torch.nn.Linear(2, 2)
    cpu = torch.device("cpu")
    for backend, expected in (("optimized", False), ("eager", False), ("bf16", True)):
        optimize(net, backend)
        with inference_autocast(net, cpu):
            assert torch.is_autocast_enabled("cpu") is expected, backend

"""Inference and training backends of the pose networks: the reference and the optimized path.

``eager`` runs the networks as written (:mod:`freipose.nn.model`, contiguous NCHW tensors,
``grid_sample`` unprojection): the reference. ``optimized`` runs the same weights with

* channels-last memory layout of every 2D map (``torch.channels_last``) and of the voxel
  volumes (``torch.channels_last_3d``), the layout oneDNN's convolutions work in, so that no
  convolution reorders its input or output;
* the unprojection as one weighted gather of feature rows
  (:func:`freipose.nn.unprojection.unproject_gather`): its sampling plan is computed once per batch
  from the cameras and the grid (each voxel's camera coordinates a sum of one term per grid
  axis) and the mean over the views is a single ``embedding_bag``, which writes the volume
  directly in the channels-last layout of the 3D U-Net;

and gives the same poses within fp32 rounding (``tests/nn/test_fast.py``). ``bf16`` is
``optimized`` under bfloat16 autocast (convolutions in bfloat16: AMX / AVX-512-BF16 on CPUs
that have them, tensor cores on GPUs; the geometry, soft-argmax and triangulation stay fp32),
the path a GPU with bfloat16 units runs; its poses differ from fp32 by a bound stated in
docs/explanation/backends.md and checked by the tests. ``auto`` is ``optimized``. A device
without bfloat16 units (:func:`bf16_support`: a CPU without AVX-512-BF16 or AMX, a GPU
older than compute capability 8.0) emulates bfloat16 many times slower than fp32, so there
nothing runs in bfloat16 by default and ``freipose predict`` refuses ``--backend bf16``.

:func:`optimize` applies a backend to a network in place (its weights keep their values and
their state-dict names); :func:`inference_autocast` is the autocast context of a backend on a
device.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import torch
from torch import nn

BACKENDS = ("auto", "eager", "optimized", "bf16")


def resolve_backend(backend: str) -> str:
    """The backend a name stands for (``auto`` -> ``optimized``).

    Args:
        backend: one of :data:`BACKENDS`.

    Returns:
        ``eager``, ``optimized`` or ``bf16``.

    Raises:
        ValueError: an unknown name.
    """
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {', '.join(BACKENDS)}, got {backend!r}")
    return "optimized" if backend == "auto" else backend


def _to_layout(module: nn.Module, channels_last: bool) -> None:
    """Convolution weights of ``module`` in channels-last (True) or contiguous layout."""
    for m in module.modules():
        if isinstance(m, nn.Conv2d | nn.ConvTranspose2d):
            fmt = torch.channels_last if channels_last else torch.contiguous_format
        elif isinstance(m, nn.Conv3d | nn.ConvTranspose3d):
            fmt = torch.channels_last_3d if channels_last else torch.contiguous_format
        else:
            continue
        with torch.no_grad():
            m.weight.data = m.weight.data.contiguous(memory_format=fmt)


def optimize(model: nn.Module, backend: str = "auto") -> nn.Module:
    """Put a pose network on a backend, in place (see the module docstring).

    Args:
        model: a :class:`~freipose.nn.model.VoxelPoseNet` or
            :class:`~freipose.nn.model.BaselineNet`.
        backend: one of :data:`BACKENDS`.

    Returns:
        ``model`` itself, its ``backend`` attribute set (weights unchanged in value).
    """
    name = resolve_backend(backend)
    fast = name != "eager"
    _to_layout(model, fast)
    model.fast = fast
    model.backend = name
    return model


def bf16_support(device: torch.device | str) -> tuple[bool, str]:
    """Whether a device computes bfloat16 in hardware, and what it is (for messages).

    CPUs: AVX-512-BF16 or AMX units (without them oneDNN emulates bfloat16; on a 2-core
    AVX2 CPU the network ran about 15 times slower than in fp32, ``benchmarks/predict.py``);
    a PyTorch that cannot tell counts as yes. GPUs: compute capability 8.0 or newer (ROCm:
    every GPU).

    Args:
        device: ``cpu``, ``cuda`` or ``cuda:N``.

    Returns:
        ``(native, description)``, e.g. ``(False, "this CPU (AVX2)")``.
    """
    dev = torch.device(device)
    if dev.type == "cuda":
        props = torch.cuda.get_device_properties(dev)
        text = f"GPU {props.name} (compute capability {props.major}.{props.minor})"
        return bool(torch.version.hip) or props.major >= 8, text
    if dev.type != "cpu":
        return False, f"device {dev}"
    probes = [getattr(torch.cpu, n, None) for n in ("_is_avx512_bf16_supported",
                                                     "_is_amx_tile_supported")]  # fmt: skip
    native = any(p() for p in probes if p is not None) or all(p is None for p in probes)
    return native, f"this CPU ({torch.backends.cpu.get_cpu_capability()})"


def backend_of(model: nn.Module) -> str:
    """The backend a network runs on (``eager`` unless :func:`optimize` set another)."""
    return str(getattr(getattr(model, "module", model), "backend", "eager"))


@contextlib.contextmanager
def inference_autocast(model: nn.Module, device: torch.device) -> Iterator[None]:
    """The autocast of a network's backend: bfloat16 for ``bf16`` and on a bf16 GPU, else none.

    A GPU computes in bfloat16 where it has the units for it (:func:`bf16_support`).

    Args:
        model: a network (possibly wrapped, with ``module``).
        device: where it runs.

    Yields:
        Nothing; inside the context the network runs in its precision.
    """
    amp = backend_of(model) == "bf16" or (device.type == "cuda" and bf16_support(device)[0])
    with torch.autocast(device_type=device.type, dtype=torch.bfloat16, enabled=amp):
        yield


def forward_flops(model: nn.Module, batch: object) -> int:
    """Floating-point operations of one forward pass (``torch.utils.flop_counter``).

    Counts the matrix products and convolutions (two per multiply-add), as
    ``FlopCounterMode`` does; elementwise work is not counted.

    Args:
        model: a network (on its backend).
        batch: its input (a collated batch).

    Returns:
        The count for the whole batch.
    """
    from torch.utils.flop_counter import FlopCounterMode

    device = next(model.parameters()).device
    with (
        torch.inference_mode(),
        inference_autocast(model, device),
        FlopCounterMode(display=False) as counter,
    ):
        model(batch)
    return int(counter.get_total_flops())


def matmul_roofline(n: int = 2048, repeats: int = 3, device: str = "cpu") -> float:
    """GFLOP/s of a fp32 ``n x n`` matrix product on the current threads (best of ``repeats``).

    The reference for the networks' achieved GFLOP/s: what the same cores reach on the most
    favourable dense kernel.

    Args:
        n: matrix side.
        repeats: timed products after one warm-up.
        device: where to multiply.

    Returns:
        GFLOP/s.
    """
    import time

    a = torch.randn(n, n, device=device)
    b = torch.randn(n, n, device=device)
    a @ b
    best = float("inf")
    for _ in range(max(1, repeats)):
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        t = time.perf_counter()
        a @ b
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        best = min(best, time.perf_counter() - t)
    return 2 * n**3 / best / 1e9

"""Exported-graph runtimes against PyTorch on the voxel network's dense parts, same run.

The voxel network's convolutions sit in three dense sub-networks with fixed shapes: the 2D
encoder with the feature lift (every view's crop to its feature maps), the 3D U-Net (the
voxel volume to the score volumes) and the 2D refinement head. The rest (the sampling plan
of the unprojection, the soft-argmax, the fusion) depends on the cameras and the data and
stays in PyTorch whatever the runtime. This script times each dense part, for one batch of
``--batch`` samples of ``--cameras`` views, on

* ``torch eager``: contiguous fp32 tensors (the ``eager`` backend);
* ``torch optimized``: channels-last fp32 (the ``optimized`` backend);
* ``torch bf16``: channels-last under bfloat16 autocast (the ``bf16`` backend);
* ``openvino f32`` / ``openvino bf16``: the part converted by ``openvino.convert_model`` and
  compiled for the CPU with that inference precision (bf16 only where the CPU reports it);
* ``onnxruntime f32``: the part exported by ``torch.onnx.export`` and run by ONNX Runtime's
  CPU provider with every graph optimisation,

alternating the runtimes ``--repeat`` times and keeping each one's median; it prints the
milliseconds, the ratio to ``torch optimized`` and the largest absolute difference of the
outputs from eager fp32, and records them. A runtime that is not installed is skipped with
what to install (``pip install "freipose[bench]"``). The network is the shipped base model of
the small preset (its speed does not depend on the weights).

Usage::

    python benchmarks/runtimes.py                  # batch 8 of 4 views, 2048 x 2048 matmul ref
    python benchmarks/runtimes.py --batch 2 --repeat 3 --runtimes torch
"""

from __future__ import annotations

import argparse
import importlib.util
import statistics
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

import numpy as np
import torch
from _results import write_result
from torch import nn

from freipose.nn.fast import matmul_roofline

RUNTIMES = ("torch", "openvino", "onnxruntime")
INSTALL = 'pip install "freipose[bench]"'
Part = tuple[nn.Module, torch.Tensor]


class _EncoderPart(nn.Module):
    """Crops (N, 3, S, S) -> the encoder's features, the lifted features and the skip maps."""

    def __init__(self, net: nn.Module):
        super().__init__()
        self.encoder, self.lift = net.encoder, net.lift

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, ...]:
        feats, skip = self.encoder(x)
        lifted = () if self.lift is None else (self.lift(feats, skip),)
        return (feats, *lifted, *skip)


class _UNetPart(nn.Module):
    """Volume (B, C, G, G, G) -> the score volumes (deep supervision included)."""

    def __init__(self, net: nn.Module):
        super().__init__()
        self.unet = net.unet

    def forward(self, vol: torch.Tensor) -> tuple[torch.Tensor, ...]:
        return tuple(self.unet(vol))


class _RefinePart(nn.Module):
    """Features, skip maps and heat maps -> the refinement's map and confidence logits."""

    def __init__(self, net: nn.Module, n_skip: int):
        super().__init__()
        self.refine, self.n_skip = net.refine, n_skip

    def forward(self, feats: torch.Tensor, *rest: torch.Tensor) -> tuple[torch.Tensor, ...]:
        skip, heat = list(rest[: self.n_skip]), rest[self.n_skip]
        maps, conf = self.refine(feats, skip, heat)
        return maps, conf


def missing(runtimes: Sequence[str]) -> dict[str, str]:
    """The asked runtimes that cannot run here, each with why and what to install."""
    modules = {"openvino": ("openvino",), "onnxruntime": ("onnxruntime", "onnx")}
    said = {}
    for name in runtimes:
        absent = [m for m in modules.get(name, ()) if importlib.util.find_spec(m) is None]
        if absent:
            said[name] = f"{', '.join(absent)} not installed; {INSTALL}"
    return said


def parts(
    net: nn.Module, batch: int, views: int
) -> dict[str, tuple[nn.Module, list[torch.Tensor]]]:
    """The dense parts of a voxel network with example inputs of one batch (random values)."""
    cfg = net.cfg
    gen = torch.Generator().manual_seed(0)
    crops = torch.randn(batch * views, 3, cfg.crop_size, cfg.crop_size, generator=gen)
    enc = _EncoderPart(net).eval()
    with torch.no_grad():  # not inference mode: the exporters trace these tensors
        feats, *rest = enc(crops)
    lifted = rest[0] if net.lift is not None else feats
    skip = rest[1:] if net.lift is not None else rest
    G = cfg.grid_size
    vol = torch.randn(batch, lifted.shape[1], G, G, G, generator=gen)
    out = {"encoder": (enc, [crops]), "unet": (_UNetPart(net).eval(), [vol])}
    if net.refine is not None:
        heat = torch.rand(batch * views, net.num_keypoints, *feats.shape[-2:], generator=gen)
        out["refine"] = (_RefinePart(net, len(skip)).eval(), [feats, *skip, heat])
    return out


def _channels_last(x: torch.Tensor) -> torch.Tensor:
    fmt = {4: torch.channels_last, 5: torch.channels_last_3d}.get(x.dim())
    return x if fmt is None else x.contiguous(memory_format=fmt)


def torch_runner(
    net: nn.Module, module: nn.Module, inputs: list[torch.Tensor], backend: str
) -> Callable:
    """A call of ``module`` on ``inputs`` on a backend of :mod:`freipose.nn.fast`."""
    from freipose.nn.fast import optimize

    fast = backend != "eager"
    args = [_channels_last(x) if fast else x for x in inputs]

    def run() -> list[np.ndarray]:
        optimize(net, backend)  # the parts share the network's modules: set its layout each call
        with (
            torch.inference_mode(),
            torch.autocast("cpu", dtype=torch.bfloat16, enabled=backend == "bf16"),
        ):
            return [o.float().numpy() for o in module(*args)]

    return run


def openvino_runner(
    module: nn.Module, inputs: list[torch.Tensor], precision: str, threads: int
) -> Callable:
    """``module`` converted by OpenVINO and compiled for the CPU at ``precision``."""
    import openvino as ov

    model = ov.convert_model(module, example_input=tuple(inputs))
    config = {"INFERENCE_PRECISION_HINT": precision, "PERFORMANCE_HINT": "LATENCY",
              "INFERENCE_NUM_THREADS": threads}  # fmt: skip
    request = ov.Core().compile_model(model, "CPU", config).create_infer_request()
    arrays = [x.numpy() for x in inputs]

    def run() -> list[np.ndarray]:
        res = request.infer(arrays)
        return [np.asarray(res[i]) for i in range(len(res))]

    return run


def onnxruntime_runner(
    module: nn.Module, inputs: list[torch.Tensor], threads: int, folder: Path
) -> Callable:
    """``module`` exported to ONNX and run by ONNX Runtime's CPU provider."""
    import onnxruntime as ort

    path = folder / f"{type(module).__name__}.onnx"
    names = [f"in{i}" for i in range(len(inputs))]
    torch.onnx.export(module, tuple(inputs), str(path), input_names=names,
                      opset_version=18, dynamo=False)  # fmt: skip
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    session = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
    # the exporter drops inputs the graph does not read (skip maps the head does not use)
    given = {n: x.numpy() for n, x in zip(names, inputs, strict=True)}
    feed = {i.name: given[i.name] for i in session.get_inputs()}

    def run() -> list[np.ndarray]:
        return list(session.run(None, feed))

    return run


def runners(net: nn.Module, module: nn.Module, inputs: list[torch.Tensor], runtimes: Sequence[str],
            threads: int, folder: Path) -> Iterator[tuple[str, Callable]]:  # fmt: skip
    """Each runtime's call of one part, in the order of the table."""
    if "torch" in runtimes:
        for backend in ("eager", "optimized", "bf16"):
            yield f"torch {backend}", torch_runner(net, module, inputs, backend)
    from freipose.nn.fast import optimize

    optimize(net, "eager")  # the exporters convert the network as written
    if "openvino" in runtimes:
        import openvino as ov

        caps = ov.Core().get_property("CPU", "OPTIMIZATION_CAPABILITIES")
        for precision in ("f32", "bf16") if "BF16" in caps else ("f32",):
            yield f"openvino {precision}", openvino_runner(module, inputs, precision, threads)
    if "onnxruntime" in runtimes:
        yield "onnxruntime f32", onnxruntime_runner(module, inputs, threads, folder)


def max_difference(got: list[np.ndarray], ref: list[np.ndarray]) -> float:
    """Largest absolute difference between two lists of outputs of the same shapes."""
    return max(float(np.abs(g.reshape(r.shape) - r).max()) for g, r in zip(got, ref, strict=True))


def measure(calls: dict[str, Callable], repeat: int) -> dict[str, float]:
    """Median milliseconds of each call, alternated ``repeat`` times after one warm-up each."""
    for call in calls.values():
        call()
    times: dict[str, list[float]] = {name: [] for name in calls}
    for _ in range(max(1, repeat)):
        for name, call in calls.items():
            t = time.perf_counter()
            call()
            times[name].append((time.perf_counter() - t) * 1000)
    return {name: statistics.median(v) for name, v in times.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, default=8, help="samples per batch (default 8)")
    ap.add_argument("--cameras", type=int, default=4, help="views per sample (default 4)")
    ap.add_argument("--repeat", type=int, default=10, help="alternated timings, median kept")
    ap.add_argument("--threads", type=int, default=0, help="threads (0: torch's default)")
    ap.add_argument("--runtimes", nargs="+", default=list(RUNTIMES), choices=RUNTIMES)
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    threads = torch.get_num_threads()
    for name, why in missing(args.runtimes).items():
        print(f"{name} skipped: {why}", file=sys.stderr)
    runtimes = [r for r in args.runtimes if r not in missing(args.runtimes)]
    if not runtimes:
        sys.exit("no runtime to measure")

    from freipose.predict.network import load_model

    base = Path(__file__).resolve().parents[1] / "freipose" / "models" / "voxel_small.pt"
    net, _, _, _ = load_model(base, "cpu")
    net.eval()
    figures: dict[str, dict[str, float]] = {}
    with tempfile.TemporaryDirectory(prefix="fp_runtimes_") as tmp:
        for part, (module, inputs) in parts(net, args.batch, args.cameras).items():
            calls = dict(runners(net, module, inputs, runtimes, threads, Path(tmp)))
            ref = torch_runner(net, module, inputs, "eager")()
            ms = measure(calls, args.repeat)
            base_ms = ms.get("torch optimized", min(ms.values()))
            figures[part] = {}
            for name, call in calls.items():
                diff = max_difference(call(), ref)
                figures[part][f"{name}/ms"] = ms[name]
                figures[part][f"{name}/vs_torch_optimized"] = base_ms / ms[name]
                figures[part][f"{name}/max_abs_diff"] = diff
                print(f"[{part}] {name:17s} {ms[name]:8.1f} ms  {base_ms / ms[name]:5.2f}x "
                      f"torch optimized  max |diff| from eager fp32 {diff:.2g}")  # fmt: skip
    totals = {name: sum(figures[p][f"{name}/ms"] for p in figures) for name in calls}
    for name, total in totals.items():
        print(f"[all parts] {name:17s} {total:8.1f} ms")
    roof = matmul_roofline()
    print(f"batch {args.batch} x {args.cameras} views, {threads} threads, medians of "
          f"{args.repeat}; fp32 2048 x 2048 matmul {roof:.0f} GFLOP/s")  # fmt: skip
    settings = {k: str(v) for k, v in vars(args).items()} | {"threads": threads}
    figs = {"parts": figures, "total_ms": totals, "matmul_gflops": roof}
    write_result("runtimes", figs, extra=settings)


if __name__ == "__main__":
    main()

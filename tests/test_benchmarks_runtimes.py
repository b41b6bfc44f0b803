"""``benchmarks/runtimes.py``: the dense parts, the missing-runtime message and a short run."""

from __future__ import annotations

import importlib.util
import json
import os
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

BENCHMARK = "runtimes"  # the script the conftest fixture ``bench`` loads


def test_a_missing_runtime_is_named_with_what_to_install(bench, monkeypatch):
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name: None if name == "onnx" else object())  # fmt: skip
    said = bench.missing(["torch", "openvino", "onnxruntime"])
    assert list(said) == ["onnxruntime"]
    assert said["onnxruntime"] == 'onnx not installed; pip install "freipose[bench]"'


def test_the_parts_give_the_networks_own_outputs(bench):
    from freipose.predict.network import load_model

    base = Path(bench.__file__).resolve().parents[1] / "freipose" / "models" / "voxel_small.pt"
    net, _, _, _ = load_model(base, "cpu")
    net.eval()
    parts = bench.parts(net, batch=1, views=2)
    assert set(parts) == {"encoder", "unet", "refine"}
    enc, (crops,) = parts["encoder"]
    assert crops.shape == (2, 3, net.cfg.crop_size, net.cfg.crop_size)
    with torch.no_grad():
        feats, skip = net.encoder(crops)
        got = enc(crops)
    np.testing.assert_array_equal(got[0].numpy(), feats.numpy())
    assert len(got) == 2 + len(skip)  # features, lifted features, skip maps
    unet, (vol,) = parts["unet"]
    assert vol.shape[2:] == (net.cfg.grid_size,) * 3
    # the optimized backend's parts agree with eager within fp32 rounding, bf16 within its bound
    for name, (module, inputs) in parts.items():
        ref = bench.torch_runner(net, module, inputs, "eager")()
        fast = bench.torch_runner(net, module, inputs, "optimized")()
        scale = max(float(np.abs(r).max()) for r in ref)
        assert bench.max_difference(fast, ref) <= 1e-4 * scale, name
        assert bench.max_difference(ref, ref) == 0.0


def test_a_short_run_records_every_part_and_runtime(bench, monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", ["runtimes.py", "--batch", "1", "--cameras", "2",
                                      "--repeat", "1", "--runtimes", "torch"])  # fmt: skip
    monkeypatch.setattr(bench, "matmul_roofline", lambda: 100.0)
    bench.main()
    out = capsys.readouterr().out
    assert "[unet] torch optimized" in out and "[all parts] torch bf16" in out
    (path,) = Path(os.environ["FREIPOSE_RESULTS_DIR"]).glob("runtimes/*.json")
    figures = json.loads(path.read_text())["figures"]
    assert set(figures["parts"]) == {"encoder", "unet", "refine"}
    enc = figures["parts"]["encoder"]
    assert enc["torch optimized/vs_torch_optimized"] == pytest.approx(1.0)
    assert enc["torch eager/max_abs_diff"] == 0.0
    assert set(figures["total_ms"]) == {"torch eager", "torch optimized", "torch bf16"}

"""The resumable step runner of ``freipose demo``.

Every finished step leaves ``OUTDIR/.demo/<step>.done`` (:mod:`freipose.demo.markers`); a
rerun skips finished steps, and the library's own resumability (rendered videos, training
checkpoints, chunked predictions, cached variables) continues an interrupted step. The
report is rewritten on every run.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from pathlib import Path
from types import MappingProxyType
from typing import Any

from freipose.demo import report
from freipose.demo.context import DemoContext
from freipose.demo.markers import STEPS, DemoError, check_outdir, read_marker, write_marker
from freipose.demo.presets import PRESETS, DemoPreset
from freipose.demo.steps import analyze, calibrate, evaluate, labels, predict, synth, train
from freipose.demo.summary import write_summary

StepFn = Callable[[DemoContext], dict[str, Any]]

STEP_INFO: Mapping[str, tuple[str, StepFn]] = MappingProxyType({
    "synth": ("Synthesize a calibration recording and stimulated sessions (freipose synth)",
              synth.run),
    "calibrate": ("Calibrate the 7 cameras from the board videos (freipose calib)",
                  calibrate.run),
    "labels": ("Import labels: triangulate 2D labels with the calibrated rig (freipose labels)",
               labels.run),
    "train": ("Train the detector, the voxel network and the baseline (freipose train)",
              train.run),
    "predict": ("Predict 3D poses of every session (freipose predict, freipose render)",
                predict.run),
    "evaluate": ("Evaluate joint position errors against the truth (freipose eval)",
                 evaluate.run),
    "analyze": ("Attribute the stimulation effect to body parts (freipose analyze)",
                analyze.run),
    "report": ("Write report.html", report.run),
})  # fmt: skip


def _resolve_preset(preset: str | DemoPreset) -> DemoPreset:
    """The preset named ``preset`` (or ``preset`` itself).

    Raises:
        DemoError: no preset has that name.
    """
    if isinstance(preset, DemoPreset):
        return preset
    if preset not in PRESETS:
        raise DemoError(f"unknown demo preset {preset!r}; choose one of {sorted(PRESETS)}")
    return PRESETS[preset]


def run_demo(
    outdir: str | Path,
    preset: str | DemoPreset = "small",
    device: str = "cpu",
    say: Callable[[str], None] = print,
    progress: bool | None = None,
    seed: int = 0,
) -> Path:
    """Run (or resume) the demo in ``outdir``; returns the path of ``report.html``.

    Args:
        outdir: output folder (created).
        preset: ``"small"`` (default, < 10 min on 2 CPU cores), ``"tiny"`` (CI) or a preset.
        device: torch device for training and prediction.
        say: where progress messages go.
        progress: progress bars (None: only on a terminal).
        seed: training seed of the detector, the voxel network and the baseline (the data
            stay the same; see :meth:`DemoPreset.with_seed`).

    Returns:
        The path of ``outdir/report.html`` (``outdir/summary.json`` holds every figure).

    Raises:
        DemoError: unknown preset, ``outdir`` is not a folder or holds a demo run with
            another preset.
    """
    if seed < 0:
        raise DemoError(f"--seed must be >= 0, got {seed}")
    preset = _resolve_preset(preset).with_seed(seed)
    out = Path(outdir)
    if out.exists() and not out.is_dir():
        raise DemoError(f"{out} exists and is not a folder; choose another output folder")
    check_outdir(out, preset)
    out.mkdir(parents=True, exist_ok=True)
    ctx = DemoContext(out, preset, device, say, progress)
    t_all = time.perf_counter()
    for i, step in enumerate(STEPS, start=1):
        title, fn = STEP_INFO[step]
        done = read_marker(out, step)
        if done is not None and step != "report":
            say(f"[{i}/{len(STEPS)}] {title}: done earlier ({done.get('seconds', 0):.0f} s), "
                "skipped")  # fmt: skip
            continue
        say(f"[{i}/{len(STEPS)}] {title}")
        t0 = time.perf_counter()
        results = fn(ctx)
        dt = time.perf_counter() - t0
        write_marker(out, preset, step, results, dt)
        say(f"      ({dt:.0f} s)")
    summary = write_summary(out, preset)
    say(f"demo finished in {time.perf_counter() - t_all:.0f} s; open {out / 'report.html'} "
        f"(every figure in {summary})")  # fmt: skip
    return out / "report.html"

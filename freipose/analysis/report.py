"""``freipose analyze STUDY.toml -o OUTDIR``: variables, attribution, tables and figures.

Outputs in OUTDIR: ``classification.csv``, ``attribution.csv``, ``dynamics.csv``,
``top_variables.csv``, ``settings.json``, the PNG figures of :mod:`freipose.analysis.figures`
and ``variables/<recording>.vars.h5`` (reused when the poses file and the settings are
unchanged, so an interrupted run resumes without recomputing the variables). A run holds
the lock ``OUTDIR.lock`` and removes an earlier run's tables and figures before it writes
its own, so that no figure of another analysis stays beside the new tables.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from pathlib import Path

from freipose.analysis import figures
from freipose.analysis.attribution import AttributionResult, run_attribution
from freipose.analysis.config import AttributionConfig
from freipose.analysis.io import cached_variables
from freipose.analysis.study import Study, check_study_events, load_study
from freipose.analysis.variables import VariableConfig
from freipose.errors import FreiPoseError
from freipose.io.atomic import atomic_path, atomic_write_text
from freipose.io.lock import output_lock
from freipose.io.poses import require_complete

log = logging.getLogger(__name__)


TABLES = ("classification.csv", "attribution.csv", "dynamics.csv", "top_variables.csv")
# what a run writes into OUTDIR besides the cached variables (figures: the PNGs it names)
_OUTPUT_PATTERNS = (
    *TABLES,
    "settings.json",
    "attribution_*.png",
    "top_variables_*.png",
    "classifier_response.png",
)


class AnalysisOutputError(FreiPoseError):
    """The output folder holds an earlier analysis (or other files) and may not be replaced."""


def clear_outputs(outdir: Path, overwrite: bool) -> list[Path]:
    """Make ``outdir`` ready for a new analysis: remove an earlier run's tables and figures.

    Args:
        outdir: the analysis folder.
        overwrite: replace what an earlier analysis wrote there (else a non-empty folder is
            refused). The cached variables are kept: they are reused only when their poses
            file and settings are unchanged.

    Returns:
        The files removed.

    Raises:
        AnalysisOutputError: ``outdir`` is a file, or not empty and not ``overwrite``.
    """
    if outdir.exists() and not outdir.is_dir():
        raise AnalysisOutputError(f"{outdir} exists and is not a folder; pass another -o")
    if not outdir.is_dir() or not any(outdir.iterdir()):
        return []
    if not overwrite:
        raise AnalysisOutputError(
            f"the output folder {outdir} is not empty (an earlier analysis?); pass "
            "--overwrite to replace its tables and figures (its cached variables are "
            "reused), or choose another -o"
        )
    old = sorted({p for pat in _OUTPUT_PATTERNS for p in outdir.glob(pat) if p.is_file()})
    for p in old:
        p.unlink()
    return old


def write_tables(result: AttributionResult, outdir: Path) -> list[Path]:
    """Write the CSV tables and settings atomically; returns the paths."""
    outdir.mkdir(parents=True, exist_ok=True)
    paths = []
    frames = (result.classification, result.attribution, result.dynamics, result.timecourses)
    for name, df in zip(TABLES, frames, strict=True):
        p = outdir / name
        with atomic_path(p) as tmp:
            df.to_csv(tmp, index=False, float_format="%.6g")
        paths.append(p)
    return paths


def write_figures(result: AttributionResult, outdir: Path) -> list[Path]:
    """Write the PNG figures; returns the paths."""
    var = result.variables
    kinds = dict(zip(var.names, var.kinds)) if var is not None else {}
    paths = []
    for (animal, cond), att in result.attribution.groupby(["animal", "condition"], sort=False):
        tag = f"{figures.safe_name(animal)}_{figures.safe_name(cond)}"
        p = outdir / f"attribution_{tag}.png"
        figures.attribution_heatmap(att, kinds, p, f"Attribution: trained on {animal}, {cond}")
        paths.append(p)
        tc = result.timecourses
        tc = tc[(tc["animal"] == animal) & (tc["condition"] == cond)]
        dyn = result.dynamics
        dyn = dyn[
            (dyn["animal"] == animal) & (dyn["condition"] == cond) & (dyn["evaluated_on"] == animal)
        ]
        if len(tc):
            p = outdir / f"top_variables_{tag}.png"
            figures.top_variables(tc, dyn, p, f"Top variables around onset: {animal}, {cond}")
            paths.append(p)
    if len(result.dynamics):
        p = outdir / "classifier_response.png"
        figures.classifier_response(result.dynamics, p)
        paths.append(p)
    return paths


def check_complete_poses(study: Study, allow_incomplete: bool = False) -> dict[str, int]:
    """Refuse the study's unfinished poses files, or warn how many frames each lacks.

    Args:
        study: the study.
        allow_incomplete: go on with unfinished files (their missing frames are NaN and
            left out of the analysis).

    Returns:
        Recording name -> frames without a prediction, for the incomplete recordings.

    Raises:
        IncompletePosesError: a poses file is unfinished and ``allow_incomplete`` is false;
            the message names the file and the command that finishes it.
    """
    missing = {}
    for rec in study.recordings:
        n = require_complete(rec.poses, allow_incomplete)
        if n:
            missing[rec.name] = n
            log.warning(
                "%s (%s) is incomplete: %d frames have no prediction (NaN, left out of the "
                "analysis)",
                rec.poses,
                rec.name,
                n,
            )
    return missing


def analyze_study(
    study_path: str | Path,
    outdir: str | Path,
    skeleton: str | Path | None = None,
    floor: str | Path = "world",
    variable_config: VariableConfig = VariableConfig(),
    config: AttributionConfig = AttributionConfig(),
    make_figures: bool = True,
    say: Callable[[str], None] | None = None,
    allow_incomplete: bool = False,
    overwrite: bool = True,
) -> AttributionResult:
    """Run the whole attribution analysis of a study and write its outputs.

    Args:
        study_path: STUDY.toml.
        outdir: output folder (created).
        skeleton: overrides the study's ``skeleton`` and the poses files' own.
        floor: default floor (``world``, ``auto`` or a file) for recordings without ``floor``.
        variable_config: gap filling and STFT settings.
        config: the attribution settings.
        make_figures: also write the PNG figures.
        say: progress messages (default: this module's logger).
        allow_incomplete: go on with poses files whose prediction run has not finished
            (with a warning naming the frames without a prediction).
        overwrite: replace an earlier analysis in ``outdir`` (its tables and figures are
            removed first); False: refuse a folder that is not empty.

    Returns:
        The result tables.

    Raises:
        IncompletePosesError: a poses file is incomplete and ``allow_incomplete`` is false.
        StudyError: an invalid study or events file (the poses and events files are checked
            before any variable is computed), or recordings without usable frames.
        AnalysisOutputError: ``outdir`` is not empty and not ``overwrite``.
        OutputLockedError: another analysis writes into ``outdir``.
    """
    study = load_study(study_path)
    check_complete_poses(study, allow_incomplete)
    check_study_events(study)
    outdir = Path(outdir)
    with output_lock(outdir, "analysis folder"):
        clear_outputs(outdir, overwrite)
        outdir.mkdir(parents=True, exist_ok=True)
        return _analyze(
            study, Path(study_path), outdir, skeleton, floor, variable_config, config,
            make_figures, say or log.info,
        )  # fmt: skip


def _analyze(
    study: Study,
    study_path: Path,
    outdir: Path,
    skeleton: str | Path | None,
    floor: str | Path,
    variable_config: VariableConfig,
    config: AttributionConfig,
    make_figures: bool,
    say: Callable[[str], None],
) -> AttributionResult:
    """The analysis of :func:`analyze_study` once the output folder is ready."""
    skel = skeleton if skeleton is not None else study.skeleton
    variables = {}
    for i, rec in enumerate(study.recordings, start=1):
        say(f"variables {i}/{len(study.recordings)}: {rec.name}")
        variables[rec.name] = cached_variables(
            rec.poses,
            outdir / "variables" / f"{figures.safe_name(rec.name)}.vars.h5",
            skel,
            rec.floor if rec.floor is not None else floor,
            variable_config,
        )
    result = run_attribution(study, variables, config, log_fn=say)
    write_tables(result, outdir)
    settings = {
        "study": str(Path(study_path).resolve()),
        "skeleton": None if skel is None else str(skel),
        "floor": str(floor),
        "variables": {
            "max_gap_s": variable_config.max_gap_s,
            "stft_window": variable_config.stft_window,
        },
        "attribution": dict(result.settings),
    }
    atomic_write_text(outdir / "settings.json", json.dumps(settings, indent=2) + "\n")
    if make_figures:
        write_figures(result, outdir)
    return result

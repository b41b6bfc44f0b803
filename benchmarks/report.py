"""Generate ``docs/benchmarks.md``, the README's demo table and the model card's figures.

Every figure is shown as the median and the range (min-max) over the recorded runs, with the
number of runs, their seeds, CPU kinds and machines, dates and commits, and the command that
reproduces them. Runs of one benchmark with different settings (apart from the seed) get
separate tables. The README block between ``<!-- demo-figures:begin -->`` and
``<!-- demo-figures:end -->`` gets the demo's key figures as ranges per CPU kind, over the
runs of the default preset with today's starting weights and training schedule (a README
without these markers is left as it is). The model card ``docs/models.md`` gets, between
``<!-- base-figures:begin -->`` and ``<!-- base-figures:end -->``, the shipped bases' data,
steps, held-out figures and commands from their manifest ``freipose/models/bases.json``. The
tutorial ``docs/tutorials/cluster.md`` gets, between ``<!-- cluster-figures:begin -->`` and
``<!-- cluster-figures:end -->``, the latest run of ``benchmarks/cluster.py`` and the paper
calculation made from its figures.

    python benchmarks/report.py            # rewrite the page and the three blocks
    python benchmarks/report.py --check    # exit 1 when one of them is out of date
"""

from __future__ import annotations

import argparse
import json
import shlex
import statistics
import sys
from collections import Counter
from pathlib import Path
from typing import Any

from _results import RESULTS, ROOT, load_results
from demo import schedule_of

from freipose.io.atomic import atomic_write_text

PAGE = ROOT / "docs" / "benchmarks.md"
README = ROOT / "README.md"
MODELS = ROOT / "docs" / "models.md"
MANIFEST = ROOT / "freipose" / "models" / "bases.json"
BEGIN, END = "<!-- demo-figures:begin -->", "<!-- demo-figures:end -->"
CARD_BEGIN, CARD_END = "<!-- base-figures:begin -->", "<!-- base-figures:end -->"
CLUSTER_DOC = ROOT / "docs" / "tutorials" / "cluster.md"
CLUSTER_BEGIN, CLUSTER_END = "<!-- cluster-figures:begin -->", "<!-- cluster-figures:end -->"
# the scripts that record results (each gets a section, recorded or not)
BENCHMARKS = (
    "accuracy", "analysis", "calibration", "calibration_coverage", "classifier_days", "cluster",
    "demo", "detector", "engines", "label_efficiency", "label_page", "null_studies", "own_rig",
    "predict", "real_finetune", "runtimes", "smooth", "smooth_ensembles", "social",
    "social_identity", "social_poses", "study_predicted", "synth", "throughput", "train_base",
)  # fmt: skip
# settings that differ between runs of the same experiment (not a different experiment)
RUN_KEYS = {"seed", "folder", "finished", "demo", "out", "workdir", "work", "export"}
# the README's demo rows: (label, figure key, unit, scale)
DEMO_ROWS = (
    ("Calibration: largest camera-centre error", "calibration/max_center_mm", "mm", 1),
    ("Detector: recall at IoU 0.5", "detector/recall", "", 1),
    ("Detector: median 3D centre error", "detector/median_center_error", "mm", 1),
    ("Held-out median JPE, voxel network (P1)", "held_out_jpe_mm/voxel_P1", "mm", 1),
    ("Held-out median JPE, voxel network (P0)", "held_out_jpe_mm/voxel_P0", "mm", 1),
    ("Held-out median JPE, 2D + triangulation baseline", "held_out_jpe_mm/baseline", "mm", 1),
    ("Whole pipeline median JPE, day 2 (test)", "pipeline_jpe_mm/rat1_day2 (test)", "mm", 1),
    ("Whole pipeline median JPE, day 3 (train)", "pipeline_jpe_mm/rat1_day3 (train)", "mm", 1),
    ("Best single variable, F1 (predicted poses)", "analysis/predicted/best_f1", "", 1),
    ("Stimulated paw among the 5 best variables", "analysis/predicted/paw_share_top5", "", 1),
    ("Stimulated paw among the 10 best variables", "analysis/predicted/paw_share_top10", "", 1),
    ("Balanced accuracy, raw predicted poses", "analysis/predicted/balanced_accuracy", "", 1),
    ("Balanced accuracy, smoothed predicted poses", "analysis/smoothed/balanced_accuracy", "", 1),
    ("Significant variables (predicted poses)", "analysis/predicted/significant", "", 1),
    ("Demo wall time", "seconds/total", "min", 1 / 60),
)


def flatten(figures: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested figures as ``{"a/b/c": value}`` in their order."""
    out: dict[str, Any] = {}
    for k, v in figures.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(flatten(v, key + "/"))
        elif isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
            # per-run or per-seed records: too long for a table row, kept in the result file
            out[key] = f"{len(v)} records (in the result file)"
        else:
            out[key] = v
    return out


def fmt(x: float) -> str:
    """A number with three significant digits (integers as they are)."""
    if float(x).is_integer() and abs(x) < 1e6:
        return str(int(x))
    return f"{x:.3g}" if abs(x) < 1000 else f"{x:.0f}"


def is_number(v: Any) -> bool:
    """A number figure (booleans are not)."""
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def spread(values: list[Any]) -> dict[str, Any]:
    """Median, min, max and count of the number values; value counts of the others."""
    nums = [float(v) for v in values if is_number(v)]
    if nums:
        return {"median": statistics.median(nums), "min": min(nums), "max": max(nums),
                "n": len(nums)}  # fmt: skip
    counts = Counter(
        _setting(v) if isinstance(v, str) else json.dumps(v) for v in values if v is not None
    )
    return {"values": counts.most_common(), "n": sum(counts.values())}


def span(lo: float, hi: float) -> str:
    """``lo-hi``, or ``lo to hi`` where a minus sign would make the dash ambiguous."""
    sep = " to " if lo < 0 or hi < 0 else "-"
    return f"{fmt(lo)}{sep}{fmt(hi)}"


def cell(s: dict[str, Any], unit: str = "") -> str:
    """A spread as table text: ``median (min-max)``, one value, or values with counts."""
    if s["n"] == 0:
        return "-"
    u = f" {unit}" if unit else ""
    if "values" in s:
        return ", ".join(v if c == 1 else f"{v} ({c}x)" for v, c in s["values"])
    if s["min"] == s["max"]:
        return fmt(s["median"]) + u
    return f"{fmt(s['median'])} ({span(s['min'], s['max'])}){u}"


def value_range(s: dict[str, Any], unit: str = "") -> str:
    """A spread as ``min-max`` (or the single value), for the README."""
    if s["n"] == 0 or "values" in s:
        return cell(s, unit)
    u = f" {unit}" if unit else ""
    if s["min"] == s["max"]:
        return fmt(s["min"]) + u
    return f"{span(s['min'], s['max'])}{u}"


def settings_key(rec: dict[str, Any]) -> str:
    """The settings of a run apart from what differs between runs of one experiment."""
    extra = {k: v for k, v in rec.get("extra", {}).items() if k not in RUN_KEYS}
    return json.dumps(extra, sort_keys=True)


def groups(records: list[dict[str, Any]]) -> dict[str, dict[str, list[dict[str, Any]]]]:
    """Records by benchmark, then by settings (in the order first recorded)."""
    out: dict[str, dict[str, list[dict[str, Any]]]] = {}
    for r in records:
        out.setdefault(r["benchmark"], {}).setdefault(settings_key(r), []).append(r)
    return dict(sorted(out.items()))


def kinds(runs: list[dict[str, Any]]) -> list[str]:
    """The CPU kinds of the runs, most runs first."""
    return [k for k, _ in Counter(r["machine"]["cpu_kind"] for r in runs).most_common()]


def seeds_text(runs: list[dict[str, Any]]) -> str:
    """The seeds of the runs, e.g. ``0, 1, 2`` (``-`` when none are recorded)."""
    seeds = sorted({r["extra"]["seed"] for r in runs if "seed" in r.get("extra", {})})
    return ", ".join(map(str, seeds)) or "-"


def runs_text(runs: list[dict[str, Any]]) -> str:
    """E.g. ``3 runs, seeds 0, 1, 2`` or ``1 run, seed 0``."""
    seeds = seeds_text(runs)
    if len(runs) == 1:
        return f"1 run, seed {seeds}"
    return f"{len(runs)} runs, seed{'s' if ',' in seeds else ''} {seeds}"


# options whose value is a folder of the machine that ran the benchmark: shown as a name to fill in
LOCAL_FOLDERS = {"--work": "WORK", "--out": "OUT", "--demo": "DEMO", "--workdir": "WORKDIR"}


def command_text(rec: dict[str, Any]) -> str:
    """The command line of a record, as a shell would take it from the repository root.

    The script is named by its path in the repository, and the scratch and run folders of
    the machine that ran it (:data:`LOCAL_FOLDERS`) by a name in capitals.
    """
    argv = list(rec.get("command") or [])
    if argv and argv[0].endswith(".py"):
        argv = ["python", f"benchmarks/{Path(argv[0]).name}", *argv[1:]]
    shown = []
    for i, arg in enumerate(argv):
        opt, eq, _ = arg.partition("=")
        if eq and opt in LOCAL_FOLDERS:
            arg = f"{opt}={LOCAL_FOLDERS[opt]}"
        elif i and argv[i - 1] in LOCAL_FOLDERS:
            arg = LOCAL_FOLDERS[argv[i - 1]]
        shown.append(arg)
    return shlex.join(shown)


def provenance(runs: list[dict[str, Any]]) -> list[str]:
    """Where the runs come from: count, seeds, CPU kinds and machines, dates, commits."""
    by_kind = Counter(r["machine"]["cpu_kind"] for r in runs)
    machines = Counter(
        f"{r['machine']['cpu_model']}, {r['machine']['cores']} cores "
        f"({r['machine']['cpu_kind']}; torch {r['versions'].get('torch')})"
        for r in runs
    )
    dates = sorted(r["date"][:10] for r in runs)
    commits = Counter((r["git"]["commit"] or "unknown")[:8] for r in runs)
    dirty = sum(bool(r["git"].get("dirty")) for r in runs)
    when = dates[0] if dates[0] == dates[-1] else f"{dates[0]} to {dates[-1]}"
    return [
        f"- runs: {len(runs)} (seeds {seeds_text(runs)}); CPU kinds: "
        + ", ".join(f"{k} {n}" for k, n in by_kind.most_common()),
        "- machines: " + "; ".join(f"{m} x{n}" for m, n in machines.most_common()),
        f"- dates: {when}; commits: "
        + ", ".join(f"`{c}`" for c in commits)
        + (f" ({dirty} with uncommitted changes in the tree)" if dirty else ""),
    ]


def table(runs: list[dict[str, Any]]) -> list[str]:
    """The figures of the runs: median (min-max) over all runs and per CPU kind."""
    flat = [flatten(r["figures"]) for r in runs]
    keys = list(dict.fromkeys(k for f in reversed(flat) for k in f))
    ks = kinds(runs)
    per_kind = len(ks) > 1
    head = "| figure | all runs |" + "".join(f" {k} |" for k in ks if per_kind)
    lines = [head, "|---|---|" + "---|" * (len(ks) if per_kind else 0)]
    for key in keys:
        row = f"| {key} | {cell(spread([f.get(key) for f in flat]))} |"
        if per_kind:
            for k in ks:
                vals = [f.get(key) for f, r in zip(flat, runs) if r["machine"]["cpu_kind"] == k]
                row += f" {cell(spread(vals))} |"
        lines.append(row)
    return lines


def _setting(value: Any) -> Any:
    """A setting or a text figure as the page shows it: an absolute path by its file name.

    A model file, or a file on the recording machine. A table of settings (a training
    schedule) is shown as ``(key=value ...)``.
    """
    if isinstance(value, dict):
        return "(" + " ".join(f"{k}={_setting(v)}" for k, v in value.items()) + ")"
    return Path(value).name if isinstance(value, str) and Path(value).is_absolute() else value


def section(name: str, by_settings: dict[str, list[dict[str, Any]]]) -> list[str]:
    """One benchmark's section: per settings, provenance, figures and the command."""
    lines = [f"## {name}", ""]
    for key, runs in by_settings.items():
        settings = json.loads(key)
        if len(by_settings) > 1 and settings:
            text = ", ".join(f"{k}={_setting(v)}" for k, v in settings.items())
            lines += [f"### {text}", ""]
        lines += provenance(runs) + [""] + table(runs) + [""]
        lines += ["Reproduce (one run):", "", "```bash", command_text(runs[-1]), "```", ""]
    return lines


def page(records: list[dict[str, Any]]) -> str:
    """The text of ``docs/benchmarks.md``."""
    lines = [
        "# Benchmarks",
        "",
        "<!-- Generated by `python benchmarks/report.py` from benchmarks/results/; "
        "do not edit by hand. -->",
        "",
        "Every figure below was measured by a script in `benchmarks/` and recorded under "
        "`benchmarks/results/<benchmark>/` with the machine, its CPU flags, the versions, the "
        "date, the git commit and the command. Each is shown as the median and, in "
        "parentheses, the range (min-max) over the recorded runs; a column per CPU kind "
        "appears where runs came from more than one (AVX2 and AVX-512 machines round floats "
        "differently, and trainings drift apart from there). Run a benchmark, then "
        "`python benchmarks/report.py` to add the run to this page.",
        "",
    ]
    found = groups(records)
    for name in sorted(set(found) | set(BENCHMARKS)):
        if name in found:
            lines += section(name, found[name])
        else:
            lines += [f"## {name}", "", "No run is recorded yet: `python benchmarks/"
                      f"{name}.py --help` tells how to run it.", ""]  # fmt: skip
    return "\n".join(lines).rstrip() + "\n"


def _scaled(value: Any, scale: float) -> Any:
    """A number figure times ``scale``; other values as they are."""
    return value * scale if is_number(value) and scale != 1 else value


def _smoothing_helped(rec: dict[str, Any]) -> bool | None:
    """Whether the smoothed poses' balanced accuracy beat the raw ones' (None: unknown)."""
    f = flatten(rec["figures"])
    raw = f.get("analysis/predicted/balanced_accuracy")
    smoothed = f.get("analysis/smoothed/balanced_accuracy")
    return None if raw is None or smoothed is None else smoothed > raw


def _is_default_demo(rec: dict[str, Any]) -> bool:
    """Whether ``rec`` is a run of ``freipose demo`` as it runs today.

    That is the default preset with its starting weights and training schedule; runs of
    earlier schedules stay on the benchmarks page.
    """
    from freipose.demo.presets import PRESETS

    preset, extra = PRESETS["small"], rec["extra"]
    return (
        rec["benchmark"] == "demo"
        and extra.get("preset") == preset.name
        and extra.get("init") == preset.init
        and extra.get("schedule") == schedule_of(preset.pose)
    )


def demo_block(records: list[dict[str, Any]]) -> str:
    """The README's demo table: each key figure's range per CPU kind.

    Only runs of the default preset as it runs today count (:func:`_is_default_demo`).
    """
    runs = [r for r in records if _is_default_demo(r)]
    if not runs:
        return "No runs of the demo's default preset are recorded yet (`benchmarks/demo.py`).\n"
    ks = kinds(runs)
    by_kind = {k: [r for r in runs if r["machine"]["cpu_kind"] == k] for k in ks}
    head = "| figure |" + "".join(f" {k}: {runs_text(rs)} |" for k, rs in by_kind.items())
    lines = [head, "|---|" + "---|" * len(ks)]
    for label, key, unit, scale in DEMO_ROWS:
        vals = {k: [_scaled(flatten(r["figures"]).get(key), scale) for r in rs]
                for k, rs in by_kind.items()}  # fmt: skip
        if not any(v is not None for vs in vals.values() for v in vs):
            continue
        lines.append(f"| {label} |" + "".join(f" {value_range(spread(v), unit)} |"
                                               for v in vals.values()))  # fmt: skip
    raised = [_smoothing_helped(r) for r in runs]
    helped = sum(1 for h in raised if h)
    known = sum(1 for h in raised if h is not None)
    best = Counter(flatten(r["figures"]).get("analysis/predicted/best_variable") for r in runs)
    best.pop(None, None)
    lines += [
        "",
        "Ranges are min-max over the recorded runs of `freipose demo` (default preset and "
        "training schedule, `--seed` as listed, `--threads 2`); best single variable on the "
        "predicted poses: "
        + ", ".join(f"{v} ({n} of {len(runs)})" for v, n in best.most_common())
        + (f". Smoothing raised the balanced accuracy in {helped} of {known} runs" if known else "")
        + ". All runs and their machines: [docs/benchmarks.md](docs/benchmarks.md#demo).",
    ]
    return "\n".join(lines) + "\n"


def _yes(value: Any) -> str:
    return {True: "yes", False: "no"}.get(value, "not checked")


def cluster_block(records: list[dict[str, Any]]) -> str:
    """The cluster tutorial's figures: the latest run of ``benchmarks/cluster.py``.

    With the paper calculation of 1,000 hours of 7-camera video from its per-frame cost and
    its units' overhead.
    """
    runs = [r for r in records if r["benchmark"] == "cluster"]
    if not runs:
        return "No run of `benchmarks/cluster.py` is recorded yet.\n"
    r = runs[-1]
    f, x, m = r["figures"], r["extra"], r["machine"]
    fps, p = f["frames_per_s"], f["paper_1000h_7cams"]
    load = f.get("load_average_1min", {})
    overhead = f["overhead_s_slurm" if "slurm" in fps else "overhead_s_local"]
    unit_cost = [k for k in ("unit_s_per_frame_slurm", "unit_s_per_frame_local") if k in f]
    source = (f"a {unit_cost[0].rsplit('_', 1)[1].replace('slurm', 'SLURM')} unit's cost per "
              "frame after its first batch" if unit_cost else "the direct run's cost")  # fmt: skip
    lines = [
        f"Measured by `{command_text(r)}` (its latest recorded run, listed with its date and "
        f"commit on the [benchmarks](../benchmarks.md) page; {m['cpu_model']}, "
        f"{m['cores']} cores, shared with other work: 1-minute load average "
        f"{fmt(load.get('start', float('nan')))} at the start, "
        f"{fmt(load.get('end', float('nan')))} at the end): {x['sessions']} synthetic sessions "
        f"of {x['frames']} frames from {x['cameras']} cameras, units of {x['chunk_frames']} "
        f"frames, {x['cores']} cores in every mode; the rat was found in "
        f"{100 * f['found_share']:.0f} % of the frames.",
        "",
        "| mode | frames/s | ratio to direct | overhead per unit (submission to first frame) |",
        "|---|---|---|---|",
        f"| direct: one process, {x['cores']} threads | {fmt(fps['direct'])} | 1 | - |",
    ]
    names = {"local": f"local executor: {x['cores']} one-thread workers",
             "slurm": f"SLURM: {x['cores']} one-core array tasks"}  # fmt: skip
    for mode in ("local", "slurm"):
        if mode in fps:
            lines.append(f"| {names[mode]} | {fmt(fps[mode])} | "
                         f"{f[f'ratio_{mode}_to_direct']:.2f} | "
                         f"{fmt(f[f'overhead_s_{mode}'])} s |")  # fmt: skip
    if "frames_per_s_one_thread_direct" in f:
        lines.append(f"| direct: one process, 1 thread (first {x['identity_sessions']} "
                     f"session(s); not at the same cores) | "
                     f"{fmt(f['frames_per_s_one_thread_direct'])} | - | - |")  # fmt: skip
    ratios = [f[f"ratio_{k}_to_direct"] for k in ("local", "slurm") if k in fps]
    if unit_cost:
        work = x["chunk_frames"] * f[unit_cost[0]]
        lines += ["", f"A unit of {x['chunk_frames']} frames did {fmt(work)} s of work after "
                  f"{fmt(overhead)} s of overhead ({100 * overhead / (work + overhead):.0f} % of "
                  f"its time); with the default `chunk_frames = 6000` the overhead is "
                  f"{100 * p['overhead_share']:.1f} % (the paper calculation below)."]  # fmt: skip
    one_thread = f.get("frames_per_s_one_thread_direct")
    if one_thread and max(ratios) > 1:
        lines += ["", f"The units ran faster than the direct run: its {x['cores']} threads gave "
                  f"{fps['direct'] / one_thread:.2f} times one thread's throughput, while "
                  f"{x['cores']} one-thread processes each run at about one thread's speed; so "
                  "a ratio above 1 shows how threads scale, and the overhead column shows the "
                  "executors' cost."]  # fmt: skip
    worst = max(f.get(f"max_difference_mm_{k}", 0.0) for k in ("local", "slurm"))
    one = [f.get(f"identical_to_one_thread_direct_{k}") for k in ("local", "slurm") if k in fps]
    lines += [
        "",
        f"Outputs: local and SLURM identical bit for bit: {_yes(f.get('identical_local_slurm'))}; "
        f"equal bit for bit to a one-thread direct run of the same session(s): "
        f"{_yes(all(one) if None not in one else None)}; against the {x['cores']}-thread direct "
        f"run at most {worst:.2g} mm apart (its sums run in another order).",
        "",
        f"**Paper calculation** from these figures: 1,000 hours of 7-camera video at 100 fps "
        f"are {p['frames'] / 1e6:.0f} million multi-view frames. At "
        f"{p['core_s_per_frame_7cams']:.2f} core-seconds per 7-camera frame ({source} on this "
        f"CPU, scaled from {x['cameras']} to 7 views) in {fmt(p['units'])} units "
        f"of 6000 frames with {fmt(overhead)} s overhead each "
        f"({100 * p['overhead_share']:.2f} % of a unit), the study takes "
        f"{fmt(p['core_hours'])} core-hours (the cost: times your cluster's price per "
        f"core-hour): {fmt(p['wall_hours_on_100_workers'])} hours on 100 one-core workers, "
        f"{fmt(p['wall_hours_on_1000_workers'])} hours on 1000. The benchmark machine has no "
        "GPU, so a GPU's rate is not measured here: with `r` frames/s per GPU, `N` GPUs take "
        f"`{p['frames'] / 1e6:.0f}e6 / (N · r) + {fmt(p['units'])} · {fmt(overhead)} / N` "
        "seconds (where loading the network onto a GPU does not change the overhead).",
    ]
    return "\n".join(lines) + "\n"


def replace_block(text: str, block: str, begin: str = BEGIN, end: str = END) -> str | None:
    """``text`` with the block between ``begin`` and ``end`` replaced (None without them)."""
    if begin not in text or end not in text:
        return None
    head, rest = text.split(begin, 1)
    _, tail = rest.split(end, 1)
    return f"{head}{begin}\n{block}{end}{tail}"


def _held_out(entry: dict[str, Any]) -> str:
    """A base's held-out figures as text."""
    h = entry.get("held_out", {})
    if not h.get("evaluated"):
        return "not evaluated"
    n = f"{h.get('samples')} held-out instants"
    if entry["kind"] == "detector":
        views = int(h.get("n_views", 0))
        return (f"recall at IoU 0.5 {h['recall']:.3f}, median 3D centre error "
                f"{h['median_center_error']:.2f} mm ({views} views, {n})")  # fmt: skip
    p0 = f", P0 {h['jpe_p0_mm']:.2f} mm" if "jpe_p0_mm" in h else ""
    return f"median JPE {'P1 ' if p0 else ''}{h['jpe_p1_mm']:.2f} mm{p0} ({n})"


def card_block(manifest: Path = MANIFEST) -> str:
    """The model card's generated part: per shipped base its data, steps, figures, commands."""
    from freipose.models import read_manifest, total_steps

    lines = [
        "| base | file | size | optimizer steps | training sessions (seeds) | held-out figures |",
        "|---|---|---|---|---|---|",
    ]
    cmds = []
    for e in read_manifest(manifest):
        seeds = e["data"]["train_seeds"]
        lines.append(
            f"| {e['name']} | `{e['file']}` | {e['size_bytes'] / 1e6:.2f} MB | "
            f"{total_steps(e)} | {seeds[1] - seeds[0] + 1} ({seeds[0]}-{seeds[1]}) | "
            f"{_held_out(e)} |"
        )
        chain = [e["started_from"]["command"]] if "started_from" in e else []
        cmds += [f"# {e['name']} (exported {e['exported'][:10]})", *chain, e["command"]]
    held = sorted({tuple(e["data"]["held_out_seeds"]) for e in read_manifest(manifest)})
    lines += [
        "",
        "Held-out sessions: seeds " + ", ".join(f"{a}-{b}" for a, b in held) + " (never "
        "trained on). The commands that made the shipped weights, in order (a warm start "
        "continues from the weights of the command above it):",
        "",
        "```bash",
        *cmds,
        "```",
    ]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    """Write (or with ``--check`` compare) the page, the README, model card and tutorial blocks."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--check", action="store_true", help="exit 1 when a file is out of date")
    ap.add_argument("--results", type=Path, default=None, help="results folder [the repo's]")
    ap.add_argument("--page", type=Path, default=PAGE)
    ap.add_argument("--readme", type=Path, default=README)
    ap.add_argument("--models", type=Path, default=MODELS, help="the model card")
    ap.add_argument("--tutorial", type=Path, default=CLUSTER_DOC, help="the cluster tutorial")
    args = ap.parse_args(argv)
    records = load_results(folder=args.results or RESULTS)
    want = {args.page: page(records)}
    if args.readme.is_file():
        new = replace_block(args.readme.read_text(encoding="utf-8"), demo_block(records))
        if new is not None:
            want[args.readme] = new
    if args.models.is_file():
        card = args.models.read_text(encoding="utf-8")
        new = replace_block(card, card_block(), CARD_BEGIN, CARD_END)
        if new is not None:
            want[args.models] = new
    if args.tutorial.is_file():
        doc = args.tutorial.read_text(encoding="utf-8")
        new = replace_block(doc, cluster_block(records), CLUSTER_BEGIN, CLUSTER_END)
        if new is not None:
            want[args.tutorial] = new
    stale = [p for p, text in want.items()
             if not p.is_file() or p.read_text(encoding="utf-8") != text]  # fmt: skip
    if args.check:
        for p in stale:
            print(f"{p} is out of date: run python benchmarks/report.py", file=sys.stderr)
        return 1 if stale else 0
    for p in stale:
        atomic_write_text(p, want[p])
        print(f"wrote {p}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

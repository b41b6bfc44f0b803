"""A synthetic study predicted directly, through the local executor and through SLURM.

Renders ``--sessions`` synthetic sessions (several rats, several days; ``freipose synth``)
and predicts them with the shipped ``small`` voxel base (background subtraction finds the
rat) in three ways, at the same total number of cores ``--cores``:

* **direct**: one ``freipose predict`` process with ``--cores`` threads;
* **local**: ``--executor local``, ``--cores`` worker processes of one thread each;
* **slurm**: ``--executor slurm`` on the SLURM this machine reaches (``.ci/start-slurm``
  starts a single-node one), ``--cores`` one-core tasks at once.

Each mode runs ``--repeat`` times, in alternating order, and the medians are kept. It prints
each mode's throughput (frames/s), the ratios local/direct and slurm/direct (target >= 0.9),
the per-unit overhead (from a unit's submission to its first predicted frame, over the
units of the first wave, which wait for no other unit), whether the joined files are
identical (local and SLURM bit for bit; against the direct run, whose process runs more
threads and so sums in another order, the largest difference in mm; and, bit for bit, against
a direct run of the first ``--identity-sessions`` sessions with one thread, the units' thread
count), the share of frames where the animal was found (frames without it skip the network
and would flatter the throughput), the machine's load average, and the paper calculation of
the tutorial: core-hours and wall time of 1,000 hours of 7-camera video at 100 fps on N
one-core workers like this run's units, in units of 6000 frames, from the measured per-frame
cost (a SLURM unit's seconds per frame after its first batch, median over the units, scaled by
the number of views from this run's cameras to 7) and SLURM's per-unit overhead. On a shared
machine a process with more threads than free cores runs several times slower (see
``--threads``); the one-thread direct run's throughput is printed beside the others.

Usage::

    python benchmarks/cluster.py                      # 8 sessions of 600 frames, 2 cores (~12 min)
    python benchmarks/cluster.py --no-slurm --sessions 4 --frames 100
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from _results import write_result

MODES = ("direct", "local", "slurm")


def render(work: Path, sessions: int, frames: int, cameras: int) -> list[Path]:
    """Synthetic sessions: animal i // 2 + 1 on day i % 2 + 1 (kept when already rendered)."""
    from freipose.synth import SceneConfig, generate_session

    out = []
    for i in range(sessions):
        folder = work / "study" / f"rat{i // 2 + 1}_day{i % 2 + 1}"
        cfg = SceneConfig(n_cameras=cameras, frames=frames, size=(320, 256), seed=100 + i,
                          animal_seed=1000 + i // 2)  # fmt: skip
        generate_session(folder, cfg, progress=False)
        out.append(folder)
    return out


def predict(mode: str, sessions: list[Path], out: Path, args: argparse.Namespace,
            threads: int | None = None) -> float:  # fmt: skip
    """Run one mode into ``out``; returns its wall time in seconds.

    ``threads``: the direct run's threads (default ``--cores``).
    """
    from importlib.resources import files

    model = files("freipose.models") / "voxel_small.pt"
    cmd = [sys.executable, "-m", "freipose.cli.main", "-q", "predict", *map(str, sessions),
           "--model", str(model), "--method", "bgsub", "--device", "cpu",
           "-o", str(out)]  # fmt: skip
    if mode == "direct":
        cmd += ["--threads", str(threads or args.cores)]
    else:
        cfg = out.parent / f"{out.name}.toml"
        cfg.write_text(
            f'[cluster]\nexecutor = "{mode}"\ncpus = 1\narray_parallelism = {args.cores}\n'
            f"chunk_frames = {args.chunk_frames}\npoll_s = 1.0\nmem_gb = 2\ntime_min = 60\n"
        )
        cmd += ["--cluster", str(cfg)]
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True)
    return time.perf_counter() - t0


def first_wave_overheads(out: Path, cores: int) -> list[float]:
    """Seconds from submission to the first predicted frame of the units of the first wave."""
    events = [json.loads(x) for x in (out / ".jobs" / "journal.jsonl").read_text().splitlines()]
    submitted = {e["unit"]: e["t"] for e in events if e["event"] == "submitted"}
    starts = []
    for unit, t_sub in submitted.items():
        rec = json.loads((out / ".jobs" / "units" / f"{unit}.json").read_text())
        if rec.get("first_frame_at"):
            starts.append((rec["started_at"], rec["first_frame_at"] - t_sub))
    return [o for _, o in sorted(starts)[:cores]]


def unit_frame_seconds(out: Path, batch: int = 8) -> float:
    """Median seconds per frame of the units after their first batch (one core each)."""
    per = []
    for f in (out / ".jobs" / "units").glob("*.json"):
        rec = json.loads(f.read_text())
        if rec.get("first_frame_at") and rec.get("frames", 0) > batch:
            end = rec["started_at"] + rec["seconds"]
            per.append((end - rec["first_frame_at"]) / (rec["frames"] - batch))
    return statistics.median(per)


def compare(a: Path, b: Path, names: list[str]) -> tuple[bool, float]:
    """(bitwise equal, largest difference of the poses in mm) over the sessions' files."""
    import h5py

    equal, worst = True, 0.0
    for n in names:
        with h5py.File(a / f"{n}.poses.h5", "r") as fa, h5py.File(b / f"{n}.poses.h5", "r") as fb:
            pa, pb = fa["poses"][()], fb["poses"][()]
            equal &= bool(np.array_equal(pa, pb, equal_nan=True))
            both = np.isfinite(pa) & np.isfinite(pb)
            if both.any():
                worst = max(worst, float(np.abs(pa - pb)[both].max()))
            equal &= bool(np.array_equal(np.isfinite(pa), np.isfinite(pb)))
    return equal, worst


def found_share(folder: Path, names: list[str]) -> float:
    """The share of frames whose pose was predicted (the animal found) over the sessions."""
    import h5py

    found = total = 0
    for n in names:
        with h5py.File(folder / f"{n}.poses.h5", "r") as f:
            status = f["extra/status"][()]
            found += int((status == 0).sum())
            total += status.size
    return found / total


def paper(per_frame_s: float, overhead_s: float, chunk: int, cameras: int) -> dict:
    """1,000 h of 7-camera 100 fps video on N one-core workers like this run's units.

    Args:
        per_frame_s: one core's seconds per multi-view frame of ``cameras`` views.
        overhead_s: a unit's overhead (submission to first frame).
        chunk: frames per unit.
        cameras: the views of the measured frames (the cost is scaled to 7 by views).
    """
    frames = 1000 * 3600 * 100
    frame_s = per_frame_s * 7 / cameras  # the network's cost grows with the number of views
    units = frames / chunk
    unit_s = chunk * frame_s + overhead_s
    return {
        "frames": frames,
        "core_s_per_frame_7cams": frame_s,
        "units": units,
        "overhead_share": overhead_s / unit_s,
        "core_hours": units * unit_s / 3600,
        **{f"wall_hours_on_{n}_workers": units * unit_s / n / 3600 for n in (100, 1000)},
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sessions", type=int, default=8)
    ap.add_argument("--frames", type=int, default=600)
    ap.add_argument("--cameras", type=int, default=4)
    ap.add_argument("--chunk-frames", type=int, default=600, help="frames per unit")
    ap.add_argument("--cores", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--identity-sessions", type=int, default=1,
                    help="sessions of the one-thread direct run that the units must equal "
                    "bit for bit (0: none)")  # fmt: skip
    ap.add_argument("--no-slurm", action="store_true", help="leave SLURM out")
    ap.add_argument("--work", type=Path, default=Path("cluster_bench"))
    args = ap.parse_args()
    modes = [m for m in MODES if not (m == "slurm" and args.no_slurm)]
    sessions = render(args.work, args.sessions, args.frames, args.cameras)
    names = [s.name for s in sessions]
    total = args.sessions * args.frames
    times: dict[str, list[float]] = {m: [] for m in modes}
    overheads: dict[str, list[float]] = {m: [] for m in modes if m != "direct"}
    last: dict[str, Path] = {}
    load_start = os.getloadavg()[0]
    for r in range(args.repeat):
        for mode in modes if r % 2 == 0 else modes[::-1]:
            out = args.work / f"{mode}_{r}"
            subprocess.run(["rm", "-rf", str(out)], check=True)
            times[mode].append(predict(mode, sessions, out, args))
            if mode != "direct":
                overheads[mode] += first_wave_overheads(out, args.cores)
            last[mode] = out
    load = os.getloadavg()[0]
    fps = {m: total / statistics.median(t) for m, t in times.items()}
    figures: dict = {"frames": total, "frames_per_s": fps,
                     "found_share": found_share(last["direct"], names),
                     "load_average_1min": {"start": load_start, "end": load}}  # fmt: skip
    for m in modes[1:]:
        figures[f"ratio_{m}_to_direct"] = fps[m] / fps["direct"]
        figures[f"overhead_s_{m}"] = statistics.median(overheads[m])
        equal, worst = compare(last["direct"], last[m], names)
        figures[f"identical_to_direct_{m}"] = equal
        figures[f"max_difference_mm_{m}"] = worst
    if "slurm" in modes:
        figures["identical_local_slurm"] = compare(last["local"], last["slurm"], names)[0]
    if args.identity_sessions:  # the same math with the units' one thread: bit for bit
        ref = args.work / "direct_one_thread"
        subprocess.run(["rm", "-rf", str(ref)], check=True)
        seconds = predict("direct", sessions[: args.identity_sessions], ref, args, threads=1)
        figures["frames_per_s_one_thread_direct"] = args.identity_sessions * args.frames / seconds
        for m in modes[1:]:
            figures[f"identical_to_one_thread_direct_{m}"] = compare(
                ref, last[m], names[: args.identity_sessions]
            )[0]
    units_mode = "slurm" if "slurm" in modes else "local"
    per_frame = unit_frame_seconds(last[units_mode])  # a one-core unit's seconds per frame
    figures[f"unit_s_per_frame_{units_mode}"] = per_frame
    figures["paper_1000h_7cams"] = paper(per_frame, figures[f"overhead_s_{units_mode}"],
                                         6000, args.cameras)  # fmt: skip
    print(json.dumps(figures, indent=1))
    write_result("cluster", figures, extra={k: v for k, v in vars(args).items() if k != "work"})


if __name__ == "__main__":
    main()

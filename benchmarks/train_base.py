r"""Train the pretrained base models that FreiPose ships in ``freipose/models`` (resumable).

Renders many varied synthetic sessions with ``freipose.synth`` (3 to 8 cameras, every coat,
several image sizes and arena sizes, stimulated and unstimulated animals (from session
``FIRST_MOVING`` on, three in four lift or oscillate a paw, mostly a front one, or the head),
and the generator's domain randomisation where it has one), then trains, in turns, the ``small``
voxel network, the triangulation baseline's 2D network (same preset) and the box detector
(the demo's architecture), each in chunks of steps that end with a checkpoint. After every
chunk the newest weights are exported (without optimizer state) to ``--export`` together
with ``bases.json``: the provenance of every base (the command, the steps, the data seeds,
the held-out figures).

Running the same command again continues where it stopped (the trainers' resume: weights,
optimizer, step, random state); ``--until HH:MM`` (UTC) or ``--minutes`` stops it at a
chunk boundary. A later session without the work folder regenerates the same data (the
seeds fix it) and, with ``--warm-start``, continues from the shipped weights with a fresh
optimizer. ``--networks`` trains some of the three only (the others keep their exported
weights and manifest entries).

Seeds: training sessions use ``10000 + i``, the held-out sessions ``10900 + j``; the demo
uses 1 and 2, ``benchmarks/accuracy.py`` 101+ and 9001, the tests small numbers, so no
evaluation anywhere sees a session the bases were trained on.

Example (the command that made the shipped weights, see docs/models.md)::

    OMP_NUM_THREADS=1 nice -n 5 python benchmarks/train_base.py --work ../base_train \\
        --until 00:30
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime as dt
import json
import logging
import shlex
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

SEED_START = 10_000
HELD_OUT_SEED_START = 10_900
SIZES = ((320, 256), (384, 288), (256, 208), (320, 240))
APPEARANCES = ("hooded", "albino", "random")
STIM_EFFECTS = ("oscillate", "lift", "freeze")
STIM_PARTS = ("Paw Front Right", "Paw Front Left", "Paw Back Right", "Head")
#: sessions from this index on draw their stimulation: lifted and oscillating paws (the
#: front ones most), which the first sessions had too rarely for the base to follow them
FIRST_MOVING = 16
MOVED_PARTS = ("Paw Front Right", "Paw Front Left", "Paw Back Right", "Paw Back Left", "Head")
MOVED_PART_SHARES = (0.3, 0.3, 0.15, 0.15, 0.1)
MOVED_EFFECT_SHARES = (0.45, 0.45, 0.1)  # of STIM_EFFECTS
#: the networks the script trains, in the order of their jobs
NETWORKS = ("voxel", "baseline", "detector")
#: the demo's detector architecture (``freipose.demo.presets``), so the demo can start from it
DETECTOR_ARCH = {"input_size": 128, "width": 0.35, "neck_channels": 24}

log = logging.getLogger("train_base")


def scene_config(seed: int, index: int, frames: int, fps: float) -> Any:
    """The varied synthetic scene of training (or held-out) session number ``index``."""
    from freipose.synth import SceneConfig
    from freipose.synth.stimulation import StimulationConfig

    rng = np.random.default_rng(seed)
    kw: dict[str, Any] = dict(
        frames=frames,
        fps=fps,
        seed=seed,
        n_cameras=3 + index % 6,
        size=SIZES[index % len(SIZES)],
        appearance=APPEARANCES[index % len(APPEARANCES)],
        arena_size=(float(rng.uniform(480, 720)),) * 2,
    )
    if index < FIRST_MOVING:  # the first sessions: every other one stimulated, in turn
        part = STIM_PARTS[(index // 2) % len(STIM_PARTS)]
        effect = STIM_EFFECTS[(index // 2) % len(STIM_EFFECTS)] if index % 2 else None
    else:  # later sessions: three in four move a paw or the head (lifted, oscillating)
        part = str(rng.choice(MOVED_PARTS, p=MOVED_PART_SHARES))
        effect = str(rng.choice(STIM_EFFECTS, p=MOVED_EFFECT_SHARES)) if index % 4 else None
    if effect is not None:
        kw["stimulation"] = StimulationConfig(
            body_part=part,
            effect=effect,
            frequency_hz=float(rng.uniform(3, 10)),
            amplitude_mm=float(rng.uniform(10, 35)),
            duration_s=2.0,
            spacing_s=2.0,
            onset_s=1.0,
        )
    if index % 3 == 0:  # one session in three like the demo's: 7 cameras, 320x256, a rat
        kw.update(n_cameras=7, size=(320, 256), arena_size=(600.0, 600.0))
    elif "randomize" in {f.name for f in dataclasses.fields(SceneConfig)}:
        kw["randomize"] = True  # the generator's domain randomisation, where it has one
    return SceneConfig(**kw)


def make_data(work: Path, n_train: int, n_eval: int, frames: int, fps: float) -> tuple:
    """Render (or keep) the training and held-out sessions; returns their labels paths."""
    from freipose.synth import generate_session

    def one(seed: int, index: int) -> Path:
        out = work / "data" / f"s{seed}"
        if not (out / "labels.h5").is_file():
            generate_session(out, scene_config(seed, index, frames, fps), progress=False)
        return out / "labels.h5"

    train = [one(SEED_START + i, i) for i in range(n_train)]
    held = [one(HELD_OUT_SEED_START + j, j + 1) for j in range(n_eval)]
    return train, held


class Concat:
    """Samples of several sources one after the other (sessions with other cameras)."""

    def __init__(self, sources: list[Any]):
        self.sources = sources
        self.offsets = np.cumsum([0] + [len(s) for s in sources])

    def __len__(self) -> int:
        return int(self.offsets[-1])

    def __getitem__(self, index: int) -> Any:
        k = int(np.searchsorted(self.offsets, index, side="right") - 1)
        sample = self.sources[k][index - int(self.offsets[k])]
        sample["index"] = index
        return sample


def pose_sources(paths: list[Path]) -> tuple[Concat, np.ndarray]:
    """One source over the sessions and the indices of the samples with 3D labels."""
    from freipose.nn.dataset import MultiViewDataset
    from freipose.nn.evaluate import usable_indices

    sets = [MultiViewDataset(p, root=p.parent) for p in paths]
    src = Concat(sets)
    idx = np.concatenate([usable_indices(s) + int(o) for s, o in zip(sets, src.offsets)])
    return src, idx


def pose_config(kind: str, steps: int, decay_steps: int = 0) -> Any:
    """The ``small`` preset with a long, slowly decaying schedule for the base.

    The learning rate (1e-3) drops tenfold every ``decay_steps`` steps (0: at 2/3 of
    ``steps``).
    """
    from freipose.nn.config import config_from_dict

    decay = decay_steps if decay_steps > 0 else max(1, steps * 2 // 3)
    return config_from_dict({
        "model": {"preset": "small", "kind": kind, "init": "scratch"},
        "schedule": {
            "steps": steps, "lr": 1e-3, "lr_decay_steps": decay,
            "refine_start": 0.01, "checkpoint_every": 250, "eval_every": 1000,
            "eval_samples": 24, "seed": 10_000,
        },
    })  # fmt: skip


@dataclass
class Job:
    """One network's resumable training: its folder, total steps and share of the time."""

    name: str
    steps: int
    share: float
    seconds: float = 0.0
    done: int = 0
    decay_steps: int = 0


class Trainer:
    """Chunks of training for the voxel network, the baseline and the detector."""

    def __init__(self, args: argparse.Namespace, train: list[Path], held: list[Path]):
        from freipose.skeleton import load_skeleton

        self.args = args
        self.work = args.work
        self.train_paths, self.held_paths = train, held
        self.skeleton = load_skeleton("rat")
        self.src, self.idx = pose_sources(train)
        self.ev, ev_idx = pose_sources(held)
        self.ev_idx = ev_idx[np.linspace(0, len(ev_idx) - 1, 24).round().astype(int)]
        self._views: Any = None

    def run_dir(self, name: str) -> Path:
        """The run folder of ``name``."""
        return self.work / "runs" / name

    def pose_chunk(self, job: Job, chunk: int) -> int:
        """Train the voxel network or the baseline ``chunk`` more steps; returns the step."""
        from freipose.nn.checkpoint import read_checkpoint
        from freipose.nn.train import train_pose

        cfg = pose_config(job.name, job.steps, job.decay_steps)
        run = self.run_dir(job.name)
        resume = (run / "checkpoint.pt").is_file()
        if not resume and self.args.warm_start:
            cfg = dataclasses.replace(
                cfg, model=dataclasses.replace(cfg.model, init=str(self.shipped(job.name)))
            )
        path = train_pose(
            cfg, run, self.src, self.skeleton, self.ev, train_indices=self.idx,
            eval_indices=self.ev_idx, resume=resume, progress=False,
            stop_after=job.done + chunk,
        )  # fmt: skip
        return int(read_checkpoint(path)["step"])

    def detector_cfg(self, job: Job) -> Any:
        """The detector's training settings (the demo's architecture)."""
        from freipose.detect.train import DetectorTrainConfig

        init = str(self.shipped("detector")) if self.args.warm_start else "scratch"
        return DetectorTrainConfig(
            **DETECTOR_ARCH, steps=job.steps, batch_size=8, lr=2e-3, warmup_steps=100,
            checkpoint_every=100, log_every=50, max_images=4000, cube_size=320.0,
            seed=10_000, init=init,
        )  # fmt: skip

    def detector_chunk(self, job: Job, chunk: int) -> int:
        """Train the detector ``chunk`` more steps; returns the step."""
        from freipose.detect.train import LAST, collect_views, fit
        from freipose.nn.dataset import MultiViewDataset

        cfg = self.detector_cfg(job)
        run = self.run_dir("detector")
        if self._views is None:
            from freipose.detect.train import ViewImages

            parts = []
            per = max(1, cfg.max_images // (5 * len(self.train_paths)))
            for p in self.train_paths:
                ds = MultiViewDataset(p, root=p.parent)
                parts.append(collect_views(ds, np.linspace(0, len(ds) - 1, per).round(), cfg))
            self._views = ViewImages(
                [im for v in parts for im in v.images], np.concatenate([v.boxes for v in parts])
            )
            log.info("detector: %d training views", len(self._views.images))
        fit(self._views, cfg, "cpu", run, resume=(run / LAST).is_file(), progress=False,
            stop_after=job.done + chunk)  # fmt: skip
        from freipose.detect.detector import load_checkpoint

        return int(load_checkpoint(run / LAST)["step"])

    def shipped(self, name: str) -> Path:
        """The shipped base file of ``name`` in the export folder."""
        return self.args.export / f"{name}_small.pt"


def current_step(trainer: Trainer, job: Job) -> int:
    """The step of the newest checkpoint of ``job`` (0 without one)."""
    run = trainer.run_dir(job.name)
    if job.name == "detector":
        from freipose.detect.detector import load_checkpoint
        from freipose.detect.train import LAST

        return int(load_checkpoint(run / LAST)["step"]) if (run / LAST).is_file() else 0
    from freipose.nn.checkpoint import read_checkpoint

    p = run / "checkpoint.pt"
    return int(read_checkpoint(p)["step"]) if p.is_file() else 0


def _held_out_pose(trainer: Trainer, name: str, path: Path) -> dict[str, float]:
    """Median JPE (mm) of a pose checkpoint on the held-out samples."""
    from freipose.nn.checkpoint import load_checkpoint
    from freipose.nn.evaluate import jpe, predict_dataset

    model, _, _ = load_checkpoint(path)
    pred = predict_dataset(model, trainer.ev, trainer.ev_idx, batch_size=2)
    keys = ("P0", "P1") if name == "voxel" else ("P1",)
    return {f"jpe_{k.lower()}_mm": float(np.nanmedian(jpe(pred[k], pred["gt"]))) for k in keys}


def _held_out_detector(trainer: Trainer, path: Path) -> dict[str, float]:
    """Recall at IoU 0.5 and the median 3D centre error of a detector on held-out instants."""
    from freipose.detect.detector import Detector
    from freipose.detect.evaluate import evaluate_source
    from freipose.detect.multiview import ConsistencyConfig

    det = Detector.load(path)
    samples = (trainer.ev[int(i)] for i in trainer.ev_idx)
    m = evaluate_source(det, samples, margin=0.1, consistency=ConsistencyConfig(cube_size=320.0))
    return {k: float(v) for k, v in dataclasses.asdict(m).items() if isinstance(v, (int, float))}


def _export_one(trainer: Trainer, job: Job, dest: Path) -> int:
    """Write the newest weights of ``job`` to ``dest`` without optimizer state; the step."""
    import torch

    from freipose.io.atomic import atomic_path

    run = trainer.run_dir(job.name)
    if job.name == "detector":
        from freipose.detect.detector import load_checkpoint
        from freipose.detect.train import LAST

        ckpt = load_checkpoint(run / LAST)
        keep = {k: v for k, v in ckpt.items() if k not in ("optimizer", "scheduler")}
        keep["kind"] = "detector"
    else:
        from freipose.nn.checkpoint import read_checkpoint

        ckpt = read_checkpoint(run / "checkpoint.pt")
        keep = {k: v for k, v in ckpt.items() if k not in ("optimizer", "rng")}
    with atomic_path(dest) as tmp:
        torch.save(keep, tmp)
    return int(ckpt["step"])


def _validation_rows(path: Path) -> list[list[float]]:
    """``[step, val_jpe_p0, val_jpe_p1]`` of the rows of a pose ``log.csv`` that have them."""
    import csv

    if not path.is_file():
        return []
    with path.open() as f:
        rows = [r for r in csv.DictReader(f) if r.get("val_jpe_p1")]
    return [[int(r["step"]), float(r["val_jpe_p0"]), float(r["val_jpe_p1"])] for r in rows]


def export_all(
    trainer: Trainer, jobs: list[Job], command: str, evaluate: bool, trained: set[str]
) -> None:
    """Export the networks to ``--export`` and rewrite its ``bases.json``.

    Networks not in ``trained`` (this run's ``--networks``) that are already exported keep
    their weights and entry.
    """
    from freipose.models import MANIFEST, read_manifest, total_steps

    export = trainer.args.export
    old = {b["name"]: b for b in read_manifest(export / MANIFEST)}
    entries = []
    for job in jobs:
        run = trainer.run_dir(job.name)
        if current_step(trainer, job) == 0 or (job.name not in trained and job.name in old):
            if job.name in old:  # not trained here: its weights and entry stay as they are
                entries.append(old[job.name])
            continue
        dest = trainer.shipped(job.name)
        step = _export_one(trainer, job, dest)
        entry = dict(old.get(job.name, {}))
        figures = dict(entry.get("held_out", {})) if entry.get("steps") == step else {}
        if evaluate and not figures.get("evaluated"):
            ev = (_held_out_detector(trainer, dest) if job.name == "detector"
                  else _held_out_pose(trainer, job.name, dest))  # fmt: skip
            figures = {**ev, "evaluated": True, "samples": int(len(trainer.ev_idx))}
        # an --export-only run keeps the command that trained the weights
        made_by = entry.get("command") if trainer.args.export_only else None
        first_of_warm_start = (
            trainer.args.warm_start
            and not trainer.args.export_only
            and bool(entry)
            and entry.get("work") != str(trainer.work)
        )
        if first_of_warm_start:
            # the first export of a warm start (another run folder made the entry): remember
            # the weights it started from (an --export-only run trains nothing)
            keep = ("command", "exported", "held_out")
            entry["started_from"] = {"steps": total_steps(entry)} | {
                k: entry[k] for k in keep if k in entry
            }
        entry.update(_provenance(trainer, job, dest, step, made_by or command))
        entry["held_out"] = figures
        entry["validation"] = _validation_rows(run / "log.csv")
        entries.append(entry)
    (export / MANIFEST).write_text(json.dumps({"bases": entries}, indent=2) + "\n")


def _provenance(trainer: Trainer, job: Job, dest: Path, step: int, command: str) -> dict:
    """The manifest entry of ``job`` apart from its held-out figures."""
    a = trainer.args
    if job.name == "detector":
        arch = trainer.detector_cfg(job).model_config().to_dict()
        schedule: dict[str, Any] = {"steps": job.steps, "batch_size": 8, "lr": 2e-3}
    else:
        from freipose.nn.config import config_to_dict

        tables = config_to_dict(pose_config(job.name, job.steps, job.decay_steps))
        arch = {k: v for k, v in tables["model"].items() if k not in ("init", "pretrained")}
        schedule = tables["schedule"]
    return {
        "name": job.name,
        "kind": job.name,
        "file": dest.name,
        "architecture": arch,
        "skeleton": list(trainer.skeleton.keypoints) if job.name != "detector" else None,
        "steps": step,
        "work": str(a.work),
        "schedule": schedule,
        "size_bytes": dest.stat().st_size,
        "command": command,
        "data": {
            "generator": "freipose.synth",
            "train_seeds": [SEED_START, SEED_START + a.sessions - 1],
            "held_out_seeds": [HELD_OUT_SEED_START, HELD_OUT_SEED_START + a.held_out - 1],
            "frames_per_session": a.frames,
            "fps": a.fps,
            "cameras": "3 to 8",
            "sizes": [list(s) for s in SIZES],
            "appearances": APPEARANCES,
            "stimulation": (
                f"sessions 0-{FIRST_MOVING - 1}: every other one, parts and effects in turn; "
                f"from {FIRST_MOVING} on: 3 in 4, the part drawn from {MOVED_PARTS} with "
                f"shares {MOVED_PART_SHARES}, the effect drawn from {STIM_EFFECTS} with shares "
                f"{MOVED_EFFECT_SHARES}"
            ),
        },
        "exported": dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
    }


def _deadline(args: argparse.Namespace) -> float:
    """The wall-clock time (epoch seconds) after which no new chunk starts."""
    now = time.time()
    end = now + args.minutes * 60 if args.minutes else float("inf")
    if args.until:
        hh, mm = (int(v) for v in args.until.split(":"))
        today = dt.datetime.now(dt.timezone.utc)
        t = today.replace(hour=hh, minute=mm, second=0, microsecond=0)
        if t.timestamp() < now - 3600:
            t += dt.timedelta(days=1)
        end = min(end, t.timestamp())
    return end


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", type=Path, default=Path("bench/base"), help="data and run folders")
    ap.add_argument(
        "--export", type=Path, default=Path(__file__).parents[1] / "freipose" / "models"
    )
    ap.add_argument("--sessions", type=int, default=16, help="training sessions")
    ap.add_argument("--held-out", type=int, default=2, help="held-out sessions")
    ap.add_argument("--frames", type=int, default=100, help="frames per session")
    ap.add_argument("--fps", type=float, default=5.0, help="frame rate (label spacing)")
    ap.add_argument("--voxel-steps", type=int, default=30_000)
    ap.add_argument("--baseline-steps", type=int, default=30_000)
    ap.add_argument("--detector-steps", type=int, default=8_000)
    ap.add_argument("--voxel-decay-steps", type=int, default=0,
                    help="the learning rate drops tenfold every N steps (0: at 2/3 of the "
                    "steps); a resumed run follows the new schedule from its step on")  # fmt: skip
    ap.add_argument("--baseline-decay-steps", type=int, default=0,
                    help="the same for the baseline")  # fmt: skip
    ap.add_argument("--chunk", type=int, default=200, help="steps per turn (pose networks)")
    ap.add_argument("--until", default="", help="UTC HH:MM after which no chunk starts")
    ap.add_argument("--minutes", type=float, default=0.0, help="stop after this many minutes")
    ap.add_argument("--warm-start", action="store_true",
                    help="without a run folder, start from the shipped weights")  # fmt: skip
    ap.add_argument("--export-only", action="store_true", help="export and evaluate, no training")
    ap.add_argument("--networks", default=",".join(NETWORKS),
                    help="the networks to train (comma-separated); the others keep their "
                    "shipped weights")  # fmt: skip
    ap.add_argument("--threads", type=int, default=1, help="PyTorch threads")
    return ap


def main(argv: list[str] | None = None) -> int:
    """Render the data, train the bases in turns until the deadline, export them."""
    import torch

    args = _parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    torch.set_num_threads(args.threads)
    from freipose.workers import keep_freed_memory

    keep_freed_memory()  # as the commands do (cli/_threads.py)
    names = {n.strip() for n in args.networks.split(",") if n.strip()}
    if not names <= set(NETWORKS):
        raise SystemExit(f"--networks: expected some of {', '.join(NETWORKS)}; got {args.networks}")
    t0 = time.perf_counter()
    train, held = make_data(args.work, args.sessions, args.held_out, args.frames, args.fps)
    log.info("data: %d training, %d held-out sessions (%.0f s)", len(train), len(held),
             time.perf_counter() - t0)  # fmt: skip
    trainer = Trainer(args, train, held)
    jobs = [
        Job("voxel", args.voxel_steps, 0.5, decay_steps=args.voxel_decay_steps),
        Job("baseline", args.baseline_steps, 0.25, decay_steps=args.baseline_decay_steps),
        Job("detector", args.detector_steps, 0.25),
    ]
    for job in jobs:
        job.done = current_step(trainer, job)
    end = _deadline(args)
    command = shlex.join([sys.executable.rsplit("/", 1)[-1], *sys.argv])
    while not args.export_only and time.time() < end:
        todo = [j for j in jobs if j.done < j.steps and j.name in names]
        if not todo:
            break
        job = min(todo, key=lambda j: j.seconds / j.share)
        t = time.perf_counter()
        if job.name == "detector":
            job.done = trainer.detector_chunk(job, max(1, args.chunk // 2))
        else:
            job.done = trainer.pose_chunk(job, args.chunk)
        job.seconds += time.perf_counter() - t
        log.info("%s: step %d of %d (%.0f s this session)", job.name, job.done, job.steps,
                 job.seconds)  # fmt: skip
        export_all(trainer, jobs, command, evaluate=False, trained=names)
    export_all(trainer, jobs, command, evaluate=True, trained=names)
    _record(args, names)
    return 0


def _record(args: argparse.Namespace, names: set[str]) -> None:
    """The held-out figures of the networks this run trained, as exported, as a result."""
    from _results import write_result

    from freipose.models import MANIFEST, read_manifest, total_steps

    figures = {}
    for entry in read_manifest(args.export / MANIFEST):
        held = entry.get("held_out", {})
        if entry["name"] in names and held.get("evaluated"):
            numbers = {k: v for k, v in held.items() if type(v) in (int, float)}
            figures[entry["name"]] = {"steps": total_steps(entry), **numbers}
    if figures:
        settings = {k: str(v) for k, v in vars(args).items() if k not in ("until", "minutes")}
        write_result("train_base", figures, extra=settings)


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).parent))
    raise SystemExit(main())

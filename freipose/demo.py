"""``freipose demo``: the whole FreiPose workflow on synthetic recordings, with a report.

Steps (each calls the same library code as the corresponding ``freipose`` command):

1. ``synth``     render a calibration recording (a ChArUco board waved through the arena)
                 and stimulated sessions of a rat filmed by 7 cameras (``freipose synth``);
2. ``calibrate`` calibrate the cameras from the board videos (``freipose calib``) and compare
                 with the true rig (camera centre, rotation and focal length errors);
3. ``labels``    import labels of a few hundred time instants: 2D labels of the visible
                 keypoints (with 1 px labelling noise) triangulated with the calibrated rig
                 (what ``freipose labels`` produces from a 2D labelling tool);
4. ``train``     train the box detector, the voxel network and the triangulation baseline
                 (``freipose train --stage detector|pose|baseline``);
5. ``predict``   predict every session to ``poses/<session>.poses.h5`` (``freipose predict``)
                 and render an overlay clip (``freipose render``);
6. ``evaluate``  joint position errors against the true 3D keypoints, voxel network vs.
                 triangulation baseline (``freipose eval``) and of the whole pipeline;
7. ``analyze``   behavioural variables and attribution of the stimulation effect
                 (``freipose analyze``);
8. ``report``    ``OUTDIR/report.html`` with every step's figures.

Every finished step leaves ``OUTDIR/.demo/<step>.done`` (JSON: the preset and the step's
results); a rerun skips finished steps, and the library's own resumability (rendered videos,
training checkpoints, chunked predictions, cached variables) continues an interrupted step.
"""

from __future__ import annotations

import dataclasses
import html
import json
import logging
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from freipose import __version__
from freipose.geometry.alignment import rig_errors as geometry_rig_errors
from freipose.io.atomic import atomic_write_text

log = logging.getLogger(__name__)

STEPS = ("synth", "calibrate", "labels", "train", "predict", "evaluate", "analyze", "report")
MARKER_DIR = ".demo"
STIM_PART = "Paw Front Right"


@dataclass(frozen=True)
class DemoSession:
    """One synthetic recording: its name, seed and role in the study."""

    name: str
    seed: int
    split: str  # "train" (labels come from it) or "test" (held out: evaluation)


@dataclass(frozen=True)
class DemoPreset:
    """Sizes of a demo run.

    Attributes:
        name: preset name.
        size: image size (width, height) of the 7 cameras.
        fps: frame rate of the sessions.
        session_frames: frames of each session.
        calibration_frames: frames of the board videos.
        sessions: the recordings (one animal, one condition, train and test splits).
        stimulation: ``freipose.synth`` stimulation protocol as a dict.
        label_instants: labeled time instants imported from the train sessions.
        eval_instants: held-out time instants with true 3D keypoints for ``freipose eval``.
        pose: ``[model]`` preset and ``[schedule]`` overrides of the voxel network.
        baseline_steps: training steps of the triangulation baseline.
        detector: the ``[detector]`` table.
        analysis: ``AttributionConfig`` fields; ``stft_window``: STFT window in frames.
        overlay_frames: frames of the overlay clip.
        batch: time steps per prediction batch.
        n_cameras: cameras of the rig.
        detection: how ``predict`` finds the animal: ``"detector"`` (the trained detector)
            or ``"bgsub"`` (background subtraction; for ``tiny``, whose few-step detector
            finds nothing).
    """

    name: str
    size: tuple[int, int]
    fps: float
    session_frames: int
    calibration_frames: int
    sessions: tuple[DemoSession, ...]
    stimulation: dict[str, Any]
    label_instants: int
    eval_instants: int
    pose: dict[str, Any]
    baseline_steps: int
    detector: dict[str, Any]
    analysis: dict[str, Any]
    stft_window: int
    overlay_frames: int
    batch: int = 8
    n_cameras: int = 7
    detection: str = "detector"

    def to_dict(self) -> dict[str, Any]:
        return json.loads(json.dumps(dataclasses.asdict(self)))


_SESSIONS = (DemoSession("rat1_day1", 1, "train"), DemoSession("rat1_day2", 2, "test"))

PRESETS: dict[str, DemoPreset] = {
    # End to end in a few minutes (CI): everything tiny, numbers meaningless.
    "tiny": DemoPreset(
        name="tiny",
        size=(320, 256),
        fps=25.0,
        session_frames=60,
        calibration_frames=70,
        sessions=_SESSIONS,
        stimulation=dict(
            body_part=STIM_PART,
            effect="oscillate",
            frequency_hz=5.0,
            amplitude_mm=20.0,
            duration_s=0.8,
            spacing_s=2.0,
            onset_s=0.6,
        ),  # fmt: skip
        label_instants=24,
        eval_instants=8,
        pose=dict(preset="tiny", steps=6, checkpoint_every=3, eval_every=3, eval_samples=4),
        baseline_steps=4,
        detector=dict(
            input_size=64,
            width=0.25,
            neck_channels=8,
            steps=4,
            batch_size=4,
            checkpoint_every=2,
            log_every=1,
            max_images=60,
            max_eval_instants=4,
            warmup_steps=1,
            cube_size=320.0,
        ),  # fmt: skip
        analysis=dict(onset_delay_s=0.2, margin_s=0.3, pre_s=0.5, post_s=0.5, top=3),
        stft_window=16,
        overlay_frames=10,
        batch=8,
        detection="bgsub",
    ),
    # The default: under 15 minutes on a 2-core CPU.
    "small": DemoPreset(
        name="small",
        size=(320, 256),
        fps=25.0,
        session_frames=750,
        calibration_frames=80,
        sessions=_SESSIONS,
        stimulation=dict(
            body_part=STIM_PART,
            effect="oscillate",
            frequency_hz=5.0,
            amplitude_mm=30.0,
            duration_s=2.0,
            spacing_s=2.0,
            onset_s=1.0,
        ),  # fmt: skip
        label_instants=300,
        eval_instants=60,
        pose=dict(
            preset="small",
            steps=300,
            lr=1e-3,
            lr_decay_steps=200,
            checkpoint_every=50,
            eval_every=100,
            eval_samples=16,
            log_every=10,
        ),  # fmt: skip
        baseline_steps=200,
        detector=dict(
            input_size=128,
            width=0.35,
            neck_channels=24,
            steps=250,
            batch_size=8,
            checkpoint_every=50,
            log_every=10,
            max_images=1400,
            max_eval_instants=40,
            warmup_steps=20,
            cube_size=320.0,
        ),  # fmt: skip
        analysis=dict(onset_delay_s=0.6, margin_s=0.5, pre_s=1.0, post_s=1.0, top=6),
        stft_window=32,
        overlay_frames=50,
        batch=8,
    ),
}


@dataclass
class DemoContext:
    """Paths and settings shared by the steps of one demo run."""

    out: Path
    preset: DemoPreset
    device: str = "cpu"
    say: Callable[[str], None] = print
    progress: bool | None = None
    results: dict[str, dict[str, Any]] = field(default_factory=dict)

    @property
    def recordings(self) -> Path:
        return self.out / "recordings"

    def session_dir(self, name: str) -> Path:
        return self.recordings / name

    @property
    def calib_videos(self) -> Path:
        return self.session_dir(self.preset.sessions[0].name) / "calibration"

    @property
    def calibration(self) -> Path:
        return self.out / "calibration" / "calibration.toml"

    @property
    def train_dir(self) -> Path:
        return self.out / "train"

    @property
    def poses_dir(self) -> Path:
        return self.out / "poses"


# --------------------------------------------------------------------------- markers
def _marker(out: Path, step: str) -> Path:
    return out / MARKER_DIR / f"{step}.done"


def _read_marker(out: Path, step: str) -> dict[str, Any] | None:
    p = _marker(out, step)
    if not p.is_file():
        return None
    try:
        return json.loads(p.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError):
        return None


def _write_marker(ctx: DemoContext, step: str, results: dict[str, Any], seconds: float) -> None:
    p = _marker(ctx.out, step)
    p.parent.mkdir(parents=True, exist_ok=True)
    doc = {
        "step": step,
        "preset": ctx.preset.to_dict(),
        "freipose_version": __version__,
        "seconds": round(seconds, 2),
        "results": results,
    }
    atomic_write_text(p, json.dumps(doc, indent=2, default=_json_default) + "\n")


def _json_default(o: Any) -> Any:
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serializable: {type(o)}")


def _check_outdir(out: Path, preset: DemoPreset) -> None:
    """Refuse to mix presets in one folder (the finished steps would not match)."""
    for step in STEPS:
        m = _read_marker(out, step)
        if m is not None and m.get("preset") != preset.to_dict():
            other = m.get("preset", {}).get("name", "?")
            raise ValueError(
                f"{out} holds a demo run with other settings (preset {other!r}, step {step} "
                f"done); use another output folder or delete {out} to start over"
            )


# --------------------------------------------------------------------------- helpers
def rig_errors(est, truth) -> dict[str, Any]:  # noqa: ANN001 - CameraRig
    """Per-camera errors of a calibrated rig against the truth, after aligning the world frames.

    The calibrated world (board on the floor in frame 0) differs from the true one by a
    rigid motion; it is estimated from the camera centres (a similarity, so the scale error
    shows too). Returns camera names, centre errors (mm), rotation errors (deg), focal
    length errors (%, fx and fy), the alignment ``scale``, ``R`` (3, 3) and ``t`` (3,) mapping
    calibrated to true world coordinates.
    """
    names = [c.name for c in truth]
    dc, rot, fe, (s, R, t) = geometry_rig_errors(est, truth)
    return {
        "cameras": names,
        "center_mm": dc.tolist(),
        "rotation_deg": rot.tolist(),
        "focal_percent": fe.tolist(),
        "scale": s,
        "R": R.tolist(),
        "t": t.tolist(),
    }


def truth_to_calibrated(points: np.ndarray, alignment: dict[str, Any]) -> np.ndarray:
    """Map true world points (..., 3) into the calibrated world frame (inverse alignment)."""
    R = np.asarray(alignment["R"])
    t = np.asarray(alignment["t"])
    return ((points - t) @ R) / float(alignment["scale"])


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _savefig(fig, path: Path) -> None:  # noqa: ANN001
    from freipose.io.atomic import atomic_path

    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=90, bbox_inches="tight")
    _plt().close(fig)


# --------------------------------------------------------------------------- 1 synth
def step_synth(ctx: DemoContext) -> dict[str, Any]:
    from freipose.synth import SceneConfig, StimulationConfig, generate_session

    p = ctx.preset
    stim = StimulationConfig.from_dict(dict(p.stimulation))
    out: dict[str, Any] = {"sessions": {}}
    for i, s in enumerate(p.sessions):
        cfg = SceneConfig(
            n_cameras=p.n_cameras,
            frames=p.session_frames,
            fps=p.fps,
            size=tuple(p.size),
            seed=s.seed,
            appearance="hooded",
            stimulation=stim,
            calibration_video=(i == 0),
            calibration_frames=p.calibration_frames,
            jitter_rig=False,  # one rig for all recordings, as in a lab
        )
        ctx.say(f"  rendering {s.name}: {p.n_cameras} cameras, {p.session_frames} frames"
                + (f" + {p.calibration_frames} board frames" if i == 0 else ""))  # fmt: skip
        paths = generate_session(ctx.session_dir(s.name), cfg, progress=ctx.progress)
        n_events = len(stim.windows(p.session_frames / p.fps))
        out["sessions"][s.name] = {"folder": str(paths.folder), "windows": n_events}
    return out


# --------------------------------------------------------------------------- 2 calibrate
def step_calibrate(ctx: DemoContext) -> dict[str, Any]:
    from freipose.calibration.boards import load_board
    from freipose.calibration.pipeline import CalibrationOptions, calibrate
    from freipose.calibration.report import write_report
    from freipose.io.calibration import load_calibration, save_calibration
    from freipose.io.video import find_camera_videos

    folder = ctx.calib_videos
    videos = find_camera_videos(folder)
    board = load_board(folder / "board.toml")
    truth = load_calibration(folder / "calibration.toml")
    out = ctx.calibration
    out.parent.mkdir(parents=True, exist_ok=True)
    opts = CalibrationOptions(origin_frame=0, jobs=min(2, os.cpu_count() or 1), progress=False)
    result = calibrate([videos[n] for n in truth.names], board, out, opts)
    save_calibration(result.rig, out)
    write_report(result, out.parent / "report")
    err = rig_errors(result.rig, truth)
    atomic_write_text(out.parent / "comparison.json", json.dumps(err, indent=2) + "\n")
    for name, dc, rot, fe, st in zip(
        err["cameras"], err["center_mm"], err["rotation_deg"], err["focal_percent"], result.stats
    ):
        ctx.say(
            f"  {name}: reprojection RMS {st.rms:.2f} px, centre error {dc:.2f} mm, "
            f"rotation error {rot:.3f} deg, focal error {fe[0]:+.2f} %"
        )
    plt = _plt()
    fig, axes = plt.subplots(1, 3, figsize=(11, 3))
    x = np.arange(len(err["cameras"]))
    for ax, vals, title in (
        (axes[0], err["center_mm"], "camera centre error (mm)"),
        (axes[1], err["rotation_deg"], "rotation error (deg)"),
        (axes[2], [abs(f[0]) for f in err["focal_percent"]], "|focal length error| (%)"),
    ):
        ax.bar(x, vals, color="C0")
        ax.set_xticks(x)
        ax.set_xticklabels(err["cameras"], rotation=45, fontsize=8)
        ax.set_title(title, fontsize=9)
        ax.grid(axis="y", alpha=0.3)
    fig.suptitle("Calibration vs. the true rig (after aligning the world frames)", fontsize=10)
    _savefig(fig, out.parent / "comparison.png")
    summary = {
        "max_center_mm": float(np.max(err["center_mm"])),
        "max_rotation_deg": float(np.max(err["rotation_deg"])),
        "max_focal_percent": float(np.max(np.abs(err["focal_percent"]))),
        "max_rms_px": float(np.nanmax([s.rms for s in result.stats])),
        "scale": err["scale"],
    }
    ctx.say(
        f"  largest errors: centre {summary['max_center_mm']:.2f} mm, rotation "
        f"{summary['max_rotation_deg']:.3f} deg, focal {summary['max_focal_percent']:.2f} %; "
        f"scale {summary['scale']:.4f}"
    )
    return {"summary": summary, "alignment": {k: err[k] for k in ("scale", "R", "t")}}


# --------------------------------------------------------------------------- 3 labels
def _session_labels(ctx: DemoContext, name: str):  # noqa: ANN202 - LabelSet
    from freipose.io.labels import read_labels_h5

    return read_labels_h5(ctx.session_dir(name) / "labels.h5")


def _pick(n_total: int, n: int) -> np.ndarray:
    return np.unique(np.linspace(0, n_total - 1, min(n, n_total)).round().astype(int))


def _labels_file(ctx: DemoContext, names: list[str], per_session: int, mode: str, path: Path):
    """Import labels of ``names`` into ``path`` with the labels library (``freipose labels``).

    ``mode`` ``"triangulate"``: the 2D labels of the visible keypoints (plus 1 px labelling
    noise, as from a 2D labelling tool) are triangulated with the calibrated rig (training
    labels); ``"truth"``: the true 3D keypoints mapped into the calibrated world frame
    (evaluation labels).
    """
    from freipose.geometry import reprojection_errors
    from freipose.io.calibration import load_calibration
    from freipose.io.labels import write_labels_h5
    from freipose.labels.importing import ImportOptions, SourceLabels, build_labelset

    rig = load_calibration(ctx.calibration)
    align = _read_marker(ctx.out, "calibrate")["results"]["alignment"]
    rng = np.random.default_rng(0)
    sources, truths = [], []
    for name in names:
        lab = _session_labels(ctx, name)
        sub = lab.select(_pick(len(lab), per_session))
        vis = sub.visible2d if sub.visible2d is not None else np.isfinite(sub.points2d).all(-1)
        p2 = np.where(vis[..., None], sub.points2d, np.nan)
        truth3d = truth_to_calibrated(sub.points3d, align)
        if mode == "triangulate":
            p2 = p2 + rng.normal(0.0, 1.0, p2.shape)
        info = sub.sessions[name]
        sources.append(
            SourceLabels(
                source=str(ctx.session_dir(name) / "labels.h5"),
                session=name,
                cameras=list(sub.cameras),
                keypoints=list(sub.keypoints),
                frame_index=np.asarray(sub.frame_index),
                points2d=p2,
                visible2d=vis,
                points3d=None if mode == "triangulate" else truth3d,
                videos={c: (ctx.session_dir(name) / v).resolve() for c, v in info.videos.items()},
                fps=info.fps,
            )
        )
        truths.append(truth3d)
    opts = ImportOptions(calibration=rig, calibration_source=str(ctx.calibration), threshold=8.0)
    labels = build_labelset(sources, opts, path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_labels_h5(labels, path)
    out = {"path": str(path), "instants": len(labels)}
    if mode == "triangulate":
        p3 = labels.points3d
        pts = np.moveaxis(labels.points2d, 1, 2)  # (N, K, V, 2)
        err = reprojection_errors(p3, pts, labels.rig_for(names[0]).subset(labels.cameras))
        d = np.linalg.norm(p3 - np.concatenate(truths), axis=-1)
        out["median_reprojection_px"] = float(np.nanmedian(err))
        out["median_3d_vs_truth_mm"] = float(np.nanmedian(d))
        out["labeled_fraction"] = float(np.isfinite(p3).all(-1).mean())
    return out


def step_labels(ctx: DemoContext) -> dict[str, Any]:
    p = ctx.preset
    train = [s.name for s in p.sessions if s.split == "train"]
    test = [s.name for s in p.sessions if s.split == "test"]
    tr = _labels_file(
        ctx, train, p.label_instants // len(train), "triangulate", ctx.out / "labels" / "train.h5"
    )
    ctx.say(
        f"  labels/train.h5: {tr['instants']} instants of {', '.join(train)}; 2D labels of "
        f"the visible keypoints triangulated with the calibrated rig: median reprojection "
        f"{tr['median_reprojection_px']:.2f} px, {tr['median_3d_vs_truth_mm']:.2f} mm from the "
        f"truth, {100 * tr['labeled_fraction']:.0f} % of keypoints labeled in 3D"
    )
    ev = _labels_file(
        ctx, test, p.eval_instants // len(test), "truth", ctx.out / "labels" / "eval.h5"
    )
    ctx.say(f"  labels/eval.h5: {ev['instants']} held-out instants of {', '.join(test)} "
            "with the true 3D keypoints (for evaluation only)")  # fmt: skip
    return {"train": tr, "eval": ev}


# --------------------------------------------------------------------------- 4 train
def _train_config(ctx: DemoContext) -> Path:
    import tomli_w

    p = ctx.preset
    pose = dict(p.pose)
    doc = {
        "data": {
            "labels": "../labels/train.h5",
            "eval_labels": "../labels/eval.h5",
            "skeleton": "rat",
        },
        "model": {"preset": pose.pop("preset")},
        "schedule": pose,
        "detector": dict(p.detector),
    }
    path = ctx.train_dir / "config.toml"
    text = (
        f"# written by freipose demo (preset {p.name}); train with\n"
        "#   freipose train config.toml --stage detector --out detector\n"
        "#   freipose train config.toml --out pose\n"
        "#   freipose train config.toml --stage baseline --out baseline\n"
    ) + tomli_w.dumps(doc)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not path.is_file() or path.read_text(encoding="utf-8") != text:
        atomic_write_text(path, text)
    return path


class _LossRecorder(logging.Handler):
    """Collects the detector's ``step %d/%d loss %.4f`` log records (its training curve)."""

    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.rows: list[tuple[int, float]] = []

    def emit(self, record: logging.LogRecord) -> None:
        if str(record.msg).startswith("step %d/%d loss") and record.args:
            self.rows.append((int(record.args[0]), float(record.args[2])))


def _plot_detector_curve(rows: list[tuple[int, float]], path: Path) -> None:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(5, 3))
    if rows:
        s, v = zip(*rows)
        ax.plot(s, v, "-o", ms=3)
    ax.set_xlabel("step")
    ax.set_ylabel("detection loss")
    ax.set_yscale("log")
    ax.grid(alpha=0.3)
    ax.set_title("detector training", fontsize=10)
    _savefig(fig, path)


def step_train(ctx: DemoContext) -> dict[str, Any]:
    import torch

    from freipose._compat import tomllib
    from freipose.detect.train import train_detector
    from freipose.nn.train import train_from_config

    cfg_path = _train_config(ctx)
    data = tomllib.loads(cfg_path.read_text(encoding="utf-8"))
    det_dir = ctx.train_dir / "detector"
    out: dict[str, Any] = {"config": str(cfg_path)}
    ctx.say("  detector (CenterNet-style boxes in every view, made consistent in 3D)")
    det_ckpt = det_dir / "detector.pt"
    if not det_ckpt.is_file():
        rec = _LossRecorder()
        lg = logging.getLogger("freipose.detect.train")
        old = lg.level
        lg.setLevel(logging.INFO)
        lg.addHandler(rec)
        try:
            det_ckpt = train_detector(
                data, cfg_path, det_dir, (det_dir / "detector_last.pt").is_file(), ctx.device
            )
        finally:
            lg.removeHandler(rec)
            lg.setLevel(old)
        lines = ["step,loss"] + [f"{s},{v:.6g}" for s, v in rec.rows]
        atomic_write_text(det_dir / "losses.csv", "\n".join(lines) + "\n")
    rows = []
    lp = det_dir / "losses.csv"
    if lp.is_file():
        for line in lp.read_text().splitlines()[1:]:
            s, v = line.split(",")
            rows.append((int(s), float(v)))
    _plot_detector_curve(rows, det_dir / "losses.png")
    metrics = torch.load(det_ckpt, map_location="cpu", weights_only=False).get("metrics", {})
    out["detector"] = {"checkpoint": str(det_ckpt), "metrics": metrics}
    for kind, sub, what in (
        (None, "pose", "voxel network (2D encoder, unprojection, 3D U-Net, refinement)"),
        ("baseline", "baseline", "triangulation baseline (per-view 2D + robust triangulation)"),
    ):
        ctx.say(f"  {what}")
        run = ctx.train_dir / sub
        if kind == "baseline":
            # the baseline gets its own step count: a config next to the main one
            bdata = json.loads(json.dumps(data))
            bdata["schedule"]["steps"] = ctx.preset.baseline_steps
            import tomli_w

            bpath = ctx.train_dir / "config_baseline.toml"
            text = tomli_w.dumps(bdata)
            if not bpath.is_file() or bpath.read_text(encoding="utf-8") != text:
                atomic_write_text(bpath, text)
            path_cfg = bpath
        else:
            path_cfg = cfg_path
        model = run / "model.pt"
        if not model.is_file():
            model = train_from_config(
                path_cfg,
                run,
                resume=(run / "checkpoint.pt").is_file(),
                device=ctx.device,
                kind=kind,
                progress=ctx.progress is not False,
            )
        out[sub] = {"checkpoint": str(model), "log": str(run / "log.csv")}
        last = _last_log_row(run / "log.csv")
        if last:
            out[sub]["last_log"] = last
            v = last.get("val_jpe_p1") or last.get("val_jpe_p0")
            ctx.say(f"    final loss {last.get('loss')}, validation JPE {v or 'n/a'} mm")
    return out


def _last_log_row(path: Path) -> dict[str, str]:
    if not path.is_file():
        return {}
    lines = [ln for ln in path.read_text().splitlines() if ln.strip()]
    if len(lines) < 2:
        return {}
    head = lines[0].split(",")
    best: dict[str, str] = {}
    for ln in lines[1:]:
        row = dict(zip(head, ln.split(",")))
        for k, v in row.items():
            if v != "":
                best[k] = v
    return best


# --------------------------------------------------------------------------- 5 predict
def step_predict(ctx: DemoContext) -> dict[str, Any]:
    from freipose.io.poses import read_poses_h5
    from freipose.io.video import FrameSource, find_camera_videos
    from freipose.predict.network import DetectorSpec, predict_sessions
    from freipose.predict.render import render_overlay
    from freipose.predict.session import discover_sessions

    p = ctx.preset
    trained = _read_marker(ctx.out, "train")["results"]
    folders = [ctx.session_dir(s.name) for s in p.sessions]
    sessions = discover_sessions(folders, ctx.calibration)
    if p.detection == "detector":
        spec = DetectorSpec("detector", Path(trained["detector"]["checkpoint"]), None, 40, 2)
    else:
        spec = DetectorSpec(p.detection, None, None, min(40, p.session_frames), 2)
    out: dict[str, Any] = {"poses": {}}

    def report(res: Any) -> None:
        if res.skipped:
            ctx.say(f"  {res.path.name}: complete, kept")
        else:
            counts = ", ".join(f"{v} {k}" for k, v in res.status_counts.items() if v)
            ctx.say(f"  {res.path.name}: {counts} ({res.frames} frames in {res.seconds:.0f} s)")

    results = predict_sessions(
        sessions,
        Path(trained["pose"]["checkpoint"]),
        spec,
        ctx.poses_dir,
        batch_size=p.batch,
        device=ctx.device,
        progress=ctx.progress is not False,
        report=report,
    )
    for s, res in zip(p.sessions, results):
        data = read_poses_h5(res.path)
        found = float(np.isfinite(data.poses).all(-1).any(-1).mean())
        out["poses"][s.name] = {"path": str(res.path), "found_fraction": found}
    # overlay clip of the held-out session (what `freipose render` writes) and a few frames
    test = next(s.name for s in p.sessions if s.split == "test")
    data = read_poses_h5(ctx.poses_dir / f"{test}.poses.h5")
    videos = find_camera_videos(ctx.session_dir(test))
    rig = data.calibration
    names = [n for n in rig.names if n in videos]
    overlay = ctx.out / "overlay"
    overlay.mkdir(parents=True, exist_ok=True)
    first = _stim_frame(ctx)
    clip = render_overlay(
        [videos[n] for n in names],
        rig.subset(names),
        data,
        overlay / f"{test}.mp4",
        frames=(first, min(first + p.overlay_frames, p.session_frames)),
        tile_width=240,
        progress=False,
    )
    import cv2

    src = FrameSource(clip)
    pngs = []
    for i in np.unique(np.linspace(0, src.num_frames - 1, 3).round().astype(int)):
        png = overlay / f"{test}_frame{first + int(i):05d}.png"
        cv2.imwrite(str(png), src.read(int(i)))
        pngs.append(str(png))
    src.close()
    out["overlay"] = {"clip": str(clip), "frames": pngs}
    ctx.say(f"  overlay clip {clip.relative_to(ctx.out)} and {len(pngs)} PNG frames")
    return out


def _stim_frame(ctx: DemoContext) -> int:
    """A frame shortly before the first stimulation window (the clip shows its onset)."""
    p = ctx.preset
    onset = float(p.stimulation.get("onset_s", 1.0))
    start = max(0, int(round((onset - 0.2) * p.fps)))
    return min(start, max(0, p.session_frames - p.overlay_frames))


# --------------------------------------------------------------------------- 6 evaluate
def step_evaluate(ctx: DemoContext) -> dict[str, Any]:
    from freipose.io.labels import read_labels_h5
    from freipose.io.poses import read_poses_h5
    from freipose.labels.dataset import MultiViewDataset
    from freipose.nn.evaluate import jpe, predict_dataset, write_report
    from freipose.nn.model import load_checkpoint

    trained = _read_marker(ctx.out, "train")["results"]
    align = _read_marker(ctx.out, "calibrate")["results"]["alignment"]
    ev_path = ctx.out / "labels" / "eval.h5"
    lab = read_labels_h5(ev_path)
    ds = MultiViewDataset(lab, root=ev_path.parent)
    results: dict[str, np.ndarray] = {}
    keypoints = tuple(lab.keypoints)
    for sub in ("pose", "baseline"):
        model, config, _ = load_checkpoint(trained[sub]["checkpoint"], ctx.device)
        pred = predict_dataset(model, ds, batch_size=4)
        if config.model.kind == "voxel":
            results["voxel_P0"] = jpe(pred["P0"], pred["gt"])
            results["voxel_P1"] = jpe(pred["P1"], pred["gt"])
        else:
            results["baseline"] = jpe(pred["P1"], pred["gt"])
    out_lab = ctx.out / "evaluation" / "labels"
    summary = write_report(out_lab, results, keypoints)
    res: dict[str, Any] = {"labels": {}}
    ctx.say("  cube on the true centre, held-out instants (what `freipose eval` reports):")
    for name, s in summary.items():
        o = s["overall"]
        res["labels"][name] = {"median": o["median"], "p30": o["p30"], "p70": o["p70"]}
        ctx.say(f"    {name:10s} median JPE {o['median']:7.2f} mm "
                f"(30-70 %: {o['p30']:.2f}-{o['p70']:.2f})")  # fmt: skip
    # the whole pipeline (detector + voxel network) on every frame of every session
    pipe: dict[str, np.ndarray] = {}
    for s in ctx.preset.sessions:
        data = read_poses_h5(ctx.poses_dir / f"{s.name}.poses.h5")
        truth = _session_labels(ctx, s.name)
        gt = truth_to_calibrated(truth.points3d, align)
        rows = {int(f): i for i, f in enumerate(truth.frame_index)}
        idx = np.array([rows[int(f)] for f in data.frame_index])
        pipe[f"{s.name} ({s.split})"] = jpe(data.poses, gt[idx])
    summary2 = write_report(ctx.out / "evaluation" / "pipeline", pipe, keypoints)
    res["pipeline"] = {}
    ctx.say("  whole pipeline (detector + voxel network, every frame, vs. the truth):")
    for name, s in summary2.items():
        o = s["overall"]
        res["pipeline"][name] = {"median": o["median"], "missing": o.get("missing", 0)}
        ctx.say(f"    {name:22s} median JPE {o['median']:7.2f} mm over {o['n']} keypoints")
    return res


# --------------------------------------------------------------------------- 7 analyze
def study_toml(ctx: DemoContext, study_dir: Path, poses_dir: Path | None = None) -> str:
    """The study manifest of the demo sessions (paths relative to ``study_dir``).

    ``poses_dir`` holds ``<session>.poses.h5`` (default: the predictions).
    """
    poses_dir = ctx.poses_dir if poses_dir is None else poses_dir
    lines = [
        "# written by freipose demo: one animal, one condition, a train and a test recording",
        'skeleton = "rat"',
        "",
    ]
    for s in ctx.preset.sessions:
        poses = os.path.relpath(poses_dir / f"{s.name}.poses.h5", study_dir)
        events = os.path.relpath(ctx.session_dir(s.name) / "events.csv", study_dir)
        lines += [
            "[[recordings]]",
            f'name = "{s.name}"',
            f'poses = "{Path(poses).as_posix()}"',
            f'events = "{Path(events).as_posix()}"',
            'animal = "rat1"',
            'condition = "paw_stimulation"',
            f'split = "{s.split}"',
            "",
        ]
    return "\n".join(lines)


def _write_truth_poses(ctx: DemoContext, folder: Path) -> None:
    """The true keypoints of every session as poses files (calibrated world frame)."""
    from freipose.io.calibration import load_calibration
    from freipose.io.poses import PoseData, write_poses_h5
    from freipose.skeleton import load_skeleton

    align = _read_marker(ctx.out, "calibrate")["results"]["alignment"]
    rig = load_calibration(ctx.calibration)
    skel = load_skeleton("rat")
    for s in ctx.preset.sessions:
        path = folder / f"{s.name}.poses.h5"
        if path.is_file():
            continue
        lab = _session_labels(ctx, s.name)
        poses = truth_to_calibrated(lab.points3d, align)
        data = PoseData(
            poses=poses,
            confidence=np.ones(poses.shape[:2]),
            keypoints=tuple(lab.keypoints),
            frame_index=np.asarray(lab.frame_index),
            fps=ctx.preset.fps,
            calibration=rig,
            skeleton=skel,
            provenance={"source": "freipose demo: true keypoints of the synthetic session"},
        )
        folder.mkdir(parents=True, exist_ok=True)
        write_poses_h5(data, path)


def _analyze(ctx: DemoContext, study: Path, text: str, results: Path) -> dict[str, Any]:
    from freipose.analysis.attribution import AttributionConfig
    from freipose.analysis.report import analyze_study
    from freipose.analysis.variables import VariableConfig

    if not study.is_file() or study.read_text(encoding="utf-8") != text:
        atomic_write_text(study, text)
    acfg = AttributionConfig(**ctx.preset.analysis)
    vcfg = VariableConfig(stft_window=ctx.preset.stft_window)
    result = analyze_study(
        study, results, None, "world", vcfg, acfg, say=lambda m: ctx.say("    " + m)
    )
    att = result.attribution.sort_values("f1", ascending=False)
    top = att.head(10)
    parts = top["part"].tolist()
    share = float(np.mean([pt == STIM_PART for pt in parts])) if parts else 0.0
    res = {
        "classification": json.loads(result.classification.to_json(orient="records")),
        "top_variables": json.loads(
            top[["variable", "part", "f1", "p_value", "p_adjusted", "significant"]].to_json(
                orient="records"
            )
        ),
        "top10_share_stimulated_part": share,
        "significant": int(att["significant"].sum()),
    }
    ctx.say(
        f"    -> {int(round(share * 10))} of the 10 best single variables belong to the "
        f"stimulated {STIM_PART} (best: {top.iloc[0]['variable']}, F1 "
        f"{top.iloc[0]['f1']:.2f}); {res['significant']} significant after the "
        "autocorrelation-corrected, Bonferroni-adjusted test"
    )
    return res


def step_analyze(ctx: DemoContext) -> dict[str, Any]:
    out = ctx.out / "analysis"
    out.mkdir(parents=True, exist_ok=True)
    ctx.say("  on the predicted poses:")
    pred = _analyze(ctx, out / "study.toml", study_toml(ctx, out), out / "results")
    # The same analysis on the true keypoints: what perfect tracking would show.
    ctx.say("  on the true keypoints (for comparison: perfect tracking):")
    truth_dir = out / "truth_poses"
    _write_truth_poses(ctx, truth_dir)
    truth = _analyze(
        ctx, out / "study_truth.toml", study_toml(ctx, out, truth_dir), out / "results_truth"
    )
    return {"stimulated_part": STIM_PART, "predicted": pred, "truth": truth}


# --------------------------------------------------------------------------- 8 report
def _rel(ctx: DemoContext, p: Path | str) -> str:
    return Path(os.path.relpath(Path(p), ctx.out)).as_posix()


def _img(ctx: DemoContext, p: Path, caption: str, width: int | None = None) -> str:
    if not p.is_file():
        return f"<p><em>missing figure {html.escape(_rel(ctx, p))}</em></p>"
    w = f' width="{width}"' if width else ""
    return (
        f'<figure><img src="{html.escape(_rel(ctx, p))}"{w} alt="{html.escape(caption)}">'
        f"<figcaption>{html.escape(caption)}</figcaption></figure>"
    )


def _table(header: list[str], rows: list[list[Any]]) -> str:
    def cell(v: Any) -> str:
        if isinstance(v, float):
            return f"{v:.3g}" if abs(v) < 1000 else f"{v:.0f}"
        return html.escape(str(v))

    h = "".join(f"<th>{html.escape(x)}</th>" for x in header)
    body = "".join("<tr>" + "".join(f"<td>{cell(v)}</td>" for v in r) + "</tr>" for r in rows)
    return f"<table><tr>{h}</tr>{body}</table>"


def step_report(ctx: DemoContext) -> dict[str, Any]:
    m = {s: (_read_marker(ctx.out, s) or {}) for s in STEPS}
    p = ctx.preset
    r = {s: m[s].get("results", {}) for s in STEPS}
    parts = [
        "<!DOCTYPE html><html><head><meta charset='utf-8'>",
        f"<title>FreiPose demo ({html.escape(p.name)})</title>",
        "<style>body{font-family:sans-serif;max-width:1100px;margin:2em auto;line-height:1.4}"
        "table{border-collapse:collapse;margin:0.5em 0}td,th{border:1px solid #bbb;"
        "padding:2px 8px;font-size:90%}figure{display:inline-block;margin:0.5em}"
        "figcaption{font-size:85%;color:#444}img{max-width:100%}</style></head><body>",
        f"<h1>FreiPose demo: preset <code>{html.escape(p.name)}</code></h1>",
        f"<p>freipose {html.escape(__version__)}. Synthetic data: a rat in a 600 mm open field "
        f"filmed by {p.n_cameras} cameras ({p.size[0]}x{p.size[1]} px, {p.fps:g} fps), "
        f"{len(p.sessions)} sessions of {p.session_frames} frames with the {STIM_PART} "
        f"stimulated ({html.escape(json.dumps(p.stimulation))}). Every step ran the same "
        "library code as the <code>freipose</code> commands; "
        "<code>examples/workflow.sh</code> runs them one by one.</p>",
    ]
    times = [[s, m[s].get("seconds", float("nan"))] for s in STEPS if s != "report"]
    parts.append("<h2>Steps and run times</h2>" + _table(["step", "seconds"], times))
    # calibration
    cal = r["calibrate"]
    parts.append("<h2>1-2. Calibration</h2>")
    comp_path = ctx.out / "calibration" / "comparison.json"
    if comp_path.is_file():
        comp = json.loads(comp_path.read_text())
        rows = [
            [c, dc, rot, f[0], f[1]]
            for c, dc, rot, f in zip(
                comp["cameras"], comp["center_mm"], comp["rotation_deg"], comp["focal_percent"]
            )
        ]
        parts.append(
            "<p>Board videos calibrated with <code>freipose calib --origin-frame 0</code>; "
            "errors against the true rig after aligning the world frames "
            f"(scale {comp['scale']:.4f}).</p>"
            + _table(["camera", "centre mm", "rotation deg", "fx %", "fy %"], rows)
        )
    parts.append(_img(ctx, ctx.out / "calibration" / "comparison.png", "calibration errors"))
    rep = ctx.out / "calibration" / "report"
    for name in ("rig_3d.png",):
        parts.append(_img(ctx, rep / name, "calibrated rig", 420))
    errs = sorted(rep.glob("errors_*.png"))[:2]
    for e in errs:
        parts.append(_img(ctx, e, f"reprojection errors {e.stem[7:]}", 360))
    if cal.get("summary"):
        s = cal["summary"]
        parts.append(
            f"<p>Largest errors: camera centre {s['max_center_mm']:.2f} mm, rotation "
            f"{s['max_rotation_deg']:.3f} deg, focal length {s['max_focal_percent']:.2f} %, "
            f"reprojection RMS {s['max_rms_px']:.2f} px.</p>"
        )
    # labels
    lab = r["labels"]
    if lab:
        tr, ev = lab["train"], lab["eval"]
        parts.append(
            "<h2>3. Labels</h2>"
            f"<p><code>labels/train.h5</code>: {tr['instants']} time instants; 2D labels of the "
            "visible keypoints (1 px noise) triangulated with the calibrated rig: median "
            f"reprojection error {tr['median_reprojection_px']:.2f} px, "
            f"{tr['median_3d_vs_truth_mm']:.2f} mm from the true 3D keypoints. "
            f"<code>labels/eval.h5</code>: {ev['instants']} held-out instants of the test "
            "session with the true keypoints.</p>"
        )
    # training
    parts.append("<h2>4. Training</h2>")
    det = r["train"].get("detector", {}).get("metrics", {})
    if det:
        keys = [k for k in ("recall", "median_center_error_mm", "cpu_fps", "train_seconds")
                if k in det]  # fmt: skip
        parts.append(_table(["detector metric", "value"], [[k, det[k]] for k in keys]))
    parts.append(_img(ctx, ctx.train_dir / "detector" / "losses.png", "detector loss", 360))
    parts.append(_img(ctx, ctx.train_dir / "pose" / "log.png", "voxel network training", 420))
    parts.append(_img(ctx, ctx.train_dir / "baseline" / "log.png", "baseline training", 420))
    # evaluation
    ev = r["evaluate"]
    parts.append("<h2>5-6. Prediction and evaluation</h2>")
    if ev:
        rows = [[k, v["median"], v["p30"], v["p70"]] for k, v in ev["labels"].items()]
        parts.append(
            "<p>Held-out instants, cube on the true centre (<code>freipose eval</code>): "
            "voxel network (P0: 3D network, P1: refined) vs. triangulation baseline.</p>"
            + _table(["method", "median JPE mm", "30 %", "70 %"], rows)
        )
        rows = [[k, v["median"]] for k, v in ev["pipeline"].items()]
        parts.append(
            "<p>Whole pipeline (detector + voxel network) on every frame of each session "
            "against the true 3D keypoints:</p>" + _table(["session", "median JPE mm"], rows)
        )
    parts.append(_img(ctx, ctx.out / "evaluation" / "labels" / "jpe_boxplot.png",
                      "per-keypoint errors, held-out instants", 700))  # fmt: skip
    parts.append(_img(ctx, ctx.out / "evaluation" / "labels" / "pck.png", "PCK", 360))
    parts.append(_img(ctx, ctx.out / "evaluation" / "pipeline" / "jpe_boxplot.png",
                      "per-keypoint errors, whole pipeline", 700))  # fmt: skip
    ov = r["predict"].get("overlay", {})
    if ov:
        parts.append(
            f"<p>Overlay clip: <a href='{html.escape(_rel(ctx, ov['clip']))}'>"
            f"{html.escape(_rel(ctx, ov['clip']))}</a> (frames below).</p>"
        )
        for f in ov["frames"]:
            parts.append(_img(ctx, Path(f), Path(f).stem, 1000))
    # analysis
    an = r["analyze"]
    parts.append("<h2>7. Analysis</h2>")
    for key, label, sub in (
        ("predicted", "the predicted poses", "results"),
        ("truth", "the true keypoints (perfect tracking, for comparison)", "results_truth"),
    ):
        a = an.get(key)
        res_dir = ctx.out / "analysis" / sub
        parts.append(f"<h3>On {html.escape(label)}</h3>")
        if a:
            rows = [
                [c["evaluated_on"], c["balanced_accuracy"], c["f1"], c["p_value"],
                 c["n_effective"]]
                for c in a["classification"]
            ]  # fmt: skip
            parts.append(
                "<p>Linear SVM on all variables, trained on the train recording, scored on "
                "the test recording:</p>"
                + _table(["evaluated on", "balanced accuracy", "F1", "p", "n effective"], rows)
            )
            rows = [[t["variable"], t["f1"], t["p_value"], t["significant"]]
                    for t in a["top_variables"]]  # fmt: skip
            n_top = int(round(a["top10_share_stimulated_part"] * 10))
            parts.append(
                f"<p>Best single variables ({n_top} of the top 10 belong to the stimulated "
                f"{STIM_PART}; {a['significant']} significant after the "
                "autocorrelation-corrected, Bonferroni-adjusted chi-squared test):</p>"
                + _table(["variable", "F1", "p", "significant"], rows)
            )
        for f in sorted(res_dir.glob("attribution_*.png")):
            parts.append(_img(ctx, f, f"attribution heat map ({key})", 1000))
        parts.append(_img(ctx, res_dir / "classifier_response.png",
                          f"onset dynamics ({key})", 480))  # fmt: skip
        for f in sorted(res_dir.glob("top_variables_*.png")):
            parts.append(_img(ctx, f, f"top variables around onset ({key})", 700))
    parts.append("</body></html>")
    path = ctx.out / "report.html"
    atomic_write_text(path, "\n".join(parts) + "\n")
    ctx.say(f"  wrote {path}")
    return {"report": str(path)}


STEP_INFO: dict[str, tuple[str, Callable[[DemoContext], dict[str, Any]]]] = {
    "synth": ("Synthesize a calibration recording and stimulated sessions (freipose synth)",
              step_synth),
    "calibrate": ("Calibrate the 7 cameras from the board videos (freipose calib)",
                  step_calibrate),
    "labels": ("Import labels: triangulate 2D labels with the calibrated rig (freipose labels)",
               step_labels),
    "train": ("Train the detector, the voxel network and the baseline (freipose train)",
              step_train),
    "predict": ("Predict 3D poses of every session (freipose predict, freipose render)",
                step_predict),
    "evaluate": ("Evaluate joint position errors against the truth (freipose eval)",
                 step_evaluate),
    "analyze": ("Attribute the stimulation effect to body parts (freipose analyze)",
                step_analyze),
    "report": ("Write report.html", step_report),
}  # fmt: skip


def run_demo(
    outdir: str | Path,
    preset: str | DemoPreset = "small",
    device: str = "cpu",
    say: Callable[[str], None] = print,
    progress: bool | None = None,
) -> Path:
    """Run (or resume) the demo in ``outdir``; returns the path of ``report.html``.

    Args:
        outdir: output folder (created).
        preset: ``"small"`` (default, < 15 min on 2 CPU cores), ``"tiny"`` (CI) or a preset.
        device: torch device for training and prediction.
        say: where progress messages go.
        progress: progress bars (None: only on a terminal).

    Raises:
        ValueError: ``outdir`` holds a demo run with another preset, or a step fails.
    """
    if isinstance(preset, str):
        if preset not in PRESETS:
            raise ValueError(f"unknown demo preset {preset!r}; choose one of {sorted(PRESETS)}")
        preset = PRESETS[preset]
    out = Path(outdir)
    if out.exists() and not out.is_dir():
        raise ValueError(f"{out} exists and is not a folder; choose another output folder")
    _check_outdir(out, preset)
    out.mkdir(parents=True, exist_ok=True)
    ctx = DemoContext(out, preset, device, say, progress)
    t_all = time.perf_counter()
    for i, step in enumerate(STEPS, start=1):
        title, fn = STEP_INFO[step]
        done = _read_marker(out, step)
        if done is not None and step != "report":
            say(f"[{i}/{len(STEPS)}] {title}: done earlier ({done.get('seconds', 0):.0f} s), "
                "skipped")  # fmt: skip
            continue
        say(f"[{i}/{len(STEPS)}] {title}")
        t0 = time.perf_counter()
        results = fn(ctx)
        dt = time.perf_counter() - t0
        _write_marker(ctx, step, results, dt)
        say(f"      ({dt:.0f} s)")
    say(f"demo finished in {time.perf_counter() - t_all:.0f} s; open {out / 'report.html'}")
    return out / "report.html"


__all__ = [
    "PRESETS",
    "STEPS",
    "DemoPreset",
    "DemoSession",
    "rig_errors",
    "run_demo",
    "study_toml",
    "truth_to_calibrated",
]

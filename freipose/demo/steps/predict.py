"""Step 5, ``predict``: poses of every session and an overlay clip (``freipose predict``)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from freipose.demo.context import DemoContext
from freipose.demo.markers import step_results


def _stim_frame(ctx: DemoContext) -> int:
    """A frame shortly before the first stimulation window (the clip shows its onset)."""
    p = ctx.preset
    onset = float(p.stimulation.get("onset_s", 1.0))
    start = max(0, int(round((onset - 0.2) * p.fps)))
    return min(start, max(0, p.session_frames - p.overlay_frames))


def _predict(ctx: DemoContext, trained: dict[str, Any]) -> dict[str, Any]:
    """Predict every session to ``poses/<session>.poses.h5``; the fraction of frames found."""
    from freipose.io.poses import read_poses_h5
    from freipose.io.session import discover_sessions
    from freipose.predict.network import DetectorSpec, predict_sessions

    p = ctx.preset
    folders = [ctx.session_dir(s.name) for s in p.analysed]
    sessions = discover_sessions(folders, ctx.calibration)
    if p.detection == "detector":
        spec = DetectorSpec("detector", Path(trained["detector"]["checkpoint"]), None, 40, 2)
    else:
        spec = DetectorSpec(p.detection, None, None, min(40, p.session_frames), 2)

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
    poses: dict[str, Any] = {}
    for s, res in zip(p.analysed, results):
        data = read_poses_h5(res.path)
        found = float(np.isfinite(data.poses).all(-1).any(-1).mean())
        poses[s.name] = {"path": str(res.path), "found_fraction": found}
    return poses


def _stills(first: int, count: int, fps: float, windows: np.ndarray) -> list[int]:
    """Three still frames of the clip ``first .. first + count - 1``.

    The first frame (before the stimulation) and the middle of the stimulation windows the
    clip shows in full, or, with fewer than two such windows, three evenly spread frames.
    """
    last = first + count - 1
    mids = [int(round(0.5 * (a + b) * fps)) for a, b in windows
            if first <= a * fps and b * fps <= last]  # fmt: skip
    if len(mids) >= 2:
        return [first, *mids[:2]]
    return [first + int(i) for i in np.unique(np.linspace(0, count - 1, 3).round().astype(int))]


def _overlay(ctx: DemoContext) -> dict[str, Any]:
    """The overlay clip of the held-out session (what ``freipose render`` writes), 3 stills."""
    from freipose.analysis.study import read_events
    from freipose.io.poses import read_poses_h5
    from freipose.io.video import find_camera_videos
    from freipose.predict.render import render_overlay, render_stills

    p = ctx.preset
    test = p.with_split("test")[0].name
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
        tile_width=p.size[0],  # the cameras' own width: no downscaling
        progress=False,
    )
    count = min(first + p.overlay_frames, p.session_frames) - first
    windows = read_events(ctx.session_dir(test) / "events.csv")
    stills = _stills(first, count, p.fps, windows)
    pngs = [str(f) for f in render_stills(
        [videos[n] for n in names], rig.subset(names), data, stills,
        [overlay / f"{test}_frame{f:05d}.png" for f in stills])]  # fmt: skip
    start, end = first / p.fps, (first + count) / p.fps
    shown = [[float(a), float(b)] for a, b in windows if a < end and b > start]
    ctx.say(f"  overlay clip {clip.relative_to(ctx.out)} ({end - start:.1f} s, "
            f"{len(shown)} stimulation windows) and {len(pngs)} PNG frames")  # fmt: skip
    return {"clip": str(clip), "frames": pngs, "start_s": start, "end_s": end,
            "stimulation_s": shown}  # fmt: skip


def run(ctx: DemoContext) -> dict[str, Any]:
    """Predict every session with the trained networks and render an overlay clip.

    Args:
        ctx: the demo run.

    Returns:
        ``poses`` (per session: path and fraction of frames with a pose) and ``overlay``
        (the clip, its PNG frames, its start and end in the recording and the stimulation
        windows it shows, in seconds).
    """
    trained = step_results(ctx.out, "train")
    return {"poses": _predict(ctx, trained), "overlay": _overlay(ctx)}

"""Step 1, ``synth``: render the board videos and the stimulated sessions (``freipose synth``)."""

from __future__ import annotations

from typing import Any

from freipose.demo.context import DemoContext


def run(ctx: DemoContext) -> dict[str, Any]:
    """Render every session of the preset (the first one with the board videos).

    Every session films the same animal (the first session's seed draws it) on another day:
    its own motion and stimulation, the same body.

    Args:
        ctx: the demo run.

    Returns:
        ``{"sessions": {name: {"folder", "windows"}}}``: each session's folder and number of
        stimulation windows.
    """
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
            animal_seed=p.sessions[0].seed,  # one rat, filmed on every day
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

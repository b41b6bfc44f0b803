"""Step 1, ``synth``: render the board videos and the stimulated sessions (``freipose synth``)."""

from __future__ import annotations

from typing import Any

from freipose.demo.context import DemoContext
from freipose.demo.presets import DemoPreset


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
    from freipose.synth import generate_session

    p = ctx.preset
    out: dict[str, Any] = {"sessions": {}}
    for i, s in enumerate(p.sessions):
        cfg = session_scene(p, s.seed, calibration=(i == 0))
        ctx.say(f"  rendering {s.name}: {p.n_cameras} cameras, {p.session_frames} frames"
                + (f" + {p.calibration_frames} board frames" if i == 0 else ""))  # fmt: skip
        paths = generate_session(ctx.session_dir(s.name), cfg, progress=ctx.progress)
        n_events = len(cfg.stimulation.windows(p.session_frames / p.fps))
        out["sessions"][s.name] = {"folder": str(paths.folder), "windows": n_events}
    return out


def session_scene(preset: DemoPreset, seed: int, calibration: bool = False) -> Any:
    """The ``SceneConfig`` of a demo recording: the preset's rat and rig, on day ``seed``.

    Args:
        preset: the demo preset.
        seed: the recording's seed (its motion, lighting and noise).
        calibration: also render the board videos.

    Returns:
        The scene; every recording of a preset films the same rat with the same rig.
    """
    from freipose.synth import SceneConfig, StimulationConfig

    return SceneConfig(
        n_cameras=preset.n_cameras,
        frames=preset.session_frames,
        fps=preset.fps,
        size=tuple(preset.size),
        seed=seed,
        animal_seed=preset.sessions[0].seed,  # one rat, filmed on every day
        appearance="hooded",
        stimulation=StimulationConfig.from_dict(dict(preset.stimulation)),
        calibration_video=calibration,
        calibration_frames=preset.calibration_frames,
        jitter_rig=False,  # one rig for all recordings, as in a lab
    )

"""The demo's overlay clip shows the stimulation: its length, its start and its stills."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from freipose.demo.context import DemoContext
from freipose.demo.presets import PRESETS
from freipose.demo.steps.predict import _stills, _stim_frame
from freipose.synth.stimulation import StimulationConfig


def test_small_overlay_clip_shows_two_whole_stimulation_windows():
    p = PRESETS["small"]
    first = _stim_frame(DemoContext(Path("unused"), p))
    start, end = first / p.fps, (first + p.overlay_frames) / p.fps
    windows = StimulationConfig(**p.stimulation).windows(p.session_frames / p.fps)
    shown = [(a, b) for a, b in windows if start <= a and b <= end]
    assert len(shown) >= 2, (start, end, windows)
    assert start < shown[0][0]  # it starts before the first stimulation
    assert end - start <= 10.0  # and stays short to render (about 0.1 s per frame)


def test_stills_show_the_stimulation_windows_in_the_clip():
    windows = np.array([[1.0, 3.0], [5.0, 7.0], [9.0, 11.0]])
    # 25 fps, clip 0.8 s - 8.8 s: the first frame and the middles of the two windows
    assert _stills(20, 200, 25.0, windows) == [20, 50, 150]
    # a clip with one whole window: three evenly spread frames
    assert _stills(20, 50, 25.0, windows) == [20, 44, 69]

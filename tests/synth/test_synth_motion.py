"""Motion model: plausible, deterministic keypoint trajectories and stimulation windows."""

from __future__ import annotations

import numpy as np
import pytest

from freipose.skeleton import load_skeleton
from freipose.synth import RAT_KEYPOINTS, RatBody, StimulationConfig, build_body, simulate_motion
from freipose.synth.motion import simulate_trajectory


@pytest.fixture(scope="module")
def long_motion():
    body = RatBody()
    state = simulate_motion(1500, 50.0, np.random.default_rng(7), body)
    return state, build_body(body, state)


def test_keypoints_match_rat_skeleton_order():
    assert load_skeleton("rat").keypoints == RAT_KEYPOINTS


def test_trajectory_shape_and_determinism():
    a = simulate_trajectory(60, 50.0, 3)
    b = simulate_trajectory(60, 50.0, np.random.default_rng(3))
    c = simulate_trajectory(60, 50.0, 4)
    assert a.shape == (60, 12, 3) and np.all(np.isfinite(a))
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)


def test_nothing_below_the_floor_and_inside_the_arena(long_motion):
    state, geom = long_motion
    assert geom.lowest_z().min() > -1e-6  # every ellipsoid stays above z = 0
    assert geom.keypoints[..., 2].min() > 0
    assert np.abs(geom.keypoints[..., :2]).max() < 300.0  # 600 mm arena


def test_feet_on_floor_when_standing_and_no_sliding(long_motion):
    state, geom = long_motion
    sk = load_skeleton("rat")
    feet = [
        sk.index(n)
        for n in ("Paw Front Right", "Paw Front Left", "Paw Back Right Tip", "Paw Back Left Tip")
    ]
    z = geom.keypoints[:, feet, 2]
    speed = np.linalg.norm(np.diff(geom.keypoints[:, feet, :2], axis=0), axis=-1) * 50.0
    on_floor = z[1:] < 6.0
    not_rearing = state.rear_weight[1:, None] < 0.01
    # most of the time the feet rest on the floor; planted feet do not slide
    assert on_floor[not_rearing[:, 0]].mean() > 0.5
    planted = on_floor & (z[:-1] < 6.0) & not_rearing & (np.abs(np.diff(z, axis=0)) < 1e-9)
    assert planted.sum() > 100
    assert np.median(speed[planted]) < 1e-6


def test_behaviour_repertoire(long_motion):
    state, geom = long_motion
    body_speed = np.linalg.norm(np.diff(state.root_xy, axis=0), axis=1) * 50.0
    assert (body_speed > 60).mean() > 0.1  # walks
    assert (body_speed < 2).mean() > 0.05  # pauses
    assert state.pitch.max() > np.deg2rad(40)  # rears
    assert np.ptp(np.unwrap(state.yaw)) > np.pi  # turns
    assert np.std(np.diff(state.head_yaw)) > 0  # moves its head
    # smooth: no teleporting keypoints (< 2 m/s)
    v = np.linalg.norm(np.diff(geom.keypoints, axis=0), axis=-1) * 50.0
    assert v.max() < 2000.0
    # rigid foot: ankle-to-toe length constant
    foot = np.linalg.norm(geom.keypoints[:, 3] - geom.keypoints[:, 4], axis=-1)
    np.testing.assert_allclose(foot, foot[0], rtol=1e-9)


def test_stimulation_windows_and_effect():
    stim = StimulationConfig(duration_s=1.0, spacing_s=1.5, onset_s=0.5, frequency_hz=10.0)
    assert stim.windows(5.0) == [(0.5, 1.5), (3.0, 4.0)]
    assert StimulationConfig(count=1, onset_s=0, duration_s=1, spacing_s=0).windows(9) == [
        (0.0, 1.0)
    ]
    body = RatBody()
    base = build_body(body, simulate_motion(250, 50.0, np.random.default_rng(1), body))
    stimd = build_body(body, simulate_motion(250, 50.0, np.random.default_rng(1), body, stim))
    paw = RAT_KEYPOINTS.index("Paw Front Right")
    dz = stimd.keypoints[:, paw, 2] - base.keypoints[:, paw, 2]
    t = np.arange(250) / 50.0
    inside = (t >= 0.5) & (t < 1.5)
    assert np.all(np.abs(dz[t < 0.5]) < 1e-9)
    # lifted and oscillating at 10 Hz, growing linearly over the window
    since = t[inside] - 0.5
    expected = since / 1.0 * 12.0 * (0.6 + 0.4 * np.sin(2 * np.pi * 10.0 * since))
    np.testing.assert_allclose(dz[inside], expected, atol=1e-9)
    spec = np.abs(np.fft.rfft(dz[inside] / np.maximum(since, 0.02)))
    freqs = np.fft.rfftfreq(inside.sum(), 1 / 50.0)
    assert abs(freqs[1:][np.argmax(spec[1:])] - 10.0) <= 1.0
    other = RAT_KEYPOINTS.index("Paw Front Left")
    np.testing.assert_allclose(stimd.keypoints[:, other], base.keypoints[:, other])


def test_stimulation_config_errors():
    with pytest.raises(ValueError, match="body_part"):
        StimulationConfig(body_part="Whiskers")
    with pytest.raises(ValueError, match="effect"):
        StimulationConfig(effect="explode")
    with pytest.raises(ValueError, match="key=value"):
        StimulationConfig.parse("duration_s")
    with pytest.raises(ValueError, match="unknown stimulation option"):
        StimulationConfig.parse("duration=3")
    assert StimulationConfig.parse("body_part=Head,effect=lift,duration_s=2").duration_s == 2.0
